import fcntl
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

_CACHE_HOME = {}
# Compilations shorter than this are not written to the shared cache: loading one costs about as much as making it.
_MIN_CACHED_COMPILE_S = 0.2
# XLA's CPU compiler at its cheapest: no fusion emitters, no LLVM optimisation, and each program's code generated as
# one LLVM module rather than split into parts for parallel compilation (the cores are busy with the run's other
# worker; unsplit, tests/test_env.py, test_pixelmpc.py and test_mppi.py took about a tenth less processor time, in two
# rounds beside a busy core: 88 -> 82 s, 77 -> 67 s). Compilation is most of the suite's time and the tests' episodes
# are short, so the suite runs about three times faster (tests/test_env.py and tests/test_pixelmpc.py: 56 s against
# 160 s on one core, before the unsplit modules). What a step computes is the same; its float rounding is not: the
# golden laps keep a recording per compilation, and the pinned DOF training fingerprints (tests/test_train.py) hold
# within their tolerance at both. A test that compares with figures recorded as a user's run compiles and would not
# hold so (the pinned VDOF weights: their rollout stage carries the rounding of the data it trains on) is marked
# ``compiled_as_shipped`` and runs in a process of its own with the flags the run began with. A program that runs long
# enough for its optimisation to pay for itself (a rendered batch, the particle filter's 6,400 particles over 1,200
# steps) is jitted with XLA's default optimisation in the run itself (:func:`jit_as_shipped`). The slow checks
# (``--runslow``) fly long laps, where a program's speed counts more than its compilation: they compile as a user's
# run does, as does ``--optimized-xla``.
#
# Nor does it hoist what a loop's body computes alike at every iteration out of the loop (XLA's loop-invariant code
# motion): on an episode, a while loop over ticks around the MPPI step's scans, that pass was a third of the
# compilation (a PixelMPC episode of 128 samples over 40 steps: 7.3 s -> 4.7 s to compile, 1.6 s to run either way,
# one core of a 2-core AMD EPYC). The same operations run on the same values, so the laps are the same bit for bit
# (tests/test_golden_laps.py held against a recording made without the flag).
FAST_COMPILE_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0 "
                          "--xla_cpu_parallel_codegen_split_count=1 "
                          "--xla_disable_hlo_passes=while-loop-invariant-code-motion")
# The first two flags above set for an optimised program (fusion emitters on, LLVM at its highest level), for the
# programs the tests compile so although the run compiles at its cheapest (:func:`jit_as_shipped`). A batch rendered
# so differed from a user's run in one colour value of eight frames: the tests that render compare within a pixel's
# tolerance.
SHIPPED_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": True, "xla_backend_optimization_level": 3}
# Set in the tests' environment when the fast flags are on: the XLA flags the run was started with.
USER_XLA_FLAGS = "PIXELMPC_TESTS_USER_XLA_FLAGS"
# Set by the run's first process for every other (xdist workers, the tests' own subprocesses): the run's cache.
RUN_CACHE = "PIXELMPC_TESTS_RUN_CACHE"


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run experiment-scale checks marked slow")
    parser.addoption("--optimized-xla", action="store_true", default=False,
                     help="compile as a user's run does (XLA's default optimisation; slower to compile). Without it "
                          "(and without --runslow) the tests compile at XLA's cheapest, their long programs apart")


def _fast_compilation() -> bool:
    return USER_XLA_FLAGS in os.environ


def xla_flags_for(device_count: int | None = None) -> str:
    """The run's XLA flags (its compilation among them) for a subprocess: with ``device_count`` CPU devices, or with
    none forced (a forced count wins over a command's own split of the host's cores)."""
    kept = [flag for flag in os.environ.get("XLA_FLAGS", "").split()
            if "xla_force_host_platform_device_count" not in flag]
    forced = [] if device_count is None else [f"--xla_force_host_platform_device_count={device_count}"]
    return " ".join(kept + forced)


def _use_fast_compilation(config) -> None:
    """Append :data:`FAST_COMPILE_XLA_FLAGS` to ``XLA_FLAGS`` before anything compiles (the xdist workers and the
    commands' subprocesses inherit it), remembering the flags the run began with."""
    if config.getoption("--runslow") or config.getoption("--optimized-xla"):
        return
    user = os.environ.get("XLA_FLAGS", "")
    os.environ[USER_XLA_FLAGS] = user
    os.environ["XLA_FLAGS"] = f"{user} {FAST_COMPILE_XLA_FLAGS}".strip()


def jit_as_shipped(jitted, **jit_kwargs):
    """The jitted function ``jitted`` compiled with XLA's default optimisation (``compiler_options``) where the run
    compiles at its cheapest, for a program that runs long: unoptimised it runs several times slower than its
    optimisation costs (240 rendered frames: 3.5 s against 25 s on one core; 1,200 particle filter steps of 6,400
    particles: 4 s against 19 s). ``jit_kwargs`` are ``jitted``'s own (its static arguments). Elsewhere ``jitted``
    itself. Such a program may only be called at the top level: inside another jit it fails loudly
    (``compiler_options`` is for top-level programs only)."""
    if not _fast_compilation():
        return jitted
    import jax

    return jax.jit(jitted.__wrapped__, compiler_options=SHIPPED_COMPILER_OPTIONS, **jit_kwargs)


def _render_batches_as_shipped() -> None:
    """Compile :func:`pixelmpc_jax.world.render.render_batch` optimised (:func:`jit_as_shipped`) where its callers
    compile it (``devices.compiled(render.render_batch, ("supersample", "chunk"))``): a rendered frame is the one long
    program several test files run (hundreds of thousands of rays). Every other function, and ``render_batch`` traced
    inside another jit, compiles as the run does. (The package's callers name it ``devices.compiled``, looked up when
    they call it, so they get this one.)"""
    import jax

    from pixelmpc_jax import devices
    from pixelmpc_jax.world import render

    compiled = devices.compiled
    shipped = jit_as_shipped(jax.jit(render.render_batch), static_argnames=("supersample", "chunk"))

    def compiled_as_shipped(fn, static_argnames=()):
        return shipped if fn is render.render_batch else compiled(fn, static_argnames)

    devices.compiled = compiled_as_shipped


def _run_computations_inline() -> None:
    """Have JAX run each CPU computation on the thread that calls it (``jax_cpu_enable_async_dispatch``), in this
    test process, before its CPU client is made.

    By default JAX hands every computation to a thread of its own and the caller waits for it. The tests run
    thousands of small programs (an eager operation is one) in two workers on two cores, and there the hand-overs
    cost them dearly: beside another test process, tests/test_costs.py took 27.6 s, and 12.2 s with each process held
    to a core of its own. The README's test command took 5:34 and 5:44 in two runs, and 4:20 with the computations
    inline (2-core Intel Xeon, 2026-12-02; its processor time 10:04-10:22 -> 8:00). What a computation gives is the
    same (the golden laps hold bit for bit); only when the caller gets it back changes. A race's own time does not
    change (`pixelmpc race` with nothing cached: 31.6-32.4 s either way, two runs each).
    The commands the tests start in processes of their own dispatch as a user's run does."""
    import jax

    jax.config.update("jax_cpu_enable_async_dispatch", False)


def pytest_configure(config):
    """One compilation cache for the whole run, made before the first compile; computations run inline
    (:func:`_run_computations_inline`).

    The commands under test keep their compiled steps in ``$XDG_CACHE_HOME`` (see
    :func:`pixelmpc_jax.host.compilation_cache_dir`). The first process of the run (the xdist controller, or the
    only process without ``-n``) points it at a fresh folder, so a run neither writes into the user's cache nor
    starts warm from an earlier run's. The xdist workers and the commands' subprocesses inherit it. Every test
    process keeps its own compilations there too (JAX's persistent cache), so a step that two test files or a
    test and a subprocess compile is compiled once per run. (:data:`RUN_CACHE` tells the run's other processes,
    pytest's own among them, that they belong to it.)"""
    from pixelmpc_jax.host import compilation_cache_dir, use_compilation_cache

    if RUN_CACHE not in os.environ:  # the run's first process
        _use_fast_compilation(config)
        _CACHE_HOME["old"] = os.environ.get("XDG_CACHE_HOME")
        _CACHE_HOME["new"] = tempfile.mkdtemp(prefix="pixelmpc-tests-cache-")
        os.environ["XDG_CACHE_HOME"] = os.environ[RUN_CACHE] = _CACHE_HOME["new"]
        # every Python the tests start that compiles with JAX (a command, a documented example, a process with
        # other devices) keeps its programs in the run's cache too, where the count of closed-loop programs sees them
        os.environ["JAX_COMPILATION_CACHE_DIR"] = compilation_cache_dir()
    use_compilation_cache(min_compile_s=_MIN_CACHED_COMPILE_S)
    _record_closed_loop_compilations()
    _run_computations_inline()
    if _fast_compilation():
        _render_batches_as_shipped()


# The compiled closed-loop programs: :func:`pixelmpc_jax.sim.episode.episode_fn`'s episode, jitted alone or vmapped.
CLOSED_LOOP_PROGRAM = "jit_closed_loop_episode"
MAX_CLOSED_LOOP_PROGRAMS = 10  # what the suite may compile (tests/test_compilation_setup.py reads the summary)


class _CompileLog(logging.Handler):
    """Appends ``cache key <TAB> seconds <TAB> test`` to this process's file in the run's folder for every closed-loop
    program it compiles, from JAX's compiler log: a persistent-cache miss names the program's key, and the end of its
    compilation (:data:`COMPILED`) its time. A program the cache does not keep (one with host callbacks: the image
    detector) is counted so too."""

    COMPILED = f"Finished XLA compilation of jit({CLOSED_LOOP_PROGRAM.removeprefix('jit_')}) in "

    def __init__(self, path: Path):
        super().__init__(logging.DEBUG)
        self.path, self.pending = path, {}

    def emit(self, record):
        args = record.args if isinstance(record.args, tuple) else ()
        thread = record.thread
        if record.msg.startswith("PERSISTENT COMPILATION CACHE MISS") and str(args[0]).startswith(
                CLOSED_LOOP_PROGRAM):
            self.pending[thread] = args[1]
        elif isinstance(record.msg, str) and record.msg.startswith(self.COMPILED) and thread in self.pending:
            seconds = float(record.msg.removeprefix(self.COMPILED).split()[0])
            test = os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" (", 1)[0]
            with open(self.path, "a") as out:
                out.write(f"{self.pending.pop(thread)}\t{seconds:.3f}\t{test}\n")


def _compile_log_dir() -> Path:
    return Path(os.environ[RUN_CACHE]) / "closed_loop_compiles"


def _record_closed_loop_compilations() -> None:
    """Log every closed-loop program this test process compiles (:class:`_CompileLog`)."""
    folder = _compile_log_dir()
    folder.mkdir(parents=True, exist_ok=True)
    handler = _CompileLog(folder / f"{os.getpid()}.tsv")
    for name in ("jax._src.compiler", "jax._src.dispatch"):
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(handler)


def closed_loop_compilations(cache_dir: Path, log_dir: Path) -> dict[str, tuple[float, str]]:
    """Every distinct closed-loop program the run compiled, ``{cache key: (compile seconds, test)}``: the run's
    compilation cache holds each once, from a test process or a command the tests started (JAX records its compile
    time in whole seconds there; such a program's test is "a command"), and a test process's log holds its time to
    the millisecond and the test that compiled it."""
    from jax._src import compilation_cache

    programs = {}
    for entry in sorted(cache_dir.glob(f"{CLOSED_LOOP_PROGRAM}-*-cache")):
        data = compilation_cache.decompress_executable(entry.read_bytes())
        seconds = float(compilation_cache.extract_executable_and_time(data)[1])
        programs[entry.name.removesuffix("-cache")] = (seconds, "a command the tests started")
    for log in sorted(log_dir.glob("*.tsv")):
        for line in log.read_text().splitlines():
            key, seconds, test = line.split("\t")
            programs[key] = (float(seconds), test)
    return programs


def pytest_terminal_summary(terminalreporter, config):
    """The closed-loop programs the run compiled and their compile time (the run's first process, at the end)."""
    if "new" not in _CACHE_HOME:
        return
    from pixelmpc_jax.host import compilation_cache_dir

    programs = closed_loop_compilations(Path(compilation_cache_dir()), _compile_log_dir())
    terminalreporter.write_sep("=", "closed-loop programs compiled")
    terminalreporter.write_line(f"{len(programs)} distinct closed-loop programs (at most {MAX_CLOSED_LOOP_PROGRAMS}), "
                                f"{sum(seconds for seconds, _ in programs.values()):.1f} s of compilation in all")
    for key, (seconds, test) in sorted(programs.items(), key=lambda item: -item[1][0]):
        terminalreporter.write_line(f"  {seconds:7.2f} s  {key[24:36]}  {test}")


def made_once_per_run(name: str, make) -> Path:
    """The folder ``name`` that ``make(folder)`` fills, made once per test run and shared by its processes (the xdist
    workers wait for the first to finish it): what several test files build alike, a collected dataset. Read it, or
    copy it before changing it."""
    root = Path(os.environ[RUN_CACHE]) / "made_once" / name
    root.parent.mkdir(parents=True, exist_ok=True)
    with open(root.parent / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root.parent / f"{name}.done").exists():
            shutil.rmtree(root, ignore_errors=True)
            make(root)
            (root.parent / f"{name}.done").touch()
    return root


_SHIPPED_OUTCOMES: dict[str, str] = {}  # nodeid -> outcome of the compiled_as_shipped tests run apart
_SHIPPED_REPORTS: dict[str, str] = {}  # test file -> the report of its process


def _run_as_shipped(item) -> None:
    """Run every ``compiled_as_shipped`` test of ``item``'s file that this run selected in one pytest process with the
    XLA flags the run began with; record each one's outcome from the process's summary (``-rA``)."""
    selected = [other.nodeid for other in item.session.items
                if other.path == item.path and other.get_closest_marker("compiled_as_shipped") is not None]
    env = {**os.environ, "XLA_FLAGS": os.environ[USER_XLA_FLAGS]}
    for name in (USER_XLA_FLAGS, "PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT"):
        env.pop(name, None)  # the run's compilation cache stays: a program compiled with other flags has another key
    # --runslow: a slow test among them was selected by the run (the run skips it before it gets here otherwise)
    command = [sys.executable, "-m", "pytest", *selected, "--optimized-xla", "-q", "-rA", "-p", "no:cacheprovider",
               "-o", "addopts=", "--runslow"]
    done = subprocess.run(command, cwd=item.config.rootpath, env=env, capture_output=True, text=True)
    _SHIPPED_REPORTS[str(item.path)] = done.stdout[-8000:] + done.stderr[-2000:]
    for line in done.stdout.splitlines():
        outcome, _, rest = line.partition(" ")
        nodeid = rest.split(" - ", 1)[0]
        if outcome in ("PASSED", "FAILED", "ERROR", "SKIPPED") and nodeid in selected:
            _SHIPPED_OUTCOMES[nodeid] = outcome


def pytest_pyfunc_call(pyfuncitem):
    """A ``compiled_as_shipped`` test, where the run compiles at XLA's cheapest: run with the others of its file in a
    pytest process with the XLA flags the run began with (``--optimized-xla``, :func:`_run_as_shipped`), and fail
    with that process's report if it did not pass there."""
    if not _fast_compilation() or pyfuncitem.get_closest_marker("compiled_as_shipped") is None:
        return None
    if pyfuncitem.nodeid not in _SHIPPED_OUTCOMES:
        _run_as_shipped(pyfuncitem)
    outcome = _SHIPPED_OUTCOMES.get(pyfuncitem.nodeid, "not reported")
    if outcome != "PASSED":
        pytest.fail(f"run with XLA's default flags it was {outcome}:\n{_SHIPPED_REPORTS[str(pyfuncitem.path)]}",
                    pytrace=False)
    return True


def pytest_unconfigure(config):
    if "new" not in _CACHE_HOME:  # a worker: the folder is the first process's
        return
    os.environ.pop(RUN_CACHE, None)
    os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)
    if USER_XLA_FLAGS in os.environ:
        os.environ["XLA_FLAGS"] = os.environ.pop(USER_XLA_FLAGS)
        if not os.environ["XLA_FLAGS"]:
            os.environ.pop("XLA_FLAGS")
    if _CACHE_HOME.get("old") is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = _CACHE_HOME["old"]
    shutil.rmtree(_CACHE_HOME["new"], ignore_errors=True)


# The files that take the longest (closed-loop episodes, subprocesses, compilations), heaviest first, as
# ``--durations`` measured them (a run on an idle 2-core AMD EPYC, 2026-12-03). They are handed out first: with one
# file to a worker (``--dist loadfile``), a run that hands out its longest files last ends on one worker while the
# other waits. xdist's own order (``--loadscope-reorder``, its default: the files with the most tests first) would
# hand out the heavy files with few tests (the golden laps, the sharding) last, so pyproject.toml turns it off.
HEAVIEST_FIRST = ("test_pixelmpc.py", "test_eskf.py", "test_readme.py", "test_particle_filter.py", "test_train.py",
                  "test_env.py", "test_sharding.py", "test_sample_devices.py", "test_detector.py", "test_collect.py",
                  "test_faults.py", "test_mppi.py", "test_golden_laps.py", "test_evaluate.py", "test_reliability.py",
                  "test_costs.py", "test_vdof.py", "test_cli.py", "test_compare.py", "test_gate_paint.py",
                  "test_perception_levers.py", "test_closed_loop_api.py", "test_quadrotor.py", "test_render.py",
                  "test_tune.py", "test_flow.py", "test_frontier.py", "test_imu_realism.py", "test_episode.py",
                  "test_dof.py")


def _heaviest_first(items) -> None:
    rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each file keeps its own order


def pytest_collection_modifyitems(config, items):
    _heaviest_first(items)
    if config.getoption("--runslow"):
        return
    marker = pytest.mark.skip(reason="experiment-scale; run with --runslow (a faster test covers the code)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(marker)
