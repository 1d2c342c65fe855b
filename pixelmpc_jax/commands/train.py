"""``pixelmpc train``: a pixel model's training, the DOF's or vdof's, through the one pipeline
(:func:`~pixelmpc_jax.learn.train.run_train`), resumable.

Each model flag sets the field of the model's configuration it is named after (:class:`~pixelmpc_jax.arguments.
FieldFlag`): those of :data:`MODEL_FLAGS` every model's, those of :data:`MODEL_ONLY` one model's (the other model
refuses them); a flag left out keeps the configuration's default.
"""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.arguments import SEED_MAX, FieldFlag
from pixelmpc_jax.commands import EXIT_INTERRUPTED
from pixelmpc_jax.dynamics.dof import PACKAGED_VARIANTS
from pixelmpc_jax.learn.dataset import INPUTS
from pixelmpc_jax.learn.dof_spec import LOSSES, DOFConfig
from pixelmpc_jax.learn.vdof_spec import BOX_CUES, BOX_LOSSES, VDOFConfig

MODELS = {"dof": DOFConfig, "vdof": VDOFConfig}
_DOF, _VDOF = DOFConfig(), VDOFConfig()  # the defaults the help names

MODEL_FLAGS: tuple[FieldFlag, ...] = (
    FieldFlag("--steps", "steps", f"Adam steps (vdof: of its one-step stage; default: dof {_DOF.steps}, vdof "
              f"{_VDOF.steps})", {"type": arg.positive_int}),
    FieldFlag("--batch-size", "batch_size", f"rows per step (dof: pixels, vdof: detections; default: dof "
              f"{_DOF.batch_size}, vdof {_VDOF.batch_size})", {"type": arg.positive_int}),
    FieldFlag("--learning-rate", "learning_rate", f"Adam's peak learning rate, in (0, 1] (default: dof "
              f"{_DOF.learning_rate:g}, vdof {_VDOF.learning_rate:g})", {"type": arg.float_in(0.0, 1.0, lo_open=True)}),
)
MODEL_ONLY: dict[str, tuple[FieldFlag, ...]] = {
    "dof": (
        FieldFlag("--loss", "loss", "polar: the paper's MSE on (l, theta) (default); endpoint: squared flow-vector "
                  "error", {"choices": LOSSES}),
        FieldFlag("--input", "input", "the network's control input: command, the paper's (the rates commanded at the "
                  "frame's tick, default), or flown (the rates flown over the frame: what the MPC's model means)",
                  {"choices": INPUTS}),
        FieldFlag("--rotation-augment", "rotation_augment", "turn training rows by an extra body rate of std SIGMA "
                  "rad/s, label and rate changed exactly (needs --input flown; default 0: off, the paper's)",
                  {"type": arg.float_in(0.0, 6.0, unit="rad/s"), "metavar": "SIGMA"}),
        FieldFlag("--rotation-augment-fraction", "rotation_augment_fraction", "share of the rows turned, in [0, 1] "
                  "(default 1)", {"type": arg.float_in(0.0, 1.0), "metavar": "P"}),
    ),
    "vdof": (
        FieldFlag("--hidden-sizes", "hidden_sizes", "hidden widths of g(uv), comma-separated (default "
                  f"{','.join(map(str, _VDOF.hidden_sizes))})", {"type": arg.widths, "metavar": "W,W"}),
        FieldFlag("--box-loss", "box_loss", "the box size's rate scored absolute or relative (s_dot / s) (default "
                  f"{_VDOF.box_loss})", {"choices": BOX_LOSSES}),
        FieldFlag("--box-cue", "box_cue", "s: the detected box's apparent size, or that per the gate's size (default "
                  f"{_VDOF.box_cue})", {"choices": BOX_CUES}),
        FieldFlag("--rollout-steps", "rollout_steps", "K of the rollout fine-tuning stage, 0: none (default "
                  f"{_VDOF.rollout_steps})", {"type": arg.int_in(0, 1000), "metavar": "K"}),
        FieldFlag("--rollout-train-steps", "rollout_train_steps", "Adam steps of the rollout stage, 0: none (default "
                  f"{_VDOF.rollout_train_steps})", {"type": arg.int_in(0, 10_000_000)}),
        FieldFlag("--rollout-learning-rate", "rollout_learning_rate", "the rollout stage's peak learning rate "
                  f"(default {_VDOF.rollout_learning_rate:g})", {"type": arg.float_in(0.0, 1.0, lo_open=True)}),
        FieldFlag("--rollout-batch-size", "rollout_batch_size", "windows per step of the rollout stage (default "
                  f"{_VDOF.rollout_batch_size})", {"type": arg.positive_int}),
        FieldFlag("--comparison-dof", "comparison_dof", "the packaged DOF the held-out figures are reported beside "
                  f"(default {_VDOF.comparison_dof})", {"choices": sorted(PACKAGED_VARIANTS)}),
    ),
}


def add_train(sub) -> None:
    """``pixelmpc train``: a pixel model's training, the DOF's or vdof's, through the one pipeline."""
    p = sub.add_parser("train", help="train a pixel model (the DOF or vdof) on a collected dataset (resumable)")
    p.add_argument("--model", choices=tuple(MODELS), default="dof",
                   help="dof: the paper's DOF on every pixel's Farneback flow (default); vdof: the velocity-and-depth "
                        "pixel model on the gate detector's frame-to-frame motion (the best preset's)")
    p.add_argument("--data", type=arg.dataset_dir, required=True, help="dataset directory from `pixelmpc collect`")
    p.add_argument("--out", type=arg.writable_dir, default=None, help="output directory (default runs/MODEL_train)")
    for flag in MODEL_FLAGS:
        flag.add_to(p)
    p.add_argument("--seed", type=arg.seed, default=0, help=f"PRNG seed in [0, {SEED_MAX}]")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.msgpack")
    p.add_argument("--ship", action="store_true", help="also copy the weights into the installed package")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    for model, flags in MODEL_ONLY.items():
        group = p.add_argument_group(f"--model {model} only")
        for flag in flags:
            flag.add_to(group)
    p.set_defaults(func=_cmd_train, validate=_check_train)


def _check_train(args) -> str | None:
    """A flag of another model than ``--model`` names is refused; turned rows need the flown input."""
    for model, flags in MODEL_ONLY.items():
        given = [flag.flag for flag in flags if model != args.model and getattr(args, flag.dest) is not None]
        if given:
            return f"argument {given[0]}: applies to --model {model} only"
    if (args.rotation_augment or 0.0) > 0 and args.input != "flown":
        return "argument --rotation-augment: needs --input flown (it turns the rate flown over the frame)"
    return None


def _cmd_train(args) -> int:
    from pixelmpc_jax.learn.train import TrainConfig, run_train

    model = MODELS[args.model](**arg.fields_given(args, MODEL_FLAGS + MODEL_ONLY[args.model]))
    config = TrainConfig(model=model, seed=args.seed, progress=not args.no_progress)
    out = args.out if args.out is not None else Path(f"runs/{args.model}_train")
    record = run_train(args.data, out_dir=out, config=config, resume=args.resume, ship=args.ship)
    return EXIT_INTERRUPTED if record.get("interrupted") else 0
