"""The racing camera's learned pixel models shipped in the package, a race picking them by its camera, and the
``racing`` preset that flies them. Nothing here flies a lap."""

from __future__ import annotations

import math

import jax.numpy as jnp
import pytest

from pixelmpc_jax.apps.racing import presets
from pixelmpc_jax.apps.racing import race as race_lib
from pixelmpc_jax.apps.racing.spec import PACKAGED_WEIGHTS, RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig
from pixelmpc_jax.dynamics import dof, network_weights, vdof
from pixelmpc_jax.world import camera as camera_lib

TILTED = {"dof": "paper_tilt30", "vdof": "vdof_tilt30"}  # each learned model's packaged weights for the racing camera
UNTILTED = {"dof": "paper", "vdof": "vdof"}  # and its default, for the untilted camera


def _own_hash(model: str, name: str) -> str:
    """The fingerprint of a packaged variant read from its file, past the packaged-hash cache."""
    path = PACKAGED_WEIGHTS[model].variants[name]
    params = vdof.load_vdof(path)[0] if model == "vdof" else dof.load_checkpoint(path)[0]
    return network_weights.dof_weights_hash(params)


@pytest.mark.parametrize("model", ["dof", "vdof"])
def test_the_racing_cameras_weights_ship_as_named_variants_with_their_own_fingerprints(model):
    packaged = PACKAGED_WEIGHTS[model]
    path = packaged.variants[TILTED[model]]
    assert path.parent == packaged.variants[UNTILTED[model]].parent and path.with_suffix(".json").exists()
    assert next(iter(packaged.variants)) == UNTILTED[model]  # the default stays first
    params = packaged.load(TILTED[model])
    # the record in the weights file and the one beside it both say the racing camera
    config = vdof.load_vdof(path)[1] if model == "vdof" else dof.load_checkpoint(path)[1]
    assert network_weights.trained_camera_tilt_deg(config) == 30.0
    assert network_weights.trained_camera_tilt_deg(network_weights.weights_record(path)) == 30.0
    assert network_weights.packaged_camera_tilt_deg(packaged.variants[UNTILTED[model]]) == 0.0
    fingerprints = {name: packaged.fingerprint(name) for name in packaged.variants}
    assert fingerprints[TILTED[model]] == network_weights.dof_weights_hash(params) == _own_hash(model, TILTED[model])
    assert len(set(fingerprints.values())) == len(fingerprints)  # every variant its own fingerprint
    assert network_weights.variant_for_camera(packaged.variants, 30.0) == TILTED[model]
    assert network_weights.variant_for_camera(packaged.variants, 0.0) == UNTILTED[model]
    assert network_weights.variant_for_camera(packaged.variants, 20.0) is None
    with pytest.raises(ValueError, match=TILTED[model]):
        packaged.load("nonexistent")


def test_the_untilted_races_keep_their_fingerprints_so_their_keys():
    """A race at camera tilt 0 names the packaged untilted weights by the same fingerprint as before the variants:
    the hash of the default file itself (the default name and no name are one race)."""
    untilted_vdof, untilted_dof = _own_hash("vdof", "vdof"), _own_hash("dof", "paper")
    assert vdof.packaged_vdof_hash() == vdof.packaged_vdof_hash("vdof") == untilted_vdof
    assert dof.packaged_dof_hash() == dof.packaged_dof_hash("paper") == untilted_dof
    best, paper = presets.preset("best"), presets.preset("paper")
    onboard = presets.with_loop(best, "onboard")
    for spec, fingerprint in ((best, untilted_vdof), (onboard, untilted_vdof), (paper, untilted_dof)):
        assert spec.camera_tilt_deg == 0.0 and spec.dof_weights is None
        assert spec.dof_fingerprint() == fingerprint
        assert spec.replace(dof_weights=fingerprint).key() == spec.key()  # as the key was made before
        assert spec.replace(dof_weights=UNTILTED[spec.config.pixel_model]).key() == spec.key()
    # a tilt no packaged weights were trained for keeps the default's fingerprint (and is refused where flown)
    assert best.replace(camera_tilt_deg=20.0).dof_fingerprint() == untilted_vdof


@pytest.mark.parametrize("model", ["dof", "vdof"])
def test_a_race_on_the_racing_camera_flies_its_packaged_weights_with_none_named(model):
    packaged = PACKAGED_WEIGHTS[model]
    spec = RaceSpec("pixelmpc", ControllerConfig(pixel_model=model), camera_tilt_deg=30.0)
    assert spec.dof_weights is None and spec.packaged_variant() == TILTED[model]
    assert spec.dof_fingerprint() == packaged.fingerprint(TILTED[model])
    spec.check_weights(None)
    spec.check_weights(packaged.load(TILTED[model]))
    with pytest.raises(ValueError, match="fingerprint"):
        spec.check_weights(packaged.load(UNTILTED[model]))
    assert network_weights.dof_weights_hash(spec.packaged_dof()) == spec.dof_fingerprint()
    # naming the variant is the same race (one spelling: None), and so are the same weights named by a file's hash
    named = spec.replace(dof_weights=TILTED[model])
    assert named == spec and named.key() == spec.key()
    assert spec.replace(dof_weights=spec.dof_fingerprint()).key() == spec.key()
    assert spec.key() != spec.replace(camera_tilt_deg=0.0).key()
    # the untilted weights named on the racing camera are refused, as the racing camera's are on the untilted one
    with pytest.raises(ValueError, match="trained for the untilted camera: with camera_tilt_deg=30"):
        spec.replace(dof_weights=UNTILTED[model]).check_weights(None)
    with pytest.raises(ValueError, match="trained for the camera tilted up 30 deg: with camera_tilt_deg=0"):
        spec.replace(camera_tilt_deg=0.0, dof_weights=TILTED[model]).check_weights(None)
    # the race function's packaged weights (world.dof None) follow its camera, a float32 tilt included
    for tilt in (math.radians(30.0), jnp.float32(math.radians(30.0))):
        flown = race_lib.packaged_weights_for(model, camera_lib.default_camera(tilt=tilt))
        assert network_weights.dof_weights_hash(flown) == packaged.fingerprint(TILTED[model])
    flat = race_lib.packaged_weights_for(model, camera_lib.default_camera())
    assert network_weights.dof_weights_hash(flat) == packaged.fingerprint(UNTILTED[model])


@pytest.mark.parametrize("model", ["dof", "vdof"])
def test_a_learned_race_at_a_tilt_nothing_ships_for_is_refused_naming_the_shipped_tilts(model):
    spec = RaceSpec("pixelmpc", ControllerConfig(pixel_model=model), camera_tilt_deg=20.0)
    message = (rf"trained for the untilted camera: with camera_tilt_deg=20 fly the projection pixel model or weights "
               rf"trained for that camera \(the package ships {model} weights for camera tilts 0, 30 deg\)$")
    with pytest.raises(ValueError, match=message):
        spec.check_weights(None)
    with pytest.raises(ValueError, match=message):
        race_lib.prepare(spec)
    spec.replace(controller="mppi").check_weights(None)  # nominal MPPI and the projection fly any tilt
    spec.replace(config=ControllerConfig(pixel_model="projection")).check_weights(None)


def test_the_race_command_flies_the_racing_camera_without_weights_named():
    from pixelmpc_jax import cli
    from pixelmpc_jax.commands import race as race_command

    parser = cli.build_parser()
    for argv, variant in ((["--camera-tilt", "30"], "vdof_tilt30"),
                          (["--preset", "paper", "--camera-tilt", "30"], "paper_tilt30"),
                          (["--camera-tilt", "30", "--dof-weights", "vdof_tilt30"], "vdof_tilt30"),
                          (["--preset", "paper", "--dof-weights", "flown"], "flown"),
                          (["--preset", "racing"], "vdof_tilt30")):
        args = parser.parse_args(["race", *argv])
        race_command._check_race(args)
        spec, dof_params = race_command.race_spec(args)
        assert dof_params is None and spec.packaged_variant() == variant, argv
    for argv, refusal in ((["--camera-tilt", "20"], "ships vdof weights for camera tilts 0, 30 deg"),
                          (["--dof-weights", "vdof_tilt30"], "tilted up 30 deg: with camera_tilt_deg=0"),
                          (["--preset", "paper", "--camera-tilt", "30", "--dof-weights", "paper"],
                           "untilted camera: with camera_tilt_deg=30"),
                          (["--dof-weights", "paper_tilt30"], "names the dof model's weights: fly it with "
                                                              "--pixel-model dof"),
                          (["--preset", "paper", "--dof-weights", "vdof"], "--pixel-model vdof")):
        with pytest.raises(ValueError, match=refusal):
            race_command._check_race(parser.parse_args(["race", *argv]))


def test_the_racing_preset_is_best_on_the_racing_camera_at_the_papers_target():
    racing, best = presets.preset("racing"), presets.preset("best")
    assert presets.PRESETS == ("best", "paper", "racing") and presets.DEFAULT_PRESET == "best"
    assert racing.config == presets._best() == best.config and racing.controller == "pixelmpc"
    assert racing.camera_tilt_deg == 30.0 and racing.speed == presets.PAPER_LABEL_SPEEDS[0] == 14.0
    assert racing.config.pixel_model == "vdof" and racing.packaged_variant() == "vdof_tilt30"
    assert racing.dof_fingerprint() == vdof.packaged_vdof_hash("vdof_tilt30") != best.dof_fingerprint()
    assert racing.replace(camera_tilt_deg=0.0, speed=best.speed) == best  # best but for the camera and the target
    racing.check_weights(None)
    assert "not yet searched" in presets.WHY["racing"] and set(presets.WHY) == set(presets.PRESETS)
    nominal = presets.nominal_of(racing)
    assert nominal.controller == "mppi" and nominal.camera_tilt_deg == 30.0 and nominal.speed == 14.0
    assert len({racing.key(), best.key(), nominal.key()}) == 3


def test_every_command_with_a_preset_takes_racing():
    from pixelmpc_jax import cli
    from pixelmpc_jax.apps.tuning import search

    parser = cli.build_parser()
    assert parser.parse_args(["race", "--preset", "racing"]).preset == "racing"
    tune = parser.parse_args(["tune", "--preset", "racing", "--space", "hand-tuned", "--out", "unused"])
    assert tune.preset == "racing"
    # the search holds the racing preset's trials to nominal MPPI seen through the same camera
    setup = search.TuneSetup(preset="racing")
    assert setup.base == presets.preset("racing") and 14.0 in setup.nominal_speeds
    assert {cell.spec.camera_tilt_deg for cell in setup.nominal_cells()} == {30.0}
    at_target = setup.nominal_cell(14.0).spec
    assert at_target.controller == "mppi" and at_target.camera_tilt_deg == 30.0 and at_target.speed == 14.0
    # the best preset's nominal frontier is the one it always flew (the same keys)
    from pixelmpc_jax.apps.experiments import frontier

    best = search.TuneSetup()
    assert [c.spec.key() for c in best.nominal_cells()] == [frontier.nominal_cell(v, best.base.max_time_s).spec.key()
                                                            for v in best.nominal_speeds]
