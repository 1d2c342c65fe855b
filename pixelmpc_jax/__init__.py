"""pixelmpc_jax: perception-aware sampling MPC (PixelMPC) with Deep Optical Flow dynamics, in JAX."""

__version__ = "0.1.0"
