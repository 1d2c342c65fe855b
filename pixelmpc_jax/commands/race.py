"""``pixelmpc race``: one race flown by PixelMPC beside nominal MPPI in the closed loop (the main job).

A race starts from a preset (``--preset``) or a saved race (``--config``), and each flag of :data:`RACE_FLAGS` sets
the one field of the :class:`~pixelmpc_jax.apps.racing.spec.RaceSpec` it names
(:class:`~pixelmpc_jax.arguments.FieldFlag`: a dotted path into the spec, ``speed``, ``config.mppi.temperature``,
``guards.detection_gate_px``). The flag's help, range and choices are that field's own
(:func:`~pixelmpc_jax.settings.setting`): a range lives once, and the flag refuses what the configuration refuses.
:func:`race_spec` reads that table and builds the spec, before anything runs; the handler hands it to
:func:`~pixelmpc_jax.apps.racing.compare.run_compare`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax import settings
from pixelmpc_jax.apps.racing.presets import DEFAULT_PRESET, LOOPS, PRESETS, preset, with_loop
from pixelmpc_jax.apps.racing.spec import PACKAGED_NAMES, PACKAGED_WEIGHTS, RaceSpec
from pixelmpc_jax.arguments import FieldFlag
from pixelmpc_jax.commands import EXIT_FAILED, EXIT_INTERRUPTED
from pixelmpc_jax.dynamics.network_weights import dof_weights_hash
from pixelmpc_jax.sim.controllers import CONTROLLERS
from pixelmpc_jax.sim.faults import FAULT_LEVELS
from pixelmpc_jax.world.course import COURSES

_DEFAULT_RACE = RaceSpec()  # the race whose fields describe the settings (building it creates no JAX array)


def _setting(flag: str, field: str, **options) -> FieldFlag:
    """The flag of the race's setting ``field``: help, range or choices from the field's description
    (:func:`~pixelmpc_jax.arguments.setting_flag`), ``options`` beside them."""
    return arg.setting_flag(flag, _DEFAULT_RACE, field, **options)


# Every flag of the race after --preset/--config, in the order --help lists them: a flag and the field of the race it
# sets, its help, range and choices read from that field (each setting's range lives once, in its field). A flag of a
# controller setting (a field under "config") lists each preset's value in its help.
RACE_FLAGS: tuple[FieldFlag, ...] = (
    FieldFlag("--controller", None, "fly one controller alone: pixelmpc or mppi, the paper's nominal baseline "
              "(default: both, at the same target and seeds)", {"choices": CONTROLLERS, "default": None}),
    _setting("--dof-weights", "dof_weights", metavar="|".join(PACKAGED_NAMES) + "|FILE"),
    _setting("--detector", "detector"),
    _setting("--course", "course", type=arg.course, metavar="|".join(COURSES) + "|FILE"),
    _setting("--estimator", "estimator"),
    FieldFlag("--video", None, "write OUT/onboard.mp4 of PixelMPC's first lap: predicted (green) and actual (red) "
              "pixel", {"action": "store_true"}),
    FieldFlag("--no-compile-cache", None, "compile afresh (by default compiled steps are kept in the user's cache "
              "folder, ~/.cache/pixelmpc-jax, so a second run starts faster)", {"action": "store_true"}),
    _setting("--pixel-model", "config.pixel_model"),
    _setting("--t-f", "config.t_f"),
    _setting("--c-pixel", "config.c_pixel"),
    _setting("--pixel-cost", "config.pixel_cost"),
    _setting("--target-prior", "config.target_prior"),
    _setting("--partial-target", "config.partial_target"),
    _setting("--look-ahead", "config.look_ahead"),
    _setting("--look-ahead-model", "config.look_ahead_model"),
    _setting("--look-ahead-from", "config.look_ahead_from"),
    _setting("--border-margin", "config.border_margin"),
    _setting("--noise-exponent", "config.mppi.noise_exponent"),
    _setting("--heading-weight", "config.racing.heading_weight"),
    _setting("--clearance", "config.racing.vehicle_radius"),
    _setting("--temperature", "config.mppi.temperature"),
    _setting("--samples", "config.mppi.num_samples"),
    _setting("--speed", "speed"),
    _setting("--laps", "laps"),
    _setting("--seed", "seed"),
    FieldFlag("--out", None, "output directory", {"type": arg.writable_dir, "default": Path("runs/race")}),
    FieldFlag("--batch", None, "laps per batched (vmapped) call; raise it on a GPU (default 1)",
              {"type": arg.positive_int, "default": 1}),
    _setting("--perturb", "perturb"),
    _setting("--map", "map"),
    _setting("--gate-switch", "gate_switch"),
    _setting("--gate-paint", "gate_paint"),
    _setting("--candidates", "association.max_candidates", metavar="K"),
    _setting("--association-gate", "association.gate_px", metavar="PX"),
    _setting("--association-ratio", "association.ratio", metavar="RATIO"),
    _setting("--imu", "imu"),
    _setting("--start-error", "start_error"),
    _setting("--gates", "gates"),
    _setting("--survey-error", "survey_error"),
    _setting("--camera-tilt", "camera_tilt_deg", metavar="DEG"),
    _setting("--max-time", "max_time_s"),
    _setting("--model-latency", "config.model_latency_ticks"),
    _setting("--disturbance-observer", "config.disturbance_time_constant_s"),
    # each --fault entry sets one or more fields of the race's faults (a later entry of a field wins)
    FieldFlag("--fault", "faults", "a fault of the world the controller does not model (repeatable): a setting of "
              "pixelmpc_jax.sim.faults.Faults (wind=3,0,0 m/s; gust=1.5 m/s; mass_factor=1.1; latency_ticks=1; "
              "miss_rate=0.2; map_error_m=0.3; ...) or a named fault at a level "
              f"({', '.join((*FAULT_LEVELS, 'combined'))}=moderate|severe) (default: none)",
              {"type": arg.fault, "action": "append", "metavar": "NAME=VALUE"}),
    _setting("--detection-gate", "guards.detection_gate_px", metavar="PX"),
    _setting("--pf-recover", "guards.recover_error_px", metavar="PX"),
    _setting("--pf-recover-after", "guards.recover_after_ticks", metavar="N"),
    _setting("--pf-imu-bias", "guards.imu_bias_std", type=arg.imu_bias_std, metavar="ACCEL,GYRO"),
    _setting("--eskf-map-sigma", "eskf.map_sigma_m", metavar="M"),
    _setting("--eskf-align", "eskf.align_s", metavar="S"),
    _setting("--eskf-noise-adapt-rate", "eskf.noise_adapt_rate", metavar="RATE"),
)


def add_race(sub) -> None:
    """``pixelmpc race``: the race to start from, then :data:`RACE_FLAGS`."""
    p = sub.add_parser("race", help="PixelMPC beside nominal MPPI on the AlphaPilot course, in the closed loop")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--preset", choices=PRESETS, default=DEFAULT_PRESET,
                       help="the race to start from: best (default), the best configuration measured on the speed "
                            "frontier at the paper's pace; paper, the paper's formulation at its 14 m/s target; "
                            "racing, best's settings on the racing camera (tilted up 30 deg, its own vdof weights) at "
                            "14 m/s. Every other flag overrides one field of it")
    start.add_argument("--config", type=Path, default=None, metavar="FILE",
                       help="start from a saved race instead of a preset: a RaceSpec record in JSON, as `pixelmpc "
                            "tune` writes its best.json; every other flag overrides one field of it")
    p.add_argument("--loop", choices=tuple(LOOPS), default=None,
                   help="the loop the race flies, set on the race it starts from before every other flag: onboard, "
                        "only what the drone has (--detector image, --estimator eskf, --gate-switch estimate, "
                        "--map surveyed); truth, the controller on the true state (--detector clipped, --estimator "
                        "truth) (default: the starting race's, the presets' truth)")
    presets = {name: preset(name) for name in PRESETS}
    for flag in RACE_FLAGS:
        flag.add_to(p, _help(flag, presets))
    p.set_defaults(func=_cmd_race, validate=arg.seed_range, precheck=_check_race)


def _help(flag: FieldFlag, presets: dict) -> str:
    """A flag's help with its default: the value both ``presets`` (``{name: RaceSpec}``) give its field, or each
    preset's where they differ and for every controller setting (building a preset creates no JAX array: no backend
    starts). A flag that sets no described setting, or a switch, keeps its own help."""
    if flag.field is None or flag.options.get("action") == "store_true":
        return flag.help
    field, _ = settings.field_at(_DEFAULT_RACE, flag.field)
    if not settings.described(field):
        return flag.help
    values = {name: settings.field_at(race, flag.field)[1] for name, race in presets.items()}
    shown = {name: _shown(value, field) for name, value in values.items()}
    if len(set(shown.values())) == 1 and not flag.field.startswith("config."):
        one = next(iter(values.values()))
        return f"{flag.help} (default{':' if one is None else ''} {shown['best']})"
    return f"{flag.help} (default: the preset's; {', '.join(f'{name} {value}' for name, value in shown.items())})"


def _shown(value, field) -> str:
    """A setting's value as --help shows it: a float in its shortest form, None as what it means ("off")."""
    if value is None:
        return field.metadata["none"]
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, tuple):
        return ",".join(_shown(v, field) for v in value)
    return str(value)


def _fields_given(args) -> dict:
    """``{dotted field of the RaceSpec: value}`` of every flag of :data:`RACE_FLAGS` given; a ``--fault`` entry sets
    the fields of the race's faults it names (a later entry of a field wins)."""
    fields = arg.fields_given(args, RACE_FLAGS)
    fields.update({f"faults.{name}": value for entry in fields.pop("faults", ()) for name, value in entry.items()})
    return fields


def race_spec(args):
    """The race the arguments ask for, and the learned pixel model's weights when a weights file names them (None for
    packaged weights, which the spec names by name).

    The race is the preset (or the saved race of ``--config``), on the loop of ``--loop`` if given
    (:func:`~pixelmpc_jax.apps.racing.presets.with_loop`), with the field of each flag given set, all at once
    (:meth:`~pixelmpc_jax.apps.racing.spec.RaceSpec.with_fields`; a ValueError names a setting the library refuses); a
    weights file enters the spec as its fingerprint."""
    base = RaceSpec.from_record(json.loads(args.config.read_text())) if args.config else preset(args.preset)
    if args.loop:
        base = with_loop(base, args.loop)
    fields = _fields_given(args)
    spec = base.with_fields(fields)
    kalman = [flag.flag for flag in RACE_FLAGS if flag.field in fields and flag.field.startswith("eskf.")]
    if kalman and spec.estimator != "eskf":
        raise ValueError(f"{kalman[0]} sets the Kalman filter: fly it with --estimator eskf")
    if fields.get("gate_paint") == "alike" and spec.detector != "image":
        raise ValueError("--gate-paint alike paints the rendered gates: fly it with --detector image (or --loop "
                         "onboard)")
    associated = [flag.flag for flag in RACE_FLAGS if flag.field in fields and flag.field.startswith("association.")]
    if associated and spec.gate_paint != "alike":
        raise ValueError(f"{associated[0]} sets the association of gates painted alike: fly it with --gate-paint alike")
    filtered = [flag.flag for flag in RACE_FLAGS if flag.field in ("imu", "start_error") and fields.get(flag.field)]
    if filtered and spec.estimator == "truth":
        raise ValueError(f"{filtered[0]} acts on a filter: fly it with --estimator pf or eskf")
    if fields.get("gates") == "estimated" and spec.estimator != "eskf":
        raise ValueError("--gates estimated are the Kalman filter's states: fly it with --estimator eskf (or --loop "
                         "onboard)")
    if fields.get("survey_error") and spec.perturb:
        raise ValueError("--survey-error draws the gates about the map: with --perturb they are moved within their "
                         "bounds instead")
    for model, packaged in PACKAGED_WEIGHTS.items():  # a packaged name names one model's weights
        if args.dof_weights in packaged.variants and spec.config.pixel_model != model:
            raise ValueError(f"--dof-weights {args.dof_weights} names the {model} model's weights: fly it with "
                             f"--pixel-model {model}")
    dof_params = None
    if spec.dof_weights is not None and spec.dof_weights not in PACKAGED_NAMES:
        dof_params, record = _read_weights(Path(spec.dof_weights), spec.config.pixel_model)
        spec = spec.replace(dof_weights=dof_weights_hash(dof_params))
        spec.check_weights(dof_params, record)  # weights from a file serve the camera their record states
    return spec, dof_params


def _read_weights(path: Path, pixel_model: str):
    """The pixel model's weights in the weights file ``--dof-weights`` names (a DOF or, for "vdof", a vdof
    checkpoint) and their record."""
    if pixel_model == "vdof":
        from pixelmpc_jax.dynamics import vdof

        return vdof.load_vdof(path)
    from pixelmpc_jax.dynamics import dof

    return dof.load_checkpoint(path)


def _controllers(args) -> tuple[str, ...]:
    return (args.controller,) if args.controller else ("pixelmpc", "mppi")


def _check_race(args) -> None:
    """Build the race and its controllers before anything runs: a ValueError names a setting the library refuses,
    and a missing or damaged weights or course file is refused."""
    from pixelmpc_jax.world.course import make_course

    spec, dof_params = race_spec(args)
    make_course(spec.course)  # a course file's bad field is named here
    for controller in _controllers(args):
        flown = spec.replace(controller=controller)
        flown.check_weights(dof_params)  # a learned pixel model flown with the camera it was trained for
        flown.policy()


def _cmd_race(args) -> int:
    from pixelmpc_jax import host
    from pixelmpc_jax.apps.racing import compare
    from pixelmpc_jax.world.course import course_title

    if not args.no_compile_cache:
        host.use_compilation_cache()
    spec, dof_params = race_spec(args)
    controllers = _controllers(args)
    source = (f"config {args.config}" if args.config else f"preset {args.preset}") + \
        (f" on the {args.loop} loop" if args.loop else "")
    print(f"{source}: {' and '.join(compare.LABELS[c] for c in controllers)} racing {course_title(spec.course)} at "
          f"{spec.speed:g} m/s, {spec.laps} lap(s) each, seeds {spec.seed}..{spec.seed + spec.laps - 1}, "
          f"output {args.out}")
    record = compare.run_compare(spec, controllers, out=args.out, preset=str(args.config or args.preset),
                                 batch_size=args.batch, video=args.video, dof_params=dof_params)
    if any(results["laps"] for results in record["controllers"].values()):
        print(compare.side_by_side(record))
        written = [p for p in ("metrics.json", *(f"ticks_{c}.npz" for c in controllers), "trajectories.png",
                               "visibility.png") if (args.out / p).exists()]
        print(f"wrote {', '.join(str(args.out / p) for p in written)}")
    if record["interrupted"]:
        print(f"interrupted; the finished laps are in {args.out / 'metrics.json'} and its ticks_*.npz",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    laps = [lap for results in record["controllers"].values() for lap in results["laps"]]
    if not any(lap.get("success") for lap in laps):
        print(f"no lap succeeded ({len(laps)} flown)", file=sys.stderr)
        return EXIT_FAILED
    return 0
