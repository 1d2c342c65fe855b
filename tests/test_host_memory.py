"""keep_host_memory: freed memory stays with the process, so a buffer allocated again is not faulted in again."""

import platform
import subprocess
import sys
import textwrap

import pytest

from pixelmpc_jax import host

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# Allocates (malloc, as XLA does), frees and allocates again a 64 MiB buffer (over glibc's largest mmap
# threshold, as a step's temporaries at 8192 samples are) and prints the page faults of the second one's first
# touch.
REUSE = textwrap.dedent("""
    import ctypes, resource, sys
    from pixelmpc_jax import host
    print(host.keep_host_memory(sys.argv[1] == "keep"), host.host_memory_kept())
    libc = ctypes.CDLL(None)
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, (ctypes.c_size_t,)
    libc.free.argtypes = (ctypes.c_void_p,)
    libc.memset.argtypes = (ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t)
    size = 64 << 20
    a = libc.malloc(size); libc.memset(a, 1, size); libc.free(a)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = libc.malloc(size); libc.memset(a, 1, size)
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
""")


def _faults(mode: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", REUSE, mode], capture_output=True, text=True, check=True).stdout
    flags, faults = out.strip().splitlines()
    return flags, int(faults)


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_kept_memory_is_reused_without_page_faults_and_released_memory_is_not():
    kept_flags, kept = _faults("keep")
    released_flags, released = _faults("release")
    assert kept_flags == "True True" and released_flags == "True False"
    pages = (64 << 20) // 4096
    assert released > pages // 2  # a fresh mapping: every page faulted in again
    assert kept < pages // 20  # the freed pages themselves, reused


@pytest.mark.skipif(GLIBC, reason="elsewhere keep_host_memory reports that it did nothing")
def test_keep_host_memory_reports_no_effect_without_glibc():
    assert host.keep_host_memory() is False and not host.host_memory_kept()
