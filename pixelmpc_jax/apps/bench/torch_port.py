"""The PixelMPC problem ported to PyTorch, batched, for the pytorch-mppi peer: the quadrotor Euler step,
the DOF network (the same weights), PolarToEuler, the racing cost of Eq. (19) and the pixel cost of
Eq. (18). Each function mirrors its JAX original line for line (``tests/test_bench.py`` checks they agree);
batch first: states (K, n), controls (K, 4).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pixelmpc_jax.control import pixelmpc as pixelmpc_lib


def to_torch(x, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.array(x), dtype=dtype)


# --------------------------------------------------------------------------------------------------
# Robot.
# --------------------------------------------------------------------------------------------------


class QuadTorch:
    """``quadrotor.step`` (Euler, quaternion renormalised) for a batch. Params as floats."""

    def __init__(self, quad_params, dt: float):
        self.mass = float(quad_params.mass)
        self.cd = float(quad_params.drag_coefficient)
        self.g = float(quad_params.gravity)
        self.dt = float(dt)

    def step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:  # (K, 10), (K, 4) -> (K, 10)
        q, v = x[:, 3:7], x[:, 7:10]
        qw, qx, qy, qz = q.unbind(1)
        wx, wy, wz, thrust = u.unbind(1)
        z_axis = torch.stack([2 * (qx * qz + qy * qw), 2 * (qy * qz - qx * qw), 1 - 2 * (qx**2 + qy**2)], 1)
        n2 = (v * v).sum(1, keepdim=True)
        speed = torch.where(n2 > 0, torch.sqrt(torch.where(n2 > 0, n2, torch.ones_like(n2))), torch.zeros_like(n2))
        force = z_axis * thrust[:, None] - self.cd * speed * v
        v_dot = force / self.mass
        v_dot = v_dot - torch.tensor([0.0, 0.0, self.g], dtype=x.dtype)
        q_dot = 0.5 * torch.stack([
            -qx * wx - qy * wy - qz * wz,
            qw * wx - qz * wy + qy * wz,
            qz * wx + qw * wy - qx * wz,
            -qy * wx + qx * wy + qw * wz,
        ], 1)
        x_next = x + self.dt * torch.cat([v, q_dot, v_dot], 1)
        q_next = x_next[:, 3:7]
        qn2 = (q_next * q_next).sum(1, keepdim=True)
        ok = qn2 > 0
        identity = torch.zeros_like(q_next)
        identity[:, 0] = 1.0
        q_next = torch.where(ok, q_next / torch.sqrt(torch.where(ok, qn2, torch.ones_like(qn2))), identity)
        return torch.cat([x_next[:, :3], q_next, x_next[:, 7:]], 1)


# --------------------------------------------------------------------------------------------------
# DOF.
# --------------------------------------------------------------------------------------------------


class DOFTorch:
    """``dof.dof_forward`` / ``dof.pixel_velocity`` with the same weights, batched (K, ...)."""

    def __init__(self, dof_params):
        weights = dof_params.weights
        names = sorted(weights.keys(), key=lambda k: int(k.split("_")[-1]))
        self.kernels = [to_torch(weights[k]["kernel"]) for k in names]
        self.biases = [to_torch(weights[k]["bias"]) for k in names]
        self.input_mean, self.input_std = to_torch(dof_params.input_mean), to_torch(dof_params.input_std)
        self.output_mean, self.output_std = to_torch(dof_params.output_mean), to_torch(dof_params.output_std)

    def forward(self, features: torch.Tensor) -> torch.Tensor:  # (K, 10) -> (K, 2) = (l, theta)
        h = (features - self.input_mean) / self.input_std
        for kernel, bias in zip(self.kernels[:-1], self.biases[:-1]):
            h = torch.relu(h @ kernel + bias)
        out = h @ self.kernels[-1] + self.biases[-1]
        return out * self.output_std + self.output_mean

    def pixel_velocity(self, q, uv, u) -> torch.Tensor:  # (K, 4), (K, 2), (K, 4) -> (K, 2)
        out = self.forward(torch.cat([q, uv, u], 1))
        l, theta = out[:, 0], out[:, 1]
        return torch.stack([l * torch.cos(theta), l * torch.sin(theta)], 1)


# --------------------------------------------------------------------------------------------------
# Costs.
# --------------------------------------------------------------------------------------------------


class RacingCostTorch:
    """``costs.racing_cost`` for a batch of states at one horizon step t (a Python int)."""

    def __init__(self, racing_params, config):
        p = racing_params
        self.path_xyz = to_torch(p.path_xyz)  # (T, 3, L)
        self.path_s = to_torch(p.path_s)  # (T, L)
        self.expected_s = to_torch(p.expected_s)  # (T,)
        self.tangent_xyz = to_torch(p.tangent_xyz)  # (T, 4, L)
        self.centre = to_torch(p.gates.centre)  # (G, 3)
        self.rotation = to_torch(p.gates.rotation)  # (G, 3, 3)
        self.width, self.height = to_torch(p.gates.width), to_torch(p.gates.height)
        self.border, self.depth = to_torch(p.gates.border), to_torch(p.gates.depth)
        self.hall_min, self.hall_max = to_torch(p.hall_min), to_torch(p.hall_max)
        self.target_speed = float(p.target_speed)
        self.config = config
        self.cos_max_tilt = None if config.max_tilt_deg is None else math.cos(math.radians(config.max_tilt_deg))

    def closest(self, p: torch.Tensor, t: int):  # (K, 3) -> distance (K,), attributes (K, 4)
        path, tangents = self.path_xyz[t], self.tangent_xyz[t]
        a = path[:, :-1]
        ab = path[:, 1:] - a  # (3, L-1)
        len2 = torch.clamp((ab * ab).sum(0), min=1e-12)
        r = p[:, :, None] - a[None]  # (K, 3, L-1)
        s_t = torch.clamp((r * ab[None]).sum(1) / len2, 0.0, 1.0)  # (K, L-1)
        e = r - s_t[:, None, :] * ab[None]
        d2 = (e * e).sum(1)
        metric = d2
        if self.config.progress_weight > 0.0:
            path_s = self.path_s[t]
            s = path_s[:-1] + s_t * (path_s[1:] - path_s[:-1])
            metric = d2 + self.config.progress_weight * (s - self.expected_s[t]) ** 2
        select = (metric <= metric.min(1, keepdim=True).values).to(p.dtype)
        select = select / select.sum(1, keepdim=True)
        m = (d2 * select).sum(1)
        attributes = tangents[:, :-1][None] + s_t[:, None, :] * (tangents[:, 1:] - tangents[:, :-1])[None]
        attributes = (attributes * select[:, None, :]).sum(2)  # (K, 4)
        tangent = attributes[:, :3] / torch.clamp(torch.sqrt((attributes[:, :3] ** 2).sum(1, keepdim=True)), min=1e-6)
        return torch.sqrt(m), torch.cat([tangent, attributes[:, 3:]], 1)

    def crashed(self, p: torch.Tensor) -> torch.Tensor:  # (K, 3) -> (K,) bool
        r = self.config.vehicle_radius
        offset = p[:, None, :] - self.centre[None]  # (K, G, 3)
        local = torch.einsum("gji,kgj->kgi", self.rotation, offset)
        slab = local[..., 0].abs() <= torch.clamp(0.5 * self.depth + r, min=self.config.crash_slab_halfwidth)
        outer = (local[..., 1].abs() <= 0.5 * self.width + self.border + r) & (
            local[..., 2].abs() <= 0.5 * self.height + self.border + r)
        opening = (local[..., 1].abs() < 0.5 * self.width - r) & (local[..., 2].abs() < 0.5 * self.height - r)
        frame = (slab & outer & ~opening).any(1)
        ground = p[:, 2] < self.hall_min[2] + r
        wall = (p < self.hall_min + r).any(1) | (p > self.hall_max - r).any(1)
        return frame | ground | wall

    def __call__(self, x: torch.Tensor, t: int) -> torch.Tensor:  # (K, >=10) -> (K,)
        c = self.config
        p, q, v = x[:, :3], x[:, 3:7], x[:, 7:10]
        distance, attributes = self.closest(p, t)
        tangent, cap = attributes[:, :3], attributes[:, 3]
        h = torch.clamp(distance / c.corridor_halfwidth, max=1.0)
        crash = self.crashed(p)
        if self.cos_max_tilt is not None:
            cos_tilt = 1.0 - 2.0 * (q[:, 1] ** 2 + q[:, 2] ** 2)
            crash = crash | (cos_tilt < self.cos_max_tilt)
        h = torch.where(crash, torch.full_like(h, c.crash_value), h)
        yaw = torch.atan2(tangent[:, 1], tangent[:, 0])
        zero = torch.zeros_like(yaw)
        q_d = torch.stack([torch.cos(0.5 * yaw), zero, zero, torch.sin(0.5 * yaw)], 1)
        attitude_error = torch.minimum(((q_d - q) ** 2).sum(1), ((q_d + q) ** 2).sum(1))
        speed = torch.clamp(cap, max=self.target_speed)
        velocity_error = ((speed[:, None] * tangent - v) ** 2).sum(1)
        return c.c1 * h**2 + c.c2 * attitude_error + c.c3 * velocity_error


def pixel_cost_torch(uv: torch.Tensor, config) -> torch.Tensor:
    """``pixelmpc.pixel_cost`` for a batch (K, 2) -> (K,)."""
    centre = torch.tensor(pixelmpc_lib.IMAGE_CENTRE, dtype=uv.dtype)
    error = torch.clamp((uv - centre).abs() - config.pixel_deadzone, min=0.0)
    if config.pixel_error_clip is not None:
        error = torch.clamp(error, max=config.pixel_error_clip)
    return config.c_pixel * config.pixel_cost_scale * error.sum(1)


class PixelMPCTorch:
    """The PixelMPC problem for pytorch-mppi (``step_dependent_dynamics=True``): ``dynamics(X, u, t)`` and
    ``running_cost(X, u, t)`` on (K, 12) states; the DOF runs only for t < n_f, as in the JAX prefix."""

    def __init__(self, problem, quad_params):
        config = problem.config
        self.config = config
        self.n_f = config.pixel_steps
        self.dt = config.mppi.dt
        self.quad = QuadTorch(quad_params, self.dt)
        self.dof = DOFTorch(problem.params.dof)
        self.racing = RacingCostTorch(problem.params.racing, config.racing)
        self.active = float(np.asarray(problem.params.target_active))
        self.target_centre = to_torch(problem.params.target_centre)
        self.target_normal = to_torch(problem.params.target_normal)

    def dynamics(self, X: torch.Tensor, u: torch.Tensor, t: int) -> torch.Tensor:
        x_next = self.quad.step(X[:, :10], u)
        uv = X[:, 10:]
        if t < self.n_f:
            uv = uv + self.dt * self.dof.pixel_velocity(X[:, 3:7], uv, u)
        return torch.cat([x_next, uv], 1)

    def running_cost(self, X: torch.Tensor, u: torch.Tensor, t: int) -> torch.Tensor:
        cost = self.racing(X, t)
        if t < self.n_f:
            ahead = ((X[:, :3] - self.target_centre) @ self.target_normal < 0.0).to(X.dtype)
            cost = cost + self.active * ahead * pixel_cost_torch(X[:, 10:], self.config)
        return cost


def make_pytorch_mppi(problem, quad_params, seed: int = 0):
    """pytorch-mppi's MPPI on the same problem: the same N, T, lambda, sigma (as a diagonal covariance),
    bounds and warm start (hover). Returns ``(mppi, x0)``; ``mppi.command(x0)`` is one step."""
    from pytorch_mppi import MPPI

    torch.manual_seed(seed)
    config = problem.config
    mppi_config = config.mppi
    port = PixelMPCTorch(problem, quad_params)
    sigma = torch.tensor(mppi_config.noise_sigma, dtype=torch.float32)
    hover = torch.tensor([0.0, 0.0, 0.0, float(quad_params.mass * quad_params.gravity)], dtype=torch.float32)
    ctrl = MPPI(port.dynamics, port.running_cost, nx=problem.x0.shape[0], noise_sigma=torch.diag(sigma**2),
                num_samples=mppi_config.num_samples, horizon=mppi_config.horizon, lambda_=mppi_config.temperature,
                u_min=torch.tensor(mppi_config.u_min), u_max=torch.tensor(mppi_config.u_max), u_init=hover,
                U_init=hover.repeat(mppi_config.horizon, 1), step_dependent_dynamics=True)
    return ctrl, to_torch(problem.x0)
