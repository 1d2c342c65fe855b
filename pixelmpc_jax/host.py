"""The process and its host: the CPU's cores as JAX devices, and the C allocator keeping freed memory.

Neither is part of a controller: they set up the process a controller runs in, once, before (or while) it
runs. ``pixelmpc race``, ``bench``, ``reproduce``, ``tune`` and ``experiment`` call both by default
(``cli.SPLIT_CPU_COMMANDS``).

* :func:`split_host_cpu`: make each usable core a JAX device (before JAX starts), so a step whose samples are
  split over the devices (``devices.Execution.sample_devices``) runs on every core.
* :func:`keep_host_memory`: the C allocator keeps the memory a step frees for the next step, instead of
  handing its largest buffers back to the system and faulting them in again, page by page, every step.
"""

from __future__ import annotations

import ctypes
import os
import platform

import jax

HOST_CPU_DEVICES_MAX = 8  # split_host_cpu's default: one device per usable core, at most this many
# glibc's mallopt parameters (malloc.h) and its defaults, restored by keep_host_memory(False)
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_GLIBC_TRIM_THRESHOLD, _GLIBC_MMAP_MAX = 128 * 1024, 65536
KEPT_FREE_BYTES = 1 << 30  # keep_host_memory: free memory above this at the top of the heap still goes back
_host_memory = {"kept": False}  # what keep_host_memory last set (the C library cannot be asked)


def usable_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def split_host_cpu(count: int | None = None) -> int:
    """Make the host CPU appear to JAX as ``count`` devices (default: one per usable core, at most
    :data:`HOST_CPU_DEVICES_MAX`), so that a step split over them runs on every core. Must run before JAX
    starts its backend (before any array is made); afterwards it changes nothing. An ``XLA_FLAGS`` setting of
    ``--xla_force_host_platform_device_count`` wins. Returns the count now in effect for the CPU platform."""
    if count is None:
        count = min(usable_cores(), HOST_CPU_DEVICES_MAX)
    if count < 1:
        raise ValueError(f"count must be a positive number of devices, got {count!r}")
    if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
        try:
            jax.config.update("jax_num_cpu_devices", int(count))
        except RuntimeError:  # JAX has started: the devices are what they are
            pass
    try:
        return len(jax.devices("cpu"))
    except RuntimeError:  # no CPU platform
        return 0


def keep_host_memory(keep: bool = True) -> bool:
    """Have the C allocator (glibc) keep freed memory for the process instead of giving it back to the system.

    An XLA step on a CPU allocates its buffers afresh at every call. glibc serves a buffer over 32 MiB (at 8192
    samples, one step's temporaries) with its own ``mmap`` and unmaps it when freed, so the next step faults
    every page of it in again: 74 MB and about 18,000 page faults per PixelMPC step at N = 8192 here, none at
    N = 512. With ``keep``, every allocation comes from the heap (``M_MMAP_MAX`` 0) and up to
    :data:`KEPT_FREE_BYTES` of freed memory stays with the process (``M_TRIM_THRESHOLD``), so a step reuses the
    last step's pages. The cost: the process holds on to its peak memory, up to that much more. ``keep=False``
    restores glibc's defaults (its dynamic ``mmap`` threshold stays off once set). Process-wide; safe at any
    time. Returns whether the settings took effect (False where the C library is not glibc, e.g. macOS)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    mmap_max, trim = (0, KEPT_FREE_BYTES) if keep else (_GLIBC_MMAP_MAX, _GLIBC_TRIM_THRESHOLD)
    done = bool(mallopt(_M_MMAP_MAX, mmap_max)) and bool(mallopt(_M_TRIM_THRESHOLD, trim))
    _host_memory["kept"] = keep and done
    return done


def host_memory_kept() -> bool:
    """Whether :func:`keep_host_memory` has the allocator keeping freed memory now."""
    return _host_memory["kept"]


def compilation_cache_dir() -> str:
    """Where ``pixelmpc`` keeps compiled steps: ``$XDG_CACHE_HOME/pixelmpc-jax/jax`` (``~/.cache/...``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "pixelmpc-jax", "jax")


def use_compilation_cache(path: str | None = None, min_compile_s: float = 0.5) -> str:
    """Keep every compilation that took over ``min_compile_s`` in JAX's persistent cache at ``path`` (default
    :func:`compilation_cache_dir`), so the next process that compiles the same step loads it instead. Returns
    the folder."""
    path = path or compilation_cache_dir()
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_s)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def _swallows_exceptions(frame) -> bool:
    """Whether an exception raised at ``frame`` would be printed and dropped instead of reaching the main code:
    inside a garbage-collector callback (JAX registers one) or a ``__del__`` method."""
    import gc

    callbacks = {getattr(callback, "__code__", None) for callback in gc.callbacks}
    while frame is not None:
        if frame.f_code in callbacks or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


REDELIVER_S = 0.01  # a signal that arrived where its exception would be dropped is delivered again this much later


def stop_on_sigterm() -> None:
    """Make SIGTERM (what a batch scheduler or ``kill`` sends) stop the process as Ctrl-C does: it raises
    KeyboardInterrupt in the main thread, so every command keeps what it had finished, as on Ctrl-C. Ctrl-C
    (SIGINT) gets the same handler where it has Python's own. A signal that lands inside a garbage-collector
    callback or a ``__del__``, where Python would print the exception and go on, is delivered again once that code
    has returned."""
    import _thread
    import signal
    import threading

    def interrupt(signum, frame):
        if _swallows_exceptions(frame):
            threading.Timer(REDELIVER_S, _thread.interrupt_main, args=(signum,)).start()
            return
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    signal.signal(signal.SIGTERM, interrupt)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # Python's own Ctrl-C, not a host's handler
        signal.signal(signal.SIGINT, interrupt)
