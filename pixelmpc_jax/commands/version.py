"""``pixelmpc version``: the package's and JAX's versions, and the devices JAX sees."""

from __future__ import annotations


def add_version(sub) -> None:
    """``pixelmpc version``."""
    p = sub.add_parser("version", help="print the package, JAX version and devices")
    p.set_defaults(func=_cmd_version)


def _cmd_version(args) -> int:
    import jax

    from pixelmpc_jax import __version__

    print(f"pixelmpc-jax {__version__} (jax {jax.__version__}, devices: {jax.devices()})")
    return 0
