"""How a computation runs: over which devices, compiled with which options, compiled how many times.

The algorithms (``control/mppi.py``, the episode driver, the trainer) say what to compute; this module says where
and how it runs, for every layer:

* :class:`Execution`: how a controller's step runs, not what it computes: over how many devices its samples are
  split (``sample_devices``) and whose kernels run its products on a CPU (``cpu_matmul``).
* :func:`compile_controller`: a pure MPPI controller (:class:`~pixelmpc_jax.control.mppi.Controller`) as an
  :class:`Execution` runs it (:class:`CompiledController`): its step jitted with :func:`compiler_options`, its
  compilations counted (:func:`counted_jit`), its inputs checked and, with ``sample_devices`` > 1, its samples
  split over the local devices (:func:`sample_shardings`) and the rest placed whole on each (:func:`replicate`).
  Each device rolls out and costs its share of the N samples; only the weights' normalisers and the weighted
  update cross devices. The noise is drawn whole from the same key (the partitionable threefry lets each device
  draw just its rows), so the samples, and the plan up to float rounding, are those of one device. On a CPU, the
  host's cores become devices with :func:`pixelmpc_jax.host.split_host_cpu` (before JAX starts): XLA runs one
  device's program on one core but for its largest kernels, and splitting the samples splits all of the step's
  work (the rollout, the DOF's 40 sequential 512 x 128 x 128 products, the costs, the noise).
* :func:`compile_estimator`: a pure estimator (:class:`~pixelmpc_jax.perception.estimator.Estimator`) compiled
  (:class:`CompiledEstimator`): its ``init``, ``step`` and ``align`` jitted, the step's inputs checked before the call
  and its compilations counted.
* :func:`compiled`: any other library function compiled where it runs at the top level (a rendered frame, its exact
  flow, a course's desired path): the library layers call no ``jax.jit`` themselves, their callers compile here,
  one jitted function per library function and set of static arguments.
* :func:`compiler_options`: on one CPU device, the products go to YNNPACK (``Execution.cpu_matmul``).
* :func:`shard_batch`, :func:`gather_batch`: batches of episodes over every device, across processes too;
  :func:`batch_shardings`: a training batch's rows over the devices.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

SAMPLE_AXIS = "samples"
BATCH_AXIS = "batch"
CPU_MATMULS = ("auto", "xla", "ynnpack")  # Execution.cpu_matmul
YNNPACK_MATMULS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_DOT"}
# "auto" on one CPU device: YNNPACK's kernels for a step whose largest matrix product is smaller than this many
# multiply-adds, XLA's own from it up. PixelMPC's step (its DOF's products of N x 128 x 128), T = 80, on a 2-core AMD
# EPYC, both cores, idle, median ms with XLA's kernels against YNNPACK's, interleaved (2026-12-03): N = 512 21.0 /
# 15.4 (YNNPACK 1.36x faster), 1024 28.2 / 27.7 and 27.5 / 27.6 (equal), 1536 46.3 / 44.1 (1.05x), 2048 53.1 / 55.8
# (XLA's 1.05x faster). A unicycle's largest product (the weighted update, N x 100) gains 1.5x from YNNPACK at 512
# and 2048 alike.
AUTO_XLA_FROM_MACS = 2048 * 128 * 128


# --------------------------------------------------------------------------------------------------
# How one controller's step runs.
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Execution:
    """How a controller's step runs, not what it computes (the same samples and plan, up to float rounding).

    Attributes:
        sample_devices: split each step's N samples over this many local devices (1: one device, the default). The
            samples are the same (drawn whole from the same key) and so is the plan, up to float rounding; each
            device rolls out N / sample_devices of them. N must split evenly. On a CPU the cores become devices
            only if asked before JAX starts (:func:`~pixelmpc_jax.host.split_host_cpu`).
        cpu_matmul: whose kernels run the step's products on a CPU: "auto", "xla" or "ynnpack"
            (:func:`compiler_options`); the same products either way.
        checked: raise where the step's input could not be flown (``info.input_rejected``: a NaN in the state or
            the params, a zero quaternion, ...), a ValueError naming each failed check
            (``Controller.check(..., values=True)``), instead of returning the fallback command with the flag set.
            It reads the flag back after every step (the step's result is waited for, as a control loop does
            anyway); the numbers are checked on the host only when the flag is set. Measured: 1.96 against 1.90 ms a
            step (a unicycle at 512 x 50, one core of a 2-core AMD EPYC), where ``jax.experimental.checkify`` would
            add a check to every op.
    """

    sample_devices: int = 1
    cpu_matmul: str = "auto"
    checked: bool = False

    def __post_init__(self):
        devices = self.sample_devices
        if not isinstance(devices, (int, np.integer)) or isinstance(devices, bool) or devices <= 0:
            raise ValueError(f"Execution.sample_devices must be a positive integer, got {devices!r}")
        if self.cpu_matmul not in CPU_MATMULS:
            raise ValueError(f"Execution.cpu_matmul must be one of {CPU_MATMULS}, got {self.cpu_matmul!r}")
        if not isinstance(self.checked, bool):
            raise ValueError(f"Execution.checked must be True or False, got {self.checked!r}")


class SampleShardings(NamedTuple):
    """Where one MPPI step's arrays live when its samples are split over devices.

    Attributes:
        samples: the leading (sample) axis split over the devices, the rest whole.
        replicated: a whole copy on every device (the plan, x0, the params, the key).
    """

    samples: NamedSharding
    replicated: NamedSharding


def sample_shardings(num_devices: int, num_samples: int) -> SampleShardings:
    """The shardings of a step whose ``num_samples`` samples are split over the first ``num_devices`` local
    devices (of the default backend). A ValueError if fewer are present or the samples do not split evenly."""
    devices = jax.local_devices()
    if num_devices > len(devices):
        raise ValueError(f"sample_devices={num_devices} but only {len(devices)} {devices[0].platform} device(s) are "
                         f"present (on a CPU, split the host's cores into devices before JAX starts: "
                         f"pixelmpc_jax.host.split_host_cpu, or the `pixelmpc` command does it)")
    if num_samples % num_devices:
        raise ValueError(f"num_samples={num_samples} does not split evenly over sample_devices={num_devices}")
    mesh = Mesh(np.asarray(devices[:num_devices]), (SAMPLE_AXIS,))
    return SampleShardings(NamedSharding(mesh, PartitionSpec(SAMPLE_AXIS)), NamedSharding(mesh, PartitionSpec()))


def usable_sample_devices(num_samples: int) -> int:
    """The most local devices, at most all of them, over which ``num_samples`` samples split evenly (1 with one
    device): what to give ``Execution.sample_devices`` to use every device for one controller."""
    count = len(jax.local_devices())
    return next(k for k in range(count, 0, -1) if num_samples % k == 0)


def replicate(tree, shardings: SampleShardings | None):
    """``tree`` with a whole copy on every device of ``shardings`` (unless every leaf is there already); as it
    is with ``shardings`` None (one device)."""
    if shardings is None or all(getattr(leaf, "sharding", None) == shardings.replicated
                                for leaf in jax.tree_util.tree_leaves(tree)):
        return tree
    return jax.device_put(tree, shardings.replicated)


# --------------------------------------------------------------------------------------------------
# Compiling.
# --------------------------------------------------------------------------------------------------


def compiler_options(cpu_matmul: str, sample_devices: int, largest_product: int | None = None) -> dict | None:
    """The XLA options a step is compiled with (``jax.jit(..., compiler_options=...)``), for
    ``Execution.cpu_matmul``: "ynnpack" hands the products and the bias and ReLU after them to YNNPACK, which
    splits even a 512 x 128 x 128 product over a CPU's cores (XLA's own kernel runs it on one); "xla" keeps
    XLA's; "auto" (the default) takes YNNPACK for a step on one CPU device and XLA's where the samples are
    split over devices already (each core then has its own share) or where the step's ``largest_product``
    (multiply-adds, :func:`largest_product`; None: not known yet) reaches :data:`AUTO_XLA_FROM_MACS`, where XLA's
    own kernels were measured as fast or faster. Other platforms ignore the option."""
    if cpu_matmul not in CPU_MATMULS:
        raise ValueError(f"cpu_matmul must be one of {CPU_MATMULS}, got {cpu_matmul!r}")
    if cpu_matmul == "xla" or (cpu_matmul == "auto" and (sample_devices > 1 or jax.default_backend() != "cpu")):
        return None
    if cpu_matmul == "auto" and largest_product is not None and largest_product >= AUTO_XLA_FROM_MACS:
        return None
    return dict(YNNPACK_MATMULS)


def largest_product(closed_jaxpr) -> int:
    """The multiply-adds of the largest matrix product (``dot_general``) in a traced program
    (``jax.make_jaxpr(fn)(*args)``), its loops' and branches' bodies included (a product inside a ``lax.scan``
    counts once per iteration, as one kernel call); 0 if it has none."""
    from jax.extend.core import jaxprs_in_params

    def walk(jaxpr) -> int:
        best = 0
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                (_, rhs_contract), (_, rhs_batch) = eqn.params["dimension_numbers"]
                lhs, rhs = (v.aval.shape for v in eqn.invars)
                free = [d for i, d in enumerate(rhs) if i not in rhs_contract and i not in rhs_batch]
                best = max(best, int(np.prod(lhs, dtype=np.int64)) * int(np.prod(free, dtype=np.int64)))
            best = max([best, *(walk(sub) for sub in jaxprs_in_params(eqn.params))])
        return best

    return walk(closed_jaxpr.jaxpr)


def counted_jit(fn: Callable, options: dict | None = None) -> tuple[Callable, Callable[[], int]]:
    """``fn`` jitted with the XLA ``options``, and ``num_compilations() -> int``: how many times it has been
    traced so far. JAX traces it once per new input signature (shapes, dtypes, static structure), right before
    compiling that version; a control loop must keep the count at 1."""
    traces = [0]

    def traced(*args):
        traces[0] += 1  # Python runs here only while JAX traces: once per new input signature, before compiling
        return fn(*args)

    return jax.jit(traced, compiler_options=options), lambda: traces[0]


@functools.cache
def compiled(fn: Callable, static_argnames: str | tuple[str, ...] = ()) -> Callable:
    """The library function ``fn`` compiled as one program (``jax.jit`` with ``static_argnames``), the same jitted
    function for the same ``fn`` and ``static_argnames`` on every call in the process.

    The library layers (``dynamics/``, ``world/``, ``perception/``, ``control/``) write pure functions and call no
    ``jax.jit`` (tests/test_layers.py); who runs one of them at the top level, on the host, compiles it here: a
    command rendering frames (``compiled(render.render_batch, ("supersample", "chunk"))``), a course built from its
    file (its desired path, :func:`pixelmpc_jax.world.course.load_course`). Being the same function each time, it
    compiles once per new input signature (shapes, dtypes, static values) and never again for the same one, however
    many times it is asked for (``fn`` is a module's function: a lambda made anew for each call would compile anew);
    inside a larger jit it is traced inline, as ``fn`` itself would be."""
    return jax.jit(fn, static_argnames=static_argnames)


class CompiledController(NamedTuple):
    """A pure controller as an :class:`Execution` runs it (:func:`compile_controller`).

    Attributes:
        init: ``init(key, u_init) -> state``, the state on every device of the sample split.
        step: ``step(state, x0, params) -> (u0, state, info)``: one compiled call, its inputs checked
            (``Controller.check``, outside jit) and placed on every device of the split before it; with
            ``Execution.checked`` a ValueError where ``info.input_rejected`` is set.
        placed: the pure controller with its samples split and its state placed (``placed.init`` is ``init``), to
            compose inside a larger ``jax.jit`` compiled with ``compiler_options`` (a closed-loop episode).
        num_compilations: ``() -> int``, how many times ``step`` has been traced: JAX traces it once per new input
            signature (shapes, dtypes, static structure), right before compiling that version; a control loop
            must keep it at 1.
        shardings: with ``sample_devices`` > 1, where the step's samples and its other inputs live (put params
            there once with ``jax.device_put(params, shardings.replicated)`` to save a copy per call); else None.
        compiler_options: the XLA options for ``placed.step`` before a step is seen (:func:`compiler_options`
            with the largest product unknown); a larger jitted function that composes ``placed.step`` (a
            closed-loop episode) passes them to its own ``jax.jit``.
        step_options: ``() -> dict | None``, the options ``step`` was compiled with, chosen at its first call:
            with ``cpu_matmul="auto"`` the traced step's largest product decides (:func:`largest_product`); a
            ValueError before the first call.
    """

    init: Callable
    step: Callable
    placed: Any
    num_compilations: Callable[[], int]
    shardings: SampleShardings | None
    compiler_options: dict | None
    step_options: Callable[[], dict | None]


def compile_controller(ctrl, execution: Execution = Execution()) -> CompiledController:
    """The pure controller ``ctrl`` (:class:`~pixelmpc_jax.control.mppi.Controller`) jitted, checked and placed as
    ``execution`` says. With ``sample_devices`` > 1 each step's white noise is constrained to the split over the
    devices where it is drawn (``Controller.with_sample_placement``: the same samples) and the state and inputs
    are placed whole on every device; a ValueError if those devices are not present or the samples do not split
    evenly over them.

    The step is jitted at its first call: with ``cpu_matmul="auto"`` on one CPU device its traced program's largest
    product picks the kernels (:func:`compiler_options`; a trace more at that call, no compile more).

    A plain ``jax.jit(ctrl.step)`` computes the same step without :func:`compiler_options` (XLA's default CPU
    kernels), without the input checks and without the compile count; where "auto" keeps XLA's kernels (PixelMPC's
    DOF at 2048 samples or more) it compiles the same program. What the options buy depends on the problem:
    a unicycle on one core of a 2-core AMD EPYC, 1.72 (plain) against 1.41 ms at 512 x 50 and 8.40 against 6.17 ms
    at 2048 x 50; PixelMPC on both cores, idle, in one ``pixelmpc bench suite --quick`` (2026-12-03), 24.3 against
    18.4 ms at 512 x 80 (YNNPACK's kernels) and 53.1 against 53.0 ms at 2048 x 80 (XLA's: the same program).
    ``pixelmpc bench`` times the two in one run (``apps/bench/jit_paths.py``) and says which is the faster."""
    placed, shardings = ctrl, None
    if execution.sample_devices > 1:
        shardings = sample_shardings(execution.sample_devices, ctrl.config.num_samples)
        split = ctrl.with_sample_placement(lambda white: jax.lax.with_sharding_constraint(white, shardings.samples))
        placed = split._replace(init=lambda key, u_init: replicate(split.init(key, u_init), shardings))
    options = compiler_options(execution.cpu_matmul, execution.sample_devices)
    compiled: dict = {}  # the step's jit, made at its first call: "auto" reads the traced step's largest product

    def step(state, x0, params):
        state, x0, params = ctrl.check(state, x0, params)
        args = replicate((state, x0, params), shardings)
        if not compiled:
            chosen = options
            if execution.cpu_matmul == "auto" and options is not None:
                chosen = compiler_options("auto", execution.sample_devices,
                                          largest_product(jax.make_jaxpr(placed.step)(*args)))
            compiled["jit"], compiled["count"] = counted_jit(placed.step, chosen)
            compiled["options"] = chosen
        out = compiled["jit"](*args)
        if execution.checked and bool(out[2].input_rejected):
            ctrl.check(state, x0, params, values=True)  # raises, naming each failed check
            raise ValueError("the step's input was rejected (info.input_rejected)")
        return out

    def step_options():
        if not compiled:
            raise ValueError("the step has not been called yet: its options are chosen at its first call")
        return compiled["options"]

    return CompiledController(init=placed.init, step=step, placed=placed,
                              num_compilations=lambda: compiled["count"]() if compiled else 0,
                              shardings=shardings, compiler_options=options, step_options=step_options)


class CompiledEstimator(NamedTuple):
    """A pure estimator compiled (:func:`compile_estimator`).

    Attributes:
        init: ``init(key, x0) -> state``, jitted.
        step: ``step(state, imu, detection, params) -> (estimate, state, info)``: one compiled call, its inputs checked
            before it (``Estimator.check``, outside jit: a ValueError naming the expected shape).
        align: ``align(state, accel_mean, gyro_mean) -> state``, jitted, or None where the estimator has none.
        pure: the estimator itself, to compose inside a larger ``jax.jit`` (a closed-loop episode) or ``jax.vmap``.
        num_compilations: ``() -> int``, how many times ``step`` has been traced (once per new input signature).
    """

    init: Callable
    step: Callable
    align: Callable | None
    pure: Any
    num_compilations: Callable[[], int]


def compile_estimator(est) -> CompiledEstimator:
    """The pure estimator ``est`` (:class:`~pixelmpc_jax.perception.estimator.Estimator`) jitted, its step's inputs
    checked outside jit (``est.check``) and its step's compilations counted (:func:`counted_jit`)."""
    step_jit, num_compilations = counted_jit(est.step)

    def step(state, imu, detection, params):
        return step_jit(*est.check(state, imu, detection, params))

    align = None if est.align is None else jax.jit(est.align)
    return CompiledEstimator(init=jax.jit(est.init), step=step, align=align, pure=est,
                             num_compilations=num_compilations)


# --------------------------------------------------------------------------------------------------
# Batches of episodes or training rows over every device.
# --------------------------------------------------------------------------------------------------


class BatchShardings(NamedTuple):
    """Where a data-parallel step's arrays live (training).

    Attributes:
        rows: the leading (batch) axis split over the devices, the rest whole.
        replicated: a whole copy on every device (the weights, the optimizer state, the dataset).
    """

    rows: NamedSharding
    replicated: NamedSharding


def batch_shardings(num_devices: int) -> BatchShardings:
    """The shardings of a batch split over the first ``num_devices`` JAX devices (of every process)."""
    mesh = Mesh(np.asarray(jax.devices()[:num_devices]), (BATCH_AXIS,))
    return BatchShardings(NamedSharding(mesh, PartitionSpec(BATCH_AXIS)), NamedSharding(mesh, PartitionSpec()))


def shard_batch(tree, devices=None):
    """Place a batch (leading axis B on every leaf) across ``devices`` (default: all JAX devices, of every
    process) with a 1-D ``Mesh`` and ``NamedSharding``, padding B to a multiple of the device count by
    repeating the last element. Returns ``(sharded tree, B)``; with one device the tree is returned as it is.

    With several processes (``jax.distributed``), every process holds the whole batch (the laps are built
    from seeds, the same everywhere) and places the rows of its own devices."""
    devices = list(devices if devices is not None else jax.devices())
    size = jax.tree_util.tree_leaves(tree)[0].shape[0]
    if len(devices) <= 1:
        return tree, size
    padded = -(-size // len(devices)) * len(devices)
    if padded != size:
        tree = jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], padded - size, axis=0)]), tree)
    sharding = NamedSharding(Mesh(np.asarray(devices), (BATCH_AXIS,)), PartitionSpec(BATCH_AXIS))
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding), size

    def place(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(place, tree), size


def gather_batch(tree):
    """Bring a batch computed over the devices of several processes back whole to every process (with one
    process it is returned as it is)."""
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)
