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


def device_line() -> str:
    """One line for reports: device, CPU, versions."""
    d = device_description()
    return (f"{d['platform']} ({d['device_kind']}, {d['num_devices']} device(s)); CPU {d['cpu_model']}, "
            f"{d['cpu_count']} cores; jax {d['jax']}, jaxlib {d['jaxlib']}")
