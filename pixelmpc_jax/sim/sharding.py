"""Batches of episodes over every device, across processes too: place a batch, bring it back whole."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def shard_batch(tree, devices=None):
    """Place a batch (leading axis B on every leaf) across ``devices`` (default: all JAX devices, of every
    process) with a 1-D ``Mesh`` and ``NamedSharding``, padding B to a multiple of the device count by
    repeating the last element. Returns ``(sharded tree, B)``; with one device the tree is returned as it is.

    With several processes (``jax.distributed``), every process holds the whole batch (the laps are built
    from seeds, the same everywhere) and places the rows of its own devices."""
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = list(devices if devices is not None else jax.devices())
    size = jax.tree_util.tree_leaves(tree)[0].shape[0]
    if len(devices) <= 1:
        return tree, size
    padded = -(-size // len(devices)) * len(devices)
    if padded != size:
        tree = jax.tree_util.tree_map(
            lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], padded - size, axis=0)]), tree)
    sharding = NamedSharding(Mesh(np.asarray(devices), ("batch",)), PartitionSpec("batch"))
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
