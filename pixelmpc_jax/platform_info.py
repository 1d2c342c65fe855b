"""What a result was measured on: the JAX device, the CPU model, library versions."""

from __future__ import annotations

import os
import platform

import jax


def device_description() -> dict:
    """The device JAX runs on, the CPU model and the library versions."""
    device = jax.devices()[0]
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import jaxlib

    return {
        "platform": device.platform,
        "device_kind": getattr(device, "device_kind", str(device)),
        "num_devices": jax.device_count(),
        "cpu_model": cpu,
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "python": platform.python_version(),
    }


def cpu_signature() -> str:
    """The processor as its float rounding depends on it: the model name, family and model numbers, and the vector
    extensions XLA's CPU kernels choose between (two processors of one name can round a lap differently)."""
    fields, flags = {}, set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                name, _, value = line.partition(":")
                name = name.strip()
                if name in ("model name", "cpu family", "model") and name not in fields:
                    fields[name] = value.strip()
                elif name == "flags" and not flags:
                    flags = set(value.split())
    except OSError:
        return platform.processor() or platform.machine()
    vector = [f for f in ("avx", "avx2", "fma", "avx512f", "avx512_bf16", "amx_tile") if f in flags]
    return " ".join([fields.get("model name", platform.machine()), f"family {fields.get('cpu family', '?')}",
                     f"model {fields.get('model', '?')}", *vector])


def device_line() -> str:
    """One line for reports: device, CPU, versions."""
    d = device_description()
    return (f"{d['platform']} ({d['device_kind']}, {d['num_devices']} device(s)); CPU {d['cpu_model']}, "
            f"{d['cpu_count']} cores; jax {d['jax']}, jaxlib {d['jaxlib']}")


def invocation(argv: list[str] | None = None) -> str:
    """The command line a record keeps, as a user would type it again: the program by its name (``pixelmpc``, or
    ``python -m pixelmpc_jax.cli``), never by the path it was installed at on this machine."""
    import shlex
    import sys

    argv = list(sys.argv if argv is None else argv)
    program = os.path.basename(argv[0]) if argv else "pixelmpc"
    if program in ("cli.py", "__main__.py"):
        program = "python -m pixelmpc_jax.cli"
    return " ".join([program, *(shlex.quote(arg) for arg in argv[1:])])
