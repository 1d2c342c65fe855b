"""``pixelmpc render``: frames of the AlphaPilot course with their exact and Farneback optical flow
(:func:`~pixelmpc_jax.perception.figures.write_render_figures`)."""

from __future__ import annotations

from pathlib import Path

from pixelmpc_jax import arguments as arg


def add_render(sub) -> None:
    """``pixelmpc render``: rendered frames and their flow."""
    p = sub.add_parser("render", help="render course frames with their exact and Farneback optical flow")
    p.add_argument("--out", type=arg.writable_dir, default=Path("runs/render"), help="output directory")
    p.set_defaults(func=_cmd_render)


def _cmd_render(args) -> int:
    from pixelmpc_jax.perception.figures import write_render_figures

    print(f"rendering the AlphaPilot course: frames, exact and Farneback flow -> {args.out}")
    results = write_render_figures(args.out)
    for name, entry in results.items():
        print(f"  {name}: Farneback vs exact AEE {entry['aee_px']:.2f} px, written to {entry['path']}")
    return 0
