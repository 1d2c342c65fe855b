"""The runtime harness: bench.json schema on a tiny run, the flop counter on hand cases, the torch port of the
PixelMPC problem against the JAX functions, and the diff-drive problem's cost-map lookup."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pixelmpc_jax.apps.bench import peers, problems, roofline, suite
from pixelmpc_jax.apps.bench.table1 import SpyNet, spynet_flops_per_image
from pixelmpc_jax.control import costs
from pixelmpc_jax.control import pixelmpc as PM
from pixelmpc_jax.dynamics import dof
from pixelmpc_jax.dynamics import quadrotor as Q

# --------------------------------------------------------------------------------------------------
# The flop counter.
# --------------------------------------------------------------------------------------------------


def test_dof_flops_hand_case():
    # 10-128-128-128-2: MACs 1280 + 16384 + 16384 + 256 = 34,304 -> 68,608 flops; biases 386 + ReLUs 384
    assert roofline.dof_flops_per_eval() == {"matmul": 68_608, "elementwise": 770}
    # a 2-3-1 network: 2 x (6 + 3) = 18 matmul flops; biases 3 + 1, ReLUs 3
    assert roofline.dof_flops_per_eval((2, 3, 1)) == {"matmul": 18, "elementwise": 7}
    # the counted products are the shipped network's weights less its biases, two flops each
    leaves = jax.tree_util.tree_leaves(dof.load_packaged_dof().weights)
    weights = sum(int(np.prod(leaf.shape)) for leaf in leaves if leaf.ndim == 2)
    biases = sum(int(np.prod(leaf.shape)) for leaf in leaves if leaf.ndim == 1)
    assert roofline.dof_flops_per_eval()["matmul"] == 2 * weights and weights + biases == 34_690


def test_step_flops_hand_case():
    per = {"dynamics": 10.0, "racing": 100.0, "pixel": 5.0}
    f = roofline.step_flops(num_samples=2, horizon=3, pixel_steps=1, per_step=per, control_dim=4,
                            layer_sizes=(2, 3, 1))
    assert f["dof_matmul"] == 2 * 1 * 18
    assert f["dof_elementwise"] == 2 * 1 * 7
    assert f["dynamics"] == 2 * 3 * 10
    assert f["racing"] == 2 * 3 * 100
    assert f["pixel"] == 2 * 1 * 5
    assert f["mppi"] == 2 * 3 * 4 * roofline.MPPI_FLOPS_PER_SAMPLE_STEP
    assert f["total"] == 36 + 14 + 60 + 600 + 10 + 2 * 3 * 4 * roofline.MPPI_FLOPS_PER_SAMPLE_STEP


def test_spynet_has_the_papers_parameter_count():
    variables = jax.eval_shape(SpyNet().init, jax.random.PRNGKey(0), jnp.zeros((1, 32, 32, 3)),
                               jnp.zeros((1, 32, 32, 3)))
    assert sum(int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(variables)) == 1_200_250
    # per pixel 49 x (8*32 + 32*64 + 64*32 + 32*16 + 16*2) MACs over a 2x2 .. 32x32 pyramid
    assert spynet_flops_per_image((32, 32)) == 2 * 49 * 4896 * (1024 + 256 + 64 + 16 + 4)


# --------------------------------------------------------------------------------------------------
# The diff-drive problem.
# --------------------------------------------------------------------------------------------------

MAP = jnp.asarray([[0.0, 1.0], [2.0, 3.0]])  # map[row, col]: value at the centre (col + 0.5, row + 0.5)
ORIGIN = jnp.zeros(2)


@pytest.mark.parametrize("xy, expected", [
    ((0.5, 0.5), 0.0),  # the centre of cell (0, 0)
    ((1.5, 0.5), 1.0),  # the centre of cell col 1, row 0
    ((1.0, 0.5), 0.5),  # half-way between the two cells of row 0
    ((1.0, 1.0), 1.5),  # the mean of all four
    ((0.5, 1.25), 1.5),  # 0.75 of the way from row 0 (value 0) to row 1 (value 2)
    ((-3.0, -3.0), 0.0),  # outside: clamped to the corner cell
    ((9.0, 9.0), 3.0),
])
def test_costmap_bilinear_hand_cases(xy, expected):
    value = problems.costmap_lookup(MAP, jnp.asarray(xy), ORIGIN, 1.0, "bilinear")
    np.testing.assert_allclose(value, expected, atol=1e-6)


@pytest.mark.parametrize("xy, expected", [((0.2, 0.3), 0.0), ((1.2, 0.3), 1.0), ((0.9, 1.7), 2.0),
                                          ((1.99, 1.01), 3.0), ((5.0, -1.0), 1.0)])
def test_costmap_nearest_hand_cases(xy, expected):
    value = problems.costmap_lookup(MAP, jnp.asarray(xy), ORIGIN, 1.0, "nearest")
    assert float(value) == expected


def test_costmap_resolution_and_origin():
    origin = jnp.asarray([10.0, -2.0])
    # cell (col 1, row 0) centre at origin + (1.5, 0.5) * 0.05
    xy = origin + jnp.asarray([1.5, 0.5]) * 0.05
    np.testing.assert_allclose(problems.costmap_lookup(MAP, xy, origin, 0.05), 1.0, atol=1e-5)


def test_diff_drive_step_hand_case():
    x = jnp.asarray([1.0, 2.0, jnp.pi / 2])
    np.testing.assert_allclose(problems.diff_drive_step(x, jnp.asarray([1.0, 0.5]), 0.02),
                               [1.0, 2.02, jnp.pi / 2 + 0.01], atol=1e-6)


# --------------------------------------------------------------------------------------------------
# The torch port equals the JAX functions.
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def port_setup():
    pytest.importorskip("torch")
    from pixelmpc_jax.apps.bench import torch_port

    problem = problems.pixelmpc_problem(16, 80, 1.0)
    port = torch_port.PixelMPCTorch(problem, Q.QuadParams())
    K = 48
    key_x, key_u, key_q = jax.random.split(jax.random.PRNGKey(5), 3)
    # states around the start pose: most fly, some crash (tilt, floor), so every branch of the cost is used
    X = jnp.broadcast_to(problem.x0, (K, 12)) + jnp.concatenate(
        [0.5 * jax.random.normal(key_x, (K, 3)), 0.3 * jax.random.normal(key_q, (K, 4)),
         2.0 * jax.random.normal(key_u, (K, 3)), 0.2 * jax.random.normal(key_x, (K, 2))], axis=1)
    X = X.at[:, 3:7].set(Q.normalize_quat(X[:, 3:7]))
    U = Q.hover_control(Q.QuadParams()) + jax.random.normal(key_u, (K, 4)) * jnp.asarray([0.2, 0.2, 0.3, 2.2])
    return torch_port, problem, port, X, U


def test_torch_quadrotor_step_equals_jax(port_setup):
    torch_port, problem, port, X, U = port_setup
    expected = jax.vmap(lambda x, u: Q.step(x[:10], u, 0.025, Q.QuadParams()))(X, U)
    got = port.quad.step(torch_port.to_torch(X[:, :10]), torch_port.to_torch(U)).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)


def test_torch_dof_equals_jax(port_setup):
    torch_port, problem, port, X, U = port_setup
    expected = jax.vmap(lambda x, u: dof.pixel_velocity(problem.params.dof, x[3:7], x[10:], u))(X, U)
    got = port.dof.pixel_velocity(*(torch_port.to_torch(a) for a in (X[:, 3:7], X[:, 10:], U))).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("t", [0, 17, 79])
def test_torch_racing_and_pixel_cost_equal_jax(port_setup, t):
    torch_port, problem, port, X, U = port_setup
    config = problem.config
    racing = costs.racing_costs(X[None], jnp.full((1,), t), problem.params.racing, config.racing)[0]
    got = port.racing(torch_port.to_torch(X), t).numpy()
    assert np.any(np.asarray(racing) < 1e5) and np.any(np.asarray(racing) > 1e8)  # flying and crashed states
    np.testing.assert_allclose(got, racing, rtol=1e-5, atol=1e-3)
    pixel = jax.vmap(lambda x: PM.pixel_cost(x[10:], config))(X)
    np.testing.assert_allclose(torch_port.pixel_cost_torch(torch_port.to_torch(X[:, 10:]), config).numpy(), pixel,
                               rtol=1e-5)


def test_torch_rollout_cost_equals_jax(port_setup):
    """A whole rollout (dynamics over t_f with the DOF, then the robot alone) and its summed cost."""
    torch_port, problem, port, X, U = port_setup
    import torch

    from pixelmpc_jax.control.rollout import Prefix, rollout_cost

    config, n_f, dt = problem.config, problem.config.pixel_steps, problem.config.mppi.dt
    controls = Q.hover_control(Q.QuadParams()) + 0.3 * jax.random.normal(jax.random.PRNGKey(9), (4, 80, 4))

    def robot(X, u, p):
        return jnp.concatenate([Q.step(X[:10], u, dt, Q.QuadParams()), X[10:]])

    def prefix_dyn(X, u, p):
        uv = X[10:] + dt * dof.pixel_velocity(p.dof, X[3:7], X[10:], u)
        return jnp.concatenate([Q.step(X[:10], u, dt, Q.QuadParams()), uv])

    def racing(X, u, t, p):  # one state: the racing cost of a batch of one
        return costs.racing_costs(X[None, None], jnp.reshape(t, (1,)), p.racing, config.racing)[0, 0]

    def prefix_cost(X, u, t, p):
        return racing(X, u, t, p) + PM.pixel_cost(X[10:], config)

    prefix = Prefix(n_f, prefix_dyn, prefix_cost)
    expected = jax.vmap(lambda c: rollout_cost(robot, racing, None, problem.x0, c, problem.params, prefix))(controls)
    state = torch_port.to_torch(problem.x0)[None].repeat(4, 1)
    total = torch.zeros(4)
    for t in range(80):
        u = torch_port.to_torch(controls[:, t])
        state = port.dynamics(state, u, t)
        total = total + port.running_cost(state, u, t)
    np.testing.assert_allclose(total.numpy(), expected, rtol=1e-4)


# --------------------------------------------------------------------------------------------------
# bench.json on a tiny run.
# --------------------------------------------------------------------------------------------------


RECORDED_ROWS = Path(__file__).resolve().parent / "data" / "bench_smoke_rows.json"


def _run_smoke(out) -> tuple:
    """A smoke run of the harness into ``out``: (folder, result, bench.json, printed output)."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        result = suite.run_bench(out, smoke=True)
    return out, result, json.loads((out / "bench.json").read_text()), printed.getvalue()


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    """One smoke run of the harness, every part measured at tiny sizes (about a minute of compilation), shared by
    the slow tests below."""
    return _run_smoke(tmp_path_factory.mktemp("bench"))


@pytest.fixture
def recorded_smoke_run(tmp_path, monkeypatch):
    """The harness's assembly on the rows of a recorded smoke run: every part that measures is replaced by the
    rows it gave (tests/data/bench_smoke_rows.json), so bench.json, bench.md, the summary and the plot are built
    and written without compiling anything. The smoke run itself is the slow test below."""
    rows = json.loads(RECORDED_ROWS.read_text())

    def part(*groups):
        return lambda *args, **kwargs: [dict(r) for r in rows if r["group"] in groups]

    from pixelmpc_jax.apps.bench import closed_loop, controller, eskf_step, jit_paths, particle_filter_step, table1

    monkeypatch.setattr(controller, "paper_size_rows", part("controller", "roofline"))
    monkeypatch.setattr(particle_filter_step, "pf_rows", lambda particles, repeats: [
        r for r in part("estimator")() if r["name"].startswith("particle filter")])
    monkeypatch.setattr(eskf_step, "eskf_rows", lambda repeats: [
        r for r in part("estimator")() if "Kalman" in r["name"]])
    monkeypatch.setattr(closed_loop, "loop_rows", part("loop"))
    monkeypatch.setattr(peers, "pytorch_mppi_rows", part("peer"))
    monkeypatch.setattr(peers, "mppi_generic_rows", part("mppi_generic"))
    monkeypatch.setattr(table1, "table1_rows", part("table1"))
    monkeypatch.setattr(controller, "scaling_rows", part("scaling"))
    monkeypatch.setattr(jit_paths, "jit_path_rows", part("jit_paths"))
    return _run_smoke(tmp_path)


def _assert_the_schema(run, peers_measured: bool) -> None:
    tmp_path, result, written, printed = run
    assert (tmp_path / "bench.md").read_text().startswith("# pixelmpc-jax runtime benchmarks")
    assert (tmp_path / "scaling.png").stat().st_size > 0
    assert written["mode"] == "smoke" and len(written["rows"]) == len(result["rows"])
    for key in ("platform", "device_kind", "cpu_model", "cpu_count"):
        assert key in written["device"]
    for key in ("jax", "jaxlib", "torch", "pytorch_mppi"):
        assert key in written["versions"]
    groups = {r["group"] for r in written["rows"]}
    assert {"controller", "roofline", "estimator", "loop", "peer", "mppi_generic", "table1", "scaling"} <= groups
    estimator_rows = [r for r in written["rows"] if r["group"] == "estimator"]
    pf_rows = [r for r in estimator_rows if r["name"].startswith("particle filter")]
    assert all(r["median_ms"] > 0 and r["num_samples"] == 256 for r in pf_rows) and len(pf_rows) == 2
    (eskf_row,) = [r for r in estimator_rows if "Kalman" in r["name"]]
    assert eskf_row["median_ms"] > 0 and eskf_row["repeats"] == 20 and eskf_row["target_ms"] == 1.0
    assert written["summary"]["eskf_tick_median_ms"] == eskf_row["median_ms"]
    for row in written["rows"]:
        for field in suite.REQUIRED_ROW_FIELDS:
            assert field in row, (row["name"], field)
        if row["status"] == "ok":
            assert 0 < row["median_ms"] <= row["max_ms"] and row["mean_ms"] > 0 and row["two_sigma_ms"] >= 0
            assert row["min_ms"] <= row["median_ms"] <= row["p95_ms"] <= row["max_ms"]
    peer_rows = [r for r in written["rows"] if r["group"] == "peer"]
    if peers_measured and written["versions"]["torch"] is not None:
        assert all(r["ratio"] > 0 for r in peer_rows)
    elif peers_measured:  # without the bench extra the peer is skipped, and says so
        assert peer_rows and all(r["status"] == peers.TORCH_MISSING for r in peer_rows)
        assert f"pytorch-mppi peer {peers.TORCH_MISSING}" in printed
    assert written["rows"][0]["num_samples"] == 16 and written["rows"][0]["horizon"] == 8
    assert set(written["summary"]["targets"]) == {
        "pixelmpc_step_ms <= 12", "pixelmpc_step_p95_ms <= 25", "nominal_step_ms <= 5",
        "ratio_vs_pytorch_mppi <= 0.1 (N=512), 0.15 (N=2048)", "step_2048_over_512 <= 4.5",
        "step_8192_over_512 <= 16 (linear)", "dof_fraction >= 0.70", "loop_tick_ms <= 25",
        "vdof_over_dof_step <= 1.10", "eskf_tick_ms <= 1", "eskf_loop_over_truth <= 1.10",
        "documented compile path <= plain jax.jit (N=512, 2048; T=80)"}


def test_the_harness_writes_the_schema_from_its_parts_rows(recorded_smoke_run):
    _assert_the_schema(recorded_smoke_run, peers_measured=False)
    tmp_path, result, written, _ = recorded_smoke_run
    assert [r["name"] for r in written["rows"]] == [r["name"] for r in json.loads(RECORDED_ROWS.read_text())]
    summary = written["summary"]
    loop = {r["controller"]: r for r in written["rows"] if r["group"] == "loop" and r["estimator"] == "truth"}
    assert summary["loop_tick_median_ms"] == loop["pixelmpc"]["median_ms"]
    assert summary["nominal_loop_tick_median_ms"] == loop["mppi"]["median_ms"]
    md = (tmp_path / "bench.md").read_text()
    assert "## Closed loop: the tick of a lap (target 25 ms median" in md
    assert md.count("| closed-loop tick: ") == 3


@pytest.mark.slow  # about a minute of compilation; the recorded rows above cover the assembly
def test_smoke_run_writes_the_schema(smoke_run):
    _assert_the_schema(smoke_run, peers_measured=True)


def test_scaling_growth_reads_the_default_rollout_at_t_80():
    def row(n, ms, horizon=80, rollout="batched"):
        return {"group": "scaling", "num_samples": n, "horizon": horizon, "rollout": rollout, "median_ms": ms}

    rows = [row(512, 10.0), row(2048, 36.0), row(8192, 150.0), row(8192, 900.0, rollout="per_step"),
            row(512, 1.0, horizon=20), {"group": "peer", "num_samples": 8192, "horizon": 80, "median_ms": 1.0}]
    assert suite._scaling_growth(rows) == pytest.approx(3.6)
    assert suite._scaling_growth(rows, large=8192) == pytest.approx(15.0)
    assert suite._scaling_growth(rows[1:], large=8192) is None  # no 512 row


@pytest.mark.slow  # the smoke run's closed-loop rows; the recorded rows above cover their summary
def test_smoke_run_has_the_closed_loop_rows(smoke_run):
    tmp_path, _, written, _ = smoke_run
    rows = {(r["controller"], r["estimator"]): r for r in written["rows"] if r["group"] == "loop"}
    assert set(rows) == {("pixelmpc", "truth"), ("mppi", "truth"), ("pixelmpc", "eskf")}
    loop = {controller: row for (controller, estimator), row in rows.items() if estimator == "truth"}
    for row in rows.values():
        # the smoke lap: N=16, T=8, 0.25 s = 10 ticks from the start, which ends as a timeout
        assert row["status"] == "ok" and row["runner"] == "single" and row["repeats"] == 2
        assert (row["num_samples"], row["horizon"], row["ticks"], row["end_cause"]) == (16, 8, 10, "timeout")
        assert np.isfinite(row["median_ms"]) and np.isfinite(row["p95_ms"]) and row["median_ms"] > 0
        assert row["sim_s"] == pytest.approx(10 * 0.025)
        # per-tick time = lap wall time / ticks flown, and the real-time factor = simulated / wall seconds
        assert row["median_ms"] == pytest.approx(1e3 * row["lap_wall_s"] / row["ticks"])
        assert row["real_time_factor"] == pytest.approx(row["sim_s"] / row["lap_wall_s"])
        assert row["compile_s"] > 0 and row["target_ms"] == 25.0
        assert row["meets_target"] == (row["median_ms"] <= 25.0)
    summary = written["summary"]
    assert summary["loop_tick_median_ms"] == loop["pixelmpc"]["median_ms"]
    assert summary["nominal_loop_tick_median_ms"] == loop["mppi"]["median_ms"]
    assert summary["targets"]["loop_tick_ms <= 25"] == suite.NOT_MEASURED  # not at the paper's size
    eskf = rows[("pixelmpc", "eskf")]
    assert "on the eskf estimate" in eskf["name"]
    assert summary["eskf_loop_over_truth"] == pytest.approx(eskf["median_ms"] / loop["pixelmpc"]["median_ms"])
    md = (tmp_path / "bench.md").read_text()
    assert "## Closed loop: the tick of a lap (target 25 ms median" in md
    assert md.count("| closed-loop tick: ") == 3


def test_loop_row_refuses_an_unknown_runner():
    from pixelmpc_jax.apps.bench.closed_loop import loop_row
    from pixelmpc_jax.apps.racing.spec import RaceSpec

    with pytest.raises(ValueError, match="runner"):
        loop_row(RaceSpec(), runner="threads")
    with pytest.raises(ValueError, match="repeats"):
        loop_row(RaceSpec(), repeats=0)


def test_a_row_that_aborts_its_process_is_reported_not_fatal():
    from pixelmpc_jax.apps.bench.measure import run_in_child

    assert run_in_child("math", "sqrt", [4.0]) == (True, 2.0)
    ok, why = run_in_child("os", "abort", [])  # what std::bad_alloc in XLA does to the process
    assert not ok and why.startswith("signal 6")


def test_what_a_run_skipped_is_not_measured_in_the_json_the_table_and_the_plot(recorded_smoke_run):
    """A quick run (no scaling, no Table I) and a missing peer: those targets say "not measured", never False."""
    rows = [r for r in json.loads(RECORDED_ROWS.read_text()) if r["group"] not in ("scaling", "table1", "peer")]
    for row in rows:  # as if measured at the paper's size
        if row["group"] in ("controller", "jit_paths"):
            row.update(num_samples=512, horizon=80)
        if row["group"] == "jit_paths":  # met at 512 x 80; 2048 x 80 not measured
            row.update(plain_over_documented=1.2)
    summary = suite.summarize(rows)
    targets = summary["targets"]
    for skipped in ("step_2048_over_512 <= 4.5", "step_8192_over_512 <= 16 (linear)",
                    "ratio_vs_pytorch_mppi <= 0.1 (N=512), 0.15 (N=2048)",
                    "documented compile path <= plain jax.jit (N=512, 2048; T=80)"):  # 2048 not measured
        assert targets[skipped] == suite.NOT_MEASURED, skipped
    assert summary["step_2048_over_512"] is None and summary["ratio_vs_pytorch_mppi"] == {}
    assert all(isinstance(met, bool) for name, met in targets.items() if name.startswith("pixelmpc_step"))
    result = {"device": recorded_smoke_run[2]["device"], "versions": recorded_smoke_run[2]["versions"],
              "mode": "quick", "rows": rows, "summary": summary}
    md = suite.markdown(result)
    assert "| step_8192_over_512 <= 16 (linear) | not measured |" in md
    assert "ours/pytorch-mppi not measured" in md
    fig = suite.scaling_figure(rows)
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert len(texts) == 2 and all("not measured" in t for t in texts)
    # the smoke run itself writes the same words into bench.json
    written = recorded_smoke_run[2]["summary"]["targets"]
    assert written["step_8192_over_512 <= 16 (linear)"] in (True, False, suite.NOT_MEASURED)
    assert written["documented compile path <= plain jax.jit (N=512, 2048; T=80)"] == suite.NOT_MEASURED


def test_the_documented_path_is_equal_where_it_keeps_xlas_kernels_and_must_be_faster_where_it_does_not():
    row = {"plain_over_documented": 0.97, "documented_kernels": "xla"}  # the plain jit's own program: noise
    assert suite._documented_target(row) is True
    assert suite._documented_target({**row, "documented_kernels": "ynnpack"}) is False
    assert suite._documented_target({**row, "plain_over_documented": 1.3, "documented_kernels": "ynnpack"}) is True
    assert suite._documented_target(None) == suite.NOT_MEASURED


def test_the_documented_compile_path_is_timed_against_a_plain_jit_in_one_run(recorded_smoke_run):
    from pixelmpc_jax.apps.bench import jit_paths

    rows = [r for r in recorded_smoke_run[2]["rows"] if r["group"] == jit_paths.GROUP]
    assert [r["name"] for r in rows] == [jit_paths.DOCUMENTED, jit_paths.PLAIN]
    ratio = rows[1]["median_ms"] / rows[0]["median_ms"]
    assert all(r["plain_over_documented"] == pytest.approx(ratio) for r in rows)
    assert "## The documented compile path against a plain jax.jit" in (recorded_smoke_run[0] / "bench.md").read_text()
