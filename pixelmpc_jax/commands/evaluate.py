"""``pixelmpc evaluate``: a pixel model's accuracy, its AEE against the baselines, its multi-step error and figures
(:func:`~pixelmpc_jax.learn.evaluate.run_evaluate`)."""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg


def add_evaluate(sub) -> None:
    """``pixelmpc evaluate``: the DOF's accuracy."""
    p = sub.add_parser("evaluate", help="DOF accuracy: AEE, baselines, multi-step error, figures")
    p.add_argument("--weights", type=arg.weights_file, default=None,
                   help="weights file (default: the shipped weights)")
    p.add_argument("--data", type=arg.dataset_dir, default=None,
                   help="dataset directory (default: collect a small seeded held-out set)")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/dof_eval"))
    p.add_argument("--horizon", type=arg.positive_int, default=80, help="multi-step horizon (default 80)")
    p.set_defaults(func=_cmd_evaluate, precheck=_check_weights)


def _check_weights(args) -> None:
    """Read the weights file before anything is written (a ValueError names what is wrong with it)."""
    if args.weights is not None:
        from pixelmpc_jax.learn.evaluate import read_weights

        read_weights(args.weights)


def _cmd_evaluate(args) -> int:
    from pixelmpc_jax.learn.evaluate import run_evaluate

    run_evaluate(weights=args.weights, data_dir=args.data, out_dir=args.out, horizon=args.horizon)
    return 0
