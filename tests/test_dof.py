"""DOF network and pixel dynamics, Eqs. (11)-(12): size, equations, transformations, checkpoints."""

from __future__ import annotations

import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization

from pixelmpc_jax.dynamics import dof, network_weights, quadrotor


@pytest.fixture(scope="module")
def dof_params():
    """Random weights with non-trivial normalisation constants (so they are exercised)."""
    return dof.init_dof_params(
        jax.random.key(3),
        input_mean=np.linspace(-0.5, 0.5, 10),
        input_std=np.linspace(0.5, 2.0, 10),
        output_mean=[0.8, 0.3],
        output_std=[0.4, 1.0],
    )


def _samples(n: int, seed: int = 0):
    """n random (q, uv, u), each (n, k)."""
    rng = np.random.default_rng(seed)
    eul = rng.uniform(-0.8, 0.8, (n, 3)).astype(np.float32)
    q = jax.vmap(quadrotor.quat_from_euler)(eul[:, 0], eul[:, 1], eul[:, 2])
    uv = jnp.asarray(rng.uniform(0, 1, (n, 2)), jnp.float32)
    u = jnp.asarray(np.concatenate([rng.uniform(-3, 3, (n, 3)), rng.uniform(5, 15, (n, 1))], 1), jnp.float32)
    return q, uv, u


def test_parameter_count_is_34690(dof_params):
    assert network_weights.num_trainable_params(dof_params) == 34_690
    kernels = [dof_params.weights[f"Dense_{k}"]["kernel"].shape for k in range(4)]
    assert kernels == [(10, 128), (128, 128), (128, 128), (128, 2)]
    assert dof.LAYER_SIZES == (10, 128, 128, 128, 2)


def test_pixel_velocity_is_polar_to_euler(dof_params):
    q, uv, u = _samples(5)
    for k in range(5):
        l, theta = dof.dof_apply(dof_params, q[k], uv[k], u[k])
        assert l.shape == () and theta.shape == ()
        uv_dot = dof.pixel_velocity(dof_params, q[k], uv[k], u[k])
        assert uv_dot.shape == (2,)
        np.testing.assert_allclose(uv_dot, [l * np.cos(theta), l * np.sin(theta)], rtol=1e-6, atol=1e-7)


def test_polar_to_euler_hand_cases():
    np.testing.assert_allclose(dof.polar_to_euler(2.0, 0.0), [2.0, 0.0], atol=1e-7)
    np.testing.assert_allclose(dof.polar_to_euler(2.0, np.pi / 2), [0.0, 2.0], atol=1e-6)
    np.testing.assert_allclose(dof.polar_to_euler(1.0, np.pi), [-1.0, 0.0], atol=1e-6)


def test_forward_applies_normalisation(dof_params):
    """dof_forward == (network on (x - mean) / std) * out_std + out_mean."""
    q, uv, u = _samples(4)
    x = dof.dof_features(q, uv, u)
    raw = dof.DOFNetwork().apply(
        {"params": dof_params.weights}, (x - dof_params.input_mean) / dof_params.input_std
    )
    expected = raw * dof_params.output_std + dof_params.output_mean
    np.testing.assert_allclose(dof.dof_forward(dof_params, x), expected, rtol=1e-6, atol=1e-6)


def test_vmap_equals_loop_and_jit_equals_nojit(dof_params):
    q, uv, u = _samples(16, seed=1)
    batched = jax.vmap(dof.pixel_velocity, in_axes=(None, 0, 0, 0))(dof_params, q, uv, u)
    looped = np.stack([dof.pixel_velocity(dof_params, q[k], uv[k], u[k]) for k in range(16)])
    np.testing.assert_allclose(batched, looped, rtol=1e-5, atol=1e-6)
    jitted = jax.jit(dof.pixel_velocity)(dof_params, q[0], uv[0], u[0])
    np.testing.assert_allclose(jitted, looped[0], rtol=1e-5, atol=1e-6)


def test_no_implicit_rank_promotion(dof_params):
    """Works under the strict rank-promotion mode (diffrax-style conftest)."""
    q, uv, u = _samples(8)
    with jax.numpy_rank_promotion("raise"):
        jax.vmap(dof.pixel_velocity, in_axes=(None, 0, 0, 0))(dof_params, q, uv, u).block_until_ready()
        dof.dof_forward(dof_params, dof.dof_features(q, uv, u)).block_until_ready()


def test_deterministic_without_dropout_stochastic_with(dof_params):
    q, uv, u = _samples(1)
    a = dof.dof_apply(dof_params, q[0], uv[0], u[0])
    b = dof.dof_apply(dof_params, q[0], uv[0], u[0])
    assert np.array_equal(a, b)
    k1, k2 = jax.random.key(1), jax.random.key(2)
    d1 = dof.dof_apply(dof_params, q[0], uv[0], u[0], dropout_key=k1)
    d1_again = dof.dof_apply(dof_params, q[0], uv[0], u[0], dropout_key=k1)
    d2 = dof.dof_apply(dof_params, q[0], uv[0], u[0], dropout_key=k2)
    assert np.array_equal(d1, d1_again)
    assert not np.array_equal(d1, d2)
    assert not np.array_equal(d1, a)


def test_dropout_masks_differ_per_row(dof_params):
    """Batched training forward: each row gets its own dropout mask."""
    q, uv, u = _samples(1)
    x = jnp.tile(dof.dof_features(q, uv, u), (64, 1))
    out = dof.dof_forward(dof_params, x, dropout_key=jax.random.key(0))
    assert len(np.unique(np.asarray(out[:, 0]))) > 1


def test_bad_shapes_raise(dof_params):
    q, uv, u = _samples(1)
    with pytest.raises(ValueError, match="uv must have trailing dimension 2"):
        dof.dof_apply(dof_params, q[0], jnp.zeros(3), u[0])
    with pytest.raises(ValueError, match="input_std must be > 0"):
        dof.init_dof_params(jax.random.key(0), input_std=np.zeros(10))


# --------------------------------------------------------------------------------------------------
# Checkpoints.
# --------------------------------------------------------------------------------------------------


def test_checkpoint_round_trip_bit_identical(dof_params, tmp_path):
    path = tmp_path / "dof.msgpack"
    config = {"train_config": {"steps": 10, "learning_rate": 1e-3}, "command": "pixelmpc train"}
    dof.save_checkpoint(path, dof_params, config)
    assert [p.name for p in tmp_path.iterdir()] == ["dof.msgpack"]  # no temp file left behind
    restored, restored_config = dof.load_checkpoint(path)
    assert restored_config == config
    chex.assert_trees_all_equal(dof_params, restored)  # bit for bit
    chex.assert_trees_all_equal_dtypes(dof_params, restored)
    q, uv, u = _samples(32, seed=4)
    f = jax.jit(jax.vmap(dof.pixel_velocity, in_axes=(None, 0, 0, 0)))
    assert np.array_equal(f(dof_params, q, uv, u), f(restored, q, uv, u))
    assert os.path.getsize(path) < 200_000  # small: 34,690 float32 + header


def test_checkpoint_overwrite_is_atomic_replace(dof_params, tmp_path):
    path = tmp_path / "dof.msgpack"
    dof.save_checkpoint(path, dof_params, {"run": 1})
    dof.save_checkpoint(path, dof_params, {"run": 2})
    assert dof.load_checkpoint(path)[1] == {"run": 2}
    assert len(list(tmp_path.iterdir())) == 1


def test_mismatched_layer_sizes_raise(tmp_path):
    small = dof.DOFNetwork(hidden_sizes=(64, 64))
    weights = small.init({"params": jax.random.key(0)}, jnp.zeros(10))["params"]
    params = dof.init_dof_params(jax.random.key(0)).replace(weights=weights)
    path = tmp_path / "small.msgpack"
    dof.save_checkpoint(path, params, {})
    with pytest.raises(
        ValueError, match=r"layer_sizes: expected \[10, 128, 128, 128, 2\], found \[10, 64, 64, 2\]"
    ):
        dof.load_checkpoint(path)


def test_mismatched_dropout_raises(dof_params, tmp_path, monkeypatch):
    path = tmp_path / "dropout.msgpack"
    monkeypatch.setattr(dof, "DROPOUT_RATE", 0.2)
    dof.save_checkpoint(path, dof_params, {})
    monkeypatch.undo()
    with pytest.raises(ValueError, match="dropout_rate: expected 0.1, found 0.2"):
        dof.load_checkpoint(path)


def test_truncated_and_foreign_files_raise(dof_params, tmp_path):
    path = tmp_path / "dof.msgpack"
    dof.save_checkpoint(path, dof_params, {})
    data = path.read_bytes()
    truncated = tmp_path / "truncated.msgpack"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="corrupted or truncated"):
        dof.load_checkpoint(truncated)
    garbage = tmp_path / "garbage.msgpack"
    garbage.write_bytes(b"\xc1\x00not msgpack at all")
    with pytest.raises(ValueError, match="corrupted or truncated"):
        dof.load_checkpoint(garbage)
    foreign = tmp_path / "foreign.msgpack"
    foreign.write_bytes(serialization.msgpack_serialize({"params": {"w": np.zeros(3)}}))
    with pytest.raises(ValueError, match="format expected 'pixelmpc_jax.dof', found None"):
        dof.load_checkpoint(foreign)


def test_config_must_be_json(dof_params, tmp_path):
    with pytest.raises(TypeError, match="JSON"):
        dof.save_checkpoint(tmp_path / "x.msgpack", dof_params, {"bad": object()})
    assert not list(tmp_path.iterdir())


def test_checkpoint_variant_defaults_to_the_papers_for_old_records():
    assert dof.checkpoint_variant({}) == {"input": "command", "loss": "polar"}
    assert dof.checkpoint_variant({"train_config": {"loss": "endpoint"}}) == {"input": "command", "loss": "endpoint"}
    assert dof.checkpoint_variant({"variant": {"input": "flown", "loss": "polar"}}) == {"input": "flown",
                                                                                        "loss": "polar"}


def test_every_packaged_variant_loads_and_its_record_says_how_it_was_trained():
    """The shipped weights: the paper's (command input), the flown-rate ones, those trained with turned rows, and the
    paper's trained through the racing camera; each record names its input and its camera, and only the turned one
    was trained with rotation augmentation."""
    expected = {"paper": ("command", 0.0, 0.0), "flown": ("flown", 0.0, 0.0), "turned": ("flown", 1.0, 0.0),
                "paper_tilt30": ("command", 0.0, 30.0)}
    assert set(dof.PACKAGED_VARIANTS) == set(expected)
    for variant, (input_, sigma, tilt) in expected.items():
        params, record = dof.load_checkpoint(dof.PACKAGED_VARIANTS[variant])
        assert network_weights.num_trainable_params(params) == 34_690
        assert dof.checkpoint_variant(record)["input"] == input_, variant
        train_config = record.get("train_config", {})
        assert train_config.get("model", train_config).get("rotation_augment", 0.0) == sigma, variant
        beside = network_weights.weights_record(dof.PACKAGED_VARIANTS[variant])
        assert network_weights.trained_camera_tilt_deg(record) == network_weights.trained_camera_tilt_deg(beside) \
            == tilt, variant
        leaves = jax.tree_util.tree_leaves(dof.load_packaged_dof(variant))
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    with pytest.raises(ValueError, match="turned"):
        dof.load_packaged_dof("nonexistent")
