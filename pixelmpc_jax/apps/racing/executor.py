"""Where a grid's cells fly: in this process, on a pool of pinned local processes, or on a Dask cluster.

An :class:`Executor` runs one function over a list of tasks (a grid's cells, :func:`grid.run_grid
<pixelmpc_jax.apps.racing.grid.run_grid>`) and yields each outcome as it completes, a failed task as its one-line
error beside the others' results. It only runs tasks: the parent process alone writes what they return (the grid's
``results.json`` and its per-cell files), so a grid flown on any executor resumes as one flown in-process.

* :class:`InProcess`: one task after another in this process (one worker).
* :class:`LocalPool`: a ``concurrent.futures.ProcessPoolExecutor`` of ``spawn``-ed processes, each pinned to a core
  of its own (``os.sched_setaffinity`` where the system has it) and running JAX on one CPU device.
* :class:`DaskCluster`: the workers of a Dask distributed scheduler (``dask://HOST:PORT``, ``tcp://HOST:PORT``), or a
  ``distributed.LocalCluster`` of ``N`` single-threaded worker processes started for the run (``dask-local:N``).
  Dask is the optional extra ``pip install "pixelmpc-jax[cluster]"``.

Every worker process flies on one CPU device (a core split into several would only share that core) and keeps its
compilations in the parent's persistent compilation cache (:func:`~pixelmpc_jax.host.use_compilation_cache`), so
the second worker to fly a program loads it instead of compiling it again.

Why Dask and not Ray, measured on a 2-core AMD EPYC (2026-12-03, Python 3.11.7): what a user installs for the
extra, ``dask[distributed]`` 2026.8.0 and its dependencies, 5.2 MB of wheels and 44 MB installed, against Ray 2.60.0,
a 79 MB wheel alone and 259 MB installed with its dependencies; a local cluster of 2 worker
processes started (import included, to the first task) in 3.2 s cold and 1.4 s warm with Dask, 12.5 s and 2.9 s with
Ray; a trivial task's round trip took 11 ms through Dask's scheduler, 2.8 ms through Ray and 0.44 ms through
:class:`LocalPool` (medians of 200, one at a time). A grid cell flies for seconds to
minutes, so no engine's overhead per task counts; what decides is the install, and that a Dask cluster is two
commands on any hosts (``dask scheduler``; ``dask worker tcp://HOST:8786 --nthreads 1`` on each).
"""

from __future__ import annotations

import abc
import concurrent.futures
import contextlib
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any, NamedTuple

ENGINES = ("local", "dask-local:N", "dask://HOST:PORT", "tcp://HOST:PORT")  # what make_executor reads
CLUSTER_EXTRA = "pip install 'pixelmpc-jax[cluster]' (or: pip install 'dask[distributed]')"


class Completed(NamedTuple):
    """One task's outcome: the task, what it returned (None if it failed) and, if it failed, its one-line error."""

    task: Any
    result: Any
    error: str | None


def one_line(err: BaseException) -> str:
    """``err`` as one line: its type and its message's lines joined."""
    text = " ".join(line.strip() for line in str(err).splitlines() if line.strip())
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


class Executor(abc.ABC):
    """Runs a function over tasks and yields each :class:`Completed` as it completes (in any order).

    Used as a context manager (or closed with :meth:`close`): leaving it, also on Ctrl-C or SIGTERM, cancels the
    tasks not finished and stops the workers, so nothing keeps flying after the parent stopped."""

    workers: int = 1

    @abc.abstractmethod
    def run(self, fn: Callable[[Any], Any], tasks: Iterable) -> Iterator[Completed]:
        """``fn(task)`` for every task, each outcome as it completes; ``fn`` and the tasks must pickle (by
        reference for ``fn``: a module-level function) for an executor of other processes."""

    @abc.abstractmethod
    def close(self) -> None:
        """Cancel what has not finished and release the workers."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class InProcess(Executor):
    """One task after another in this process: what a grid did before executors, its failures kept apart."""

    def run(self, fn, tasks) -> Iterator[Completed]:
        for task in tasks:
            try:
                result = fn(task)
            except Exception as err:  # a failed task is reported; KeyboardInterrupt stops the run
                yield Completed(task, None, one_line(err))
            else:
                yield Completed(task, result, None)

    def close(self) -> None:
        """Nothing to release: a task stopped by Ctrl-C stopped this process's own loop."""


def _outcome(task, future) -> Completed:
    """A finished (or failed, or cancelled) future of ``task`` as its :class:`Completed`."""
    try:
        return Completed(task, future.result(), None)
    except Exception as err:  # the task's own error, raised again here; or the pool broke under it
        return Completed(task, None, one_line(err))


def prepare_worker(cache_dir: str | None, keep_memory: bool = False, pool_worker: bool = False) -> None:
    """Set up a worker process before it runs JAX: one CPU device (not :func:`~pixelmpc_jax.host.split_host_cpu`'s
    one per core: a pinned worker has one core), the parent's compilation cache ``cache_dir`` (None: this host's
    default), freed memory kept for the next step where the parent keeps it (``keep_memory``,
    :func:`~pixelmpc_jax.host.keep_host_memory`, as a ``pixelmpc`` process flying the cells itself would), and, for
    a ``pool_worker`` (:class:`LocalPool`'s, already pinned to its core from birth), deaf to Ctrl-C: the terminal's
    Ctrl-C reaches every process of its group, and the parent alone decides what stops (:meth:`Executor.close`)
    after writing what finished."""
    import signal

    if pool_worker:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    flags = [flag for flag in os.environ.get("XLA_FLAGS", "").split()
             if not flag.startswith("--xla_force_host_platform_device_count")]
    os.environ["XLA_FLAGS"] = " ".join(flags)
    import jax

    from pixelmpc_jax import host

    try:
        jax.config.update("jax_num_cpu_devices", 1)
    except RuntimeError:  # JAX already started in this process (a Dask worker that ran another job): keep it
        pass
    host.use_compilation_cache(cache_dir)
    if keep_memory:
        host.keep_host_memory()


@contextlib.contextmanager
def _pinned(core: int | None):
    """The calling thread runs on ``core`` inside the block (None, or a system without affinities: unchanged)."""
    if core is None or not hasattr(os, "sched_setaffinity"):
        yield
        return
    mask = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {core})
    try:
        yield
    finally:
        os.sched_setaffinity(0, mask)


def usable_cpus() -> list[int]:
    """The CPU cores this process may run on, in order."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def parent_memory_kept() -> bool:
    """Whether this process keeps freed memory (:func:`~pixelmpc_jax.host.host_memory_kept`), for its workers to."""
    from pixelmpc_jax import host

    return host.host_memory_kept()


def parent_cache_dir() -> str:
    """The persistent compilation cache this process uses (:func:`~pixelmpc_jax.host.compilation_cache_dir` when
    it set none), for its workers to share."""
    import jax

    from pixelmpc_jax import host

    return jax.config.jax_compilation_cache_dir or host.compilation_cache_dir()


class LocalPool(Executor):
    """``workers`` spawned processes on this host (at most one per task of a run; one runs in-process), each pinned
    to a core of its own (the first of the usable cores; more workers than cores share them in turn) and flying on
    one CPU device. Each :meth:`run` starts its pool and stops it when done."""

    def __init__(self, workers: int):
        if workers < 1:
            raise ValueError(f"workers must be a positive number of processes, got {workers!r}")
        self.workers = workers
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._futures: list = []

    def run(self, fn, tasks) -> Iterator[Completed]:
        tasks = list(tasks)
        workers = min(self.workers, len(tasks))
        if workers <= 1:  # a pool of one would only add a process start: fly here
            yield from InProcess().run(fn, tasks)
            return
        self._pool = concurrent.futures.ProcessPoolExecutor(
            workers, mp_context=multiprocessing.get_context("spawn"), initializer=prepare_worker,
            initargs=(parent_cache_dir(), parent_memory_kept(), True))
        cpus = usable_cpus()
        submitted = {}
        for index, task in enumerate(tasks):
            # a spawn pool starts a worker inside each of its first submits, from the submitting thread: the
            # worker is born on that thread's core (as under taskset), every thread it ever starts with it
            with _pinned(cpus[index % len(cpus)] if index < workers else None):
                submitted[self._pool.submit(fn, task)] = task
        self._futures = list(submitted)
        try:
            for future in concurrent.futures.as_completed(submitted):
                yield _outcome(submitted[future], future)
        finally:
            self.close()

    def close(self) -> None:
        if self._pool is None:
            return
        for future in self._futures:
            future.cancel()
        unfinished = any(not future.done() for future in self._futures)
        if unfinished:  # stopped early: the running tasks are stopped with their processes, not waited for
            for process in list(getattr(self._pool, "_processes", {}).values()):  # no public way before 3.14
                process.terminate()
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._pool, self._futures = None, []


def _dask_task(fn, task, cache_dir, keep_memory):
    """``fn(task)`` on a Dask worker, the worker set up first (:func:`prepare_worker`, once per process)."""
    if not _WORKER_READY:
        prepare_worker(cache_dir, keep_memory)
        _WORKER_READY.append(True)
    return fn(task)


_WORKER_READY: list = []  # a Dask worker process that ran prepare_worker holds one entry


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise ImportError(f"a Dask executor needs dask's distributed scheduler: {CLUSTER_EXTRA}") from None
    return distributed


class DaskCluster(Executor):
    """The workers of a Dask distributed scheduler at ``address`` (``tcp://HOST:PORT``), or of a local cluster of
    ``local_workers`` single-threaded processes started here for the run and stopped after it."""

    def __init__(self, address: str | None = None, local_workers: int | None = None):
        if (address is None) == (local_workers is None):
            raise ValueError("a Dask executor takes a scheduler address or a number of local workers, one of them")
        if local_workers is not None and local_workers < 1:
            raise ValueError(f"dask-local needs a positive number of workers, got {local_workers!r}")
        self._distributed = _import_distributed()
        self.address, self.workers = address, local_workers or 0
        self._cluster = self._client = None
        self._futures: list = []

    def _connect(self):
        distributed = self._distributed
        if self.address is None:
            self._cluster = distributed.LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                                     dashboard_address=None)
            self._client = distributed.Client(self._cluster)
            return parent_cache_dir()  # the same host: the same cache
        try:
            self._client = distributed.Client(self.address, timeout="30s")
        except OSError as err:
            raise OSError(f"no Dask scheduler answers at {self.address}: {one_line(err)}") from None
        self.workers = len(self._client.scheduler_info().get("workers", {})) or 1
        return None  # other hosts: each worker its own host's cache

    def run(self, fn, tasks) -> Iterator[Completed]:
        distributed = self._distributed
        cache_dir = self._connect()
        tasks = list(tasks)
        keep = parent_memory_kept()
        futures = [self._client.submit(_dask_task, fn, task, cache_dir, keep, pure=False) for task in tasks]
        self._futures = futures
        of_future = {future.key: task for future, task in zip(futures, tasks)}
        try:
            for future in distributed.as_completed(futures):
                yield _outcome(of_future[future.key], future)
        finally:
            self.close()

    def close(self) -> None:
        if self._client is not None:
            if self._futures:
                self._client.cancel(self._futures)
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._cluster = self._client = None
        self._futures = []


def parse_engine(engine: str) -> tuple[str, object]:
    """``(kind, value)`` of an engine's name: ("local", None), ("dask-local", N) or ("dask", "tcp://HOST:PORT"); a
    ValueError names a malformed one."""
    if engine == "local":
        return "local", None
    if engine.startswith("dask-local:"):
        count = engine.split(":", 1)[1]
        if not count.isdigit() or int(count) < 1:
            raise ValueError(f"executor {engine!r}: dask-local:N needs a positive number of workers N")
        return "dask-local", int(count)
    if engine.startswith(("dask://", "tcp://")):
        host_port = engine.split("://", 1)[1]
        if ":" not in host_port or not host_port.rsplit(":", 1)[1].isdigit() or not host_port.rsplit(":", 1)[0]:
            raise ValueError(f"executor {engine!r}: a Dask scheduler is named as dask://HOST:PORT")
        return "dask", "tcp://" + host_port
    raise ValueError(f"unknown executor {engine!r}; choose one of {', '.join(ENGINES)}")


def make_executor(engine: str | None = None, workers: int | None = None) -> Executor:
    """The executor an ``--executor`` / ``--workers`` pair names. ``engine`` (:func:`parse_engine`): "local"
    (default) a :class:`LocalPool` of ``workers`` processes (default: one per usable core; never more than the tasks
    of a run; one worker is :class:`InProcess`), "dask-local:N" a local Dask cluster of N workers,
    "dask://HOST:PORT" or "tcp://HOST:PORT" the Dask scheduler there. A ValueError names a malformed engine, or
    ``workers`` given to a Dask engine (its workers are its own); an ImportError names the extra Dask needs."""
    kind, value = parse_engine(engine or "local")
    if kind == "local":
        count = len(usable_cpus()) if workers is None else workers
        return InProcess() if count == 1 else LocalPool(count)
    if workers is not None:
        raise ValueError(f"--workers is for the local pool; {engine} has its own workers")
    return DaskCluster(local_workers=value) if kind == "dask-local" else DaskCluster(address=value)
