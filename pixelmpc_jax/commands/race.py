"""``pixelmpc race``: one race flown by PixelMPC beside nominal MPPI in the closed loop (the main job).

A race starts from a preset (``--preset``) or a saved race (``--config``), and each flag of :data:`RACE_FLAGS` sets
the one field of the :class:`~pixelmpc_jax.apps.racing.spec.RaceSpec` it names
(:class:`~pixelmpc_jax.arguments.FieldFlag`: a dotted path into the spec, ``speed``, ``config.mppi.temperature``,
``guards.detection_gate_px``). :func:`race_spec` reads that table and builds the spec, before anything runs; the
handler hands it to :func:`~pixelmpc_jax.apps.racing.compare.run_compare`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.apps.racing.presets import DEFAULT_PRESET, LOOPS, PRESETS, preset, with_loop
from pixelmpc_jax.apps.racing.spec import CAMERA_TILT_MAX_DEG, MAPS, RaceSpec
from pixelmpc_jax.arguments import MAX_TIME_S, SEED_MAX, FieldFlag
from pixelmpc_jax.commands import EXIT_FAILED, EXIT_INTERRUPTED
from pixelmpc_jax.control.costs import HEADING_WEIGHT_RANGE, VEHICLE_RADIUS_RANGE
from pixelmpc_jax.control.mppi_checks import NOISE_EXPONENT_RANGE, TEMPERATURE_RANGE
from pixelmpc_jax.control.pixelmpc import (
    BORDER_MARGIN_RANGE,
    C_PIXEL_RANGE,
    DISTURBANCE_TIME_CONSTANT_RANGE,
    LOOK_AHEAD_FROM,
    LOOK_AHEAD_MODELS,
    LOOK_AHEAD_RANGE,
    PARTIAL_TARGETS,
    PIXEL_COSTS,
    PIXEL_MODELS,
    T_F_RANGE,
    TARGET_PRIORS,
)
from pixelmpc_jax.dynamics.dof import PACKAGED_VARIANTS
from pixelmpc_jax.dynamics.network_weights import dof_weights_hash
from pixelmpc_jax.sim.controllers import CONTROLLERS
from pixelmpc_jax.sim.env import DETECTORS, ESTIMATORS, GATE_SWITCHES
from pixelmpc_jax.sim.faults import FAULT_LEVELS
from pixelmpc_jax.timing import LAP_TIME_LIMIT_S
from pixelmpc_jax.world.course import COURSES

# Every flag of the race after --preset/--config, in the order --help lists them. A flag of a controller setting
# (a field under "config") lists both presets' value in its help.
RACE_FLAGS: tuple[FieldFlag, ...] = (
    FieldFlag("--controller", None, "fly one controller alone: pixelmpc or mppi, the paper's nominal baseline "
              "(default: both, at the same target and seeds)", {"choices": CONTROLLERS, "default": None}),
    FieldFlag("--dof-weights", "dof_weights", "the learned pixel model's weights: a packaged DOF variant (paper: "
              "command input; flown: the flown-rate weights; turned: trained with turned rows) or a weights file from "
              "`pixelmpc train`; with --pixel-model vdof: vdof, the packaged vdof weights (its default), or a file) "
              "(default: the preset's)", {"metavar": "|".join(PACKAGED_VARIANTS) + "|vdof|FILE"}),
    FieldFlag("--detector", "detector", "target detection: clipped, the projection of the true gate cut at the image "
              "border as a camera's detector reports it (the corners in view, a centre from the visible outline); "
              "ideal, the projection reported whole, in the image or not; or image, OpenCV on rendered frames "
              "(default: the preset's, clipped)", {"choices": DETECTORS}),
    FieldFlag("--course", "course", "alphapilot, straight (five gates 20 m apart, the paper's straight lane) or a "
              "course file in the format of pixelmpc_jax/data/alphapilot_course.json (`pixelmpc course` makes one) "
              "(default: the preset's, alphapilot)", {"type": arg.course, "metavar": "|".join(COURSES) + "|FILE"}),
    FieldFlag("--estimator", "estimator", "state the controller acts on: truth, pf (the paper's particle filter) or "
              "eskf (an error-state Kalman filter with IMU bias states) (default: the preset's, truth)",
              {"choices": ESTIMATORS}),
    FieldFlag("--video", None, "write OUT/onboard.mp4 of PixelMPC's first lap: predicted (green) and actual (red) "
              "pixel", {"action": "store_true"}),
    FieldFlag("--no-compile-cache", None, "compile afresh (by default compiled steps are kept in the user's cache "
              "folder, ~/.cache/pixelmpc-jax, so a second run starts faster)", {"action": "store_true"}),
    FieldFlag("--pixel-model", "config.pixel_model", "PixelMPC's pixel model: dof, the paper's DOF network; vdof, the "
              "learned model with velocity and the gate's size; or projection, the PAMPC-style projection of the "
              "known gate", {"choices": PIXEL_MODELS}),
    FieldFlag("--t-f", "config.t_f", f"PixelMPC pixel-cost horizon t_f, in {T_F_RANGE.interval} (the MPC "
              "horizon)", {"type": arg.float_range(T_F_RANGE)}),
    FieldFlag("--c-pixel", "config.c_pixel", f"PixelMPC pixel-cost weight, in {C_PIXEL_RANGE.interval}",
              {"type": arg.float_range(C_PIXEL_RANGE)}),
    FieldFlag("--pixel-cost", "config.pixel_cost", "PixelMPC pixel cost: l1, the paper's distance from the image "
              "centre, or border, a barrier on the image border that charges only a gate leaving the view",
              {"choices": PIXEL_COSTS}),
    FieldFlag("--target-prior", "config.target_prior", "what PixelMPC's pixel cost charges while the target is not "
              "detected: none, the paper's (no pixel cost); map, its pixel projected from the map and the estimate; "
              "kept, its last pixel moved on by the pixel model since it was last seen; or seeded, kept once seen "
              "and from the map before", {"choices": TARGET_PRIORS}),
    FieldFlag("--partial-target", "config.partial_target", "where PixelMPC's target pixel starts when the detector "
              "reports the gate cut by the image border: detected, the centre of its visible outline (the paper's); "
              "map, the gate projected from the map and the estimate", {"choices": PARTIAL_TARGETS}),
    FieldFlag("--look-ahead", "config.look_ahead", "PixelMPC's weight, relative to the target's, of the next gate's "
              "pixel cost on the predicted states past the target (its pixel from the map and the estimate); 0: none, "
              f"the paper's; in {LOOK_AHEAD_RANGE.interval}", {"type": arg.float_range(LOOK_AHEAD_RANGE)}),
    FieldFlag("--look-ahead-model", "config.look_ahead_model", "what predicts the next gate's pixel along the horizon "
              "with the look-ahead: own, PixelMPC's pixel model; projection, the gate's centre from the map projected "
              "through each predicted pose (map-aided)", {"choices": LOOK_AHEAD_MODELS}),
    FieldFlag("--look-ahead-from", "config.look_ahead_from", "from which predicted state the look-ahead charges the "
              "next gate: plane, once the sample has passed the target's plane (a sample that stops short of the gate "
              "escapes it); plan, from there or from the step the current plan passes it, the earlier",
              {"choices": LOOK_AHEAD_FROM}),
    FieldFlag("--border-margin", "config.border_margin", "where the border cost starts, as a fraction of the image "
              f"inside the border, in {BORDER_MARGIN_RANGE.interval}", {"type": arg.float_range(BORDER_MARGIN_RANGE)}),
    FieldFlag("--noise-exponent", "config.mppi.noise_exponent", "MPPI sampling noise coloured as 1/f^beta along the "
              f"horizon, beta in {NOISE_EXPONENT_RANGE.interval} (0: white, the paper's)",
              {"type": arg.float_range(NOISE_EXPONENT_RANGE)}),
    FieldFlag("--heading-weight", "config.racing.heading_weight", "share of the racing cost's attitude term that pins "
              f"the heading to the path, in {HEADING_WEIGHT_RANGE.interval} (1: the paper's)",
              {"type": arg.float_range(HEADING_WEIGHT_RANGE)}),
    FieldFlag("--clearance", "config.racing.vehicle_radius", "m: the racing cost's clearance to gate frames, floor "
              f"and walls (the world keeps the vehicle's 0.1 m), in {VEHICLE_RADIUS_RANGE.interval}",
              {"type": arg.float_range(VEHICLE_RADIUS_RANGE)}),
    FieldFlag("--temperature", "config.mppi.temperature", f"MPPI lambda, in {TEMPERATURE_RANGE.interval}",
              {"type": arg.float_range(TEMPERATURE_RANGE)}),
    FieldFlag("--samples", "config.mppi.num_samples", "MPPI samples per step, in [1, 2^20]",
              {"type": arg.int_in(1, 2**20)}),
    FieldFlag("--speed", "speed", f"target speed, m/s, in (0, {arg.TARGET_SPEED_MAX:g}] (default: the preset's; best "
              "8.5, the paper's pace; paper 14, the paper's label)", {"type": arg.target_speed}),
    FieldFlag("--laps", "laps", "laps per controller (default 1)", {"type": arg.positive_int}),
    FieldFlag("--seed", "seed", f"seed of the first lap, in [0, {SEED_MAX}]; lap i uses seed + i (default 0)",
              {"type": arg.seed}),
    FieldFlag("--out", None, "output directory", {"type": arg.writable_dir, "default": Path("runs/race")}),
    FieldFlag("--batch", None, "laps per batched (vmapped) call; raise it on a GPU (default 1)",
              {"type": arg.positive_int, "default": 1}),
    FieldFlag("--perturb", "perturb", "perturb the gates per lap within the AlphaPilot bounds",
              {"action": "store_true"}),
    FieldFlag("--map", "map", "with --perturb, what the controller and the filter read: surveyed, the nominal course, "
              "while the world flies the perturbed gates; known, the perturbed course itself (as perturbed races flew "
              "before) (default: surveyed)", {"choices": MAPS}),
    FieldFlag("--gate-switch", "gate_switch", "with --estimator pf or eskf, when the controller's target moves to the "
              "next gate: estimate, when the estimate crosses the map's gate (a lap whose target then parts from the "
              "world's ends as target_mismatch); truth, when the true position passes the true gate (as races on a "
              "filter flew before) (default: estimate)", {"choices": GATE_SWITCHES}),
    FieldFlag("--camera-tilt", "camera_tilt_deg", "the onboard camera tilted up on its mount by DEG degrees, in "
              f"[0, {CAMERA_TILT_MAX_DEG:g}], for both controllers, the detector and the measure (default 0, the "
              "paper's); the packaged learned pixel models are trained for 0, so fly --pixel-model projection",
              {"type": arg.float_in(0.0, CAMERA_TILT_MAX_DEG, unit="deg"), "metavar": "DEG"}),
    FieldFlag("--max-time", "max_time_s", f"timeout per lap, s, in (0, {MAX_TIME_S:g}] (default "
              f"{LAP_TIME_LIMIT_S:g})", {"type": arg.float_in(0.0, MAX_TIME_S, lo_open=True, unit="s")}),
    FieldFlag("--model-latency", "config.model_latency_ticks", "ticks of actuation latency the controller's model "
              "predicts across, in [0, 3] (0: none)", {"type": arg.int_in(0, 3)}),
    FieldFlag("--disturbance-observer", "config.disturbance_time_constant_s", "s: the controller's model learns an "
              f"external push (wind, model error) with this time constant, in "
              f"{DISTURBANCE_TIME_CONSTANT_RANGE.interval}",
              {"type": arg.float_range(DISTURBANCE_TIME_CONSTANT_RANGE)}),
    # each --fault entry sets one or more fields of the race's faults (a later entry of a field wins)
    FieldFlag("--fault", "faults", "a fault of the world the controller does not model (repeatable): a setting of "
              "pixelmpc_jax.sim.faults.Faults (wind=3,0,0 m/s; gust=1.5 m/s; mass_factor=1.1; latency_ticks=1; "
              "miss_rate=0.2; map_error_m=0.3; ...) or a named fault at a level "
              f"({', '.join((*FAULT_LEVELS, 'combined'))}=moderate|severe) (default: none)",
              {"type": arg.fault, "action": "append", "metavar": "NAME=VALUE"}),
    FieldFlag("--detection-gate", "guards.detection_gate_px", "with --estimator pf: reject a detection farther than PX "
              "pixels from where the filter's particles put the gate (default: off)",
              {"type": arg.float_in(0.0, 1e4, lo_open=True, unit="px"), "metavar": "PX"}),
    FieldFlag("--pf-recover", "guards.recover_error_px", "with --estimator pf: re-spread the particles when no "
              "particle explains a detection within PX pixels summed over its corners, N detections in a row "
              "(--pf-recover-after; default: off)", {"type": arg.float_in(0.0, 1e5, lo_open=True, unit="px"),
                                                    "metavar": "PX"}),
    FieldFlag("--pf-recover-after", "guards.recover_after_ticks", "with --pf-recover: re-spread after N unexplained "
              "detections in a row (default: 1; 3 lets one false detection pass without a re-spread)",
              {"type": arg.int_in(1, 1000), "metavar": "N"}),
    FieldFlag("--pf-imu-bias", "guards.imu_bias_std", "with --estimator pf: the filter estimates its IMU's biases, "
              "each particle carrying its own, spread by ACCEL m/s^2 and GYRO rad/s (e.g. 0.3,0.02; default: off)",
              {"type": arg.imu_bias_std, "metavar": "ACCEL,GYRO"}),
    FieldFlag("--eskf-map-sigma", "eskf.map_sigma_m", "with --estimator eskf: each gate stands within M m per axis "
              "(1 sigma) of where the map says, so a gate's corners share that offset in the filter's update (0: an "
              "exact map; default: 0.2, a tape-measured course)",
              {"type": arg.float_in(0.0, 100.0, unit="m"), "metavar": "M"}),
    FieldFlag("--eskf-align", "eskf.align_s", "with --estimator eskf: the filter averages S s of its IMU's readings at "
              "rest before the lap (on the pad) and learns the gyro bias and the accelerometer's along gravity from "
              "them (2 is a usual pre-flight wait; default: 0, none)",
              {"type": arg.float_in(0.0, 60.0, unit="s"), "metavar": "S"}),
    FieldFlag("--eskf-noise-adapt-rate", "eskf.noise_adapt_rate", "with --estimator eskf: the corners' noise follows "
              "what the filter's innovations show, moving by RATE of the way at each detection, never below its 2 px "
              "(0.05 takes a 6 px detector in a few seconds; default: 0, the noise stays 2 px)",
              {"type": arg.float_in(0.0, 1.0), "metavar": "RATE"}),
)


def add_race(sub) -> None:
    """``pixelmpc race``: the race to start from, then :data:`RACE_FLAGS`."""
    p = sub.add_parser("race", help="PixelMPC beside nominal MPPI on the AlphaPilot course, in the closed loop")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--preset", choices=PRESETS, default=DEFAULT_PRESET,
                       help="the race to start from: best (default), the best configuration measured on the speed "
                            "frontier at the paper's pace; paper, the paper's formulation at its 14 m/s target. Every "
                            "other flag overrides one field of it")
    start.add_argument("--config", type=Path, default=None, metavar="FILE",
                       help="start from a saved race instead of a preset: a RaceSpec record in JSON, as `pixelmpc "
                            "tune` writes its best.json; every other flag overrides one field of it")
    p.add_argument("--loop", choices=tuple(LOOPS), default=None,
                   help="the loop the race flies, set on the race it starts from before every other flag: onboard, "
                        "only what the drone has (--detector image, --estimator eskf, --gate-switch estimate, "
                        "--map surveyed); truth, the controller on the true state (--detector clipped, --estimator "
                        "truth) (default: the starting race's, the presets' truth)")
    for flag in RACE_FLAGS:
        flag.add_to(p, _help(flag))
    p.set_defaults(func=_cmd_race, validate=arg.seed_range, precheck=_check_race)


def _help(flag: FieldFlag) -> str:
    """A flag's help; a controller setting's shows both presets' value of it (building a preset creates no JAX
    array: no backend starts)."""
    if flag.field is None or not flag.field.startswith("config."):
        return flag.help
    shown = {name: _field_value(preset(name), flag.field) for name in ("best", "paper")}
    shown = ", ".join(f"{name} {value:g}" if isinstance(value, float) else f"{name} {value}"
                      for name, value in shown.items())
    return f"{flag.help} (default: the preset's; {shown})"


def _field_value(spec: RaceSpec, field: str):
    """The value of the spec's field at the dotted path ``field``."""
    value = spec
    for name in field.split("."):
        value = getattr(value, name)
    return value


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
    if args.dof_weights == "vdof":  # the packaged vdof weights: the vdof model's default
        if spec.config.pixel_model != "vdof":
            raise ValueError("--dof-weights vdof names the vdof model's weights: fly it with --pixel-model vdof")
        spec = spec.replace(dof_weights=None)
    dof_params = None
    if spec.dof_weights is not None and spec.dof_weights not in PACKAGED_VARIANTS:
        dof_params = _read_weights(Path(spec.dof_weights), spec.config.pixel_model)
        spec = spec.replace(dof_weights=dof_weights_hash(dof_params))
    return spec, dof_params


def _read_weights(path: Path, pixel_model: str):
    """The pixel model's weights in the weights file ``--dof-weights`` names (a DOF or, for "vdof", a vdof
    checkpoint)."""
    if pixel_model == "vdof":
        from pixelmpc_jax.dynamics import vdof

        return vdof.load_vdof(path)[0]
    from pixelmpc_jax.dynamics import dof

    return dof.load_checkpoint(path)[0]


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
