"""``pixelmpc tune``: its arguments and its handler, thin (the search is :mod:`pixelmpc_jax.apps.tuning.search`)."""

from __future__ import annotations

from pixelmpc_jax import arguments as arg


def add_tune(sub) -> None:
    """``pixelmpc tune``: controller settings by search against the speed frontier (docs/tune.md)."""
    from pixelmpc_jax.apps.racing.presets import PRESETS
    from pixelmpc_jax.apps.tuning import search
    from pixelmpc_jax.apps.tuning.space import SPACES

    p = sub.add_parser("tune", help="search controller settings against the speed frontier (Optuna, resumable)")
    p.add_argument("--space", required=True, metavar="|".join(SPACES) + "|FILE",
                   help="the settings searched: a space's name or a JSON file of {dotted setting: {low, high[, log]} "
                        "or {choices}} (docs/tune.md)")
    p.add_argument("--out", type=arg.writable_dir, required=True, help="the study's folder (resumable)")
    p.add_argument("--trials", type=arg.positive_int, default=30,
                   help="completed trials the study must hold; finished ones are never flown again (default 30)")
    p.add_argument("--minutes", type=arg.float_in(0.0, 1e6, lo_open=True), default=None,
                   help="stop starting trials after this many minutes (default: no limit)")
    p.add_argument("--preset", choices=PRESETS, default="best", help="the race whose settings are searched")
    p.add_argument("--seed", type=arg.seed, default=0, help="first training seed (default 0); lap i flies seed + i")
    p.add_argument("--laps", type=arg.positive_int, default=4, help="training laps per trial (default 4)")
    p.add_argument("--nominal-speeds", type=arg.target_speed, nargs="+", default=list(search.NOMINAL_SPEEDS),
                   metavar="V", help="nominal MPPI's target speeds for the frontier (default 7 8 8.5 10; the preset's "
                                     "is added)")
    p.add_argument("--bound", type=arg.float_in(0.0, 10.0, lo_open=True), default=search.LAP_TIME_BOUND,
                   help="a feasible trial's lap time is at most (1 + BOUND) x nominal MPPI's at the same target "
                        "(default 0.1)")
    p.add_argument("--storage", default=None, metavar="URL",
                   help="the study's database (default sqlite:///OUT/study.db); a server URL such as "
                        "postgresql://user@host/db lets several processes or machines share the study")
    p.add_argument("--study", default="tune", help="the study's name in the storage (default tune)")
    p.add_argument("--sampler-seed", type=arg.seed, default=0,
                   help="the TPE sampler's seed (default 0); give each worker of a shared study its own")
    p.add_argument("--reuse", type=arg.grid_dir, nargs="+", default=[], metavar="DIR",
                   help="grid folders (a results.json) whose cells are copied, not flown, where they are the race "
                        "asked (same settings, seeds and laps)")
    p.add_argument("--validate-seed", type=arg.seed, default=None,
                   help="then fly the best trial, the preset and nominal MPPI on held-out seeds from this one")
    p.add_argument("--validate-laps", type=arg.positive_int, default=10, help="held-out laps (default 10)")
    p.add_argument("--validate-course", type=arg.course, default=None, metavar="FILE",
                   help="with --validate-seed, also fly the validation on this course (a course file, e.g. one "
                        "`pixelmpc course` generated that no one tuned on)")

    def check(args) -> None:
        """The search space, checked before anything runs: one line per bad entry, exit code 2."""
        from pixelmpc_jax.apps.tuning.space import SpaceError

        try:
            _setup(args)
        except SpaceError as err:
            p.error("\n".join(err.problems))

    p.set_defaults(func=_cmd_tune, precheck=check)


def _setup(args):
    """The study's :class:`~pixelmpc_jax.apps.tuning.search.TuneSetup` the arguments ask for."""
    from pixelmpc_jax.apps.racing.presets import preset
    from pixelmpc_jax.apps.tuning import search
    from pixelmpc_jax.apps.tuning.space import load_space

    space = load_space(args.space, preset(args.preset))
    return search.TuneSetup(args.preset, tuple(space.values()), tuple(args.nominal_speeds), args.laps, args.seed,
                            args.bound)


def _cmd_tune(args) -> int:
    from pixelmpc_jax import host
    from pixelmpc_jax.apps.tuning import report, search

    host.use_compilation_cache()
    setup = _setup(args)
    study = search.run_tune(setup, args.out, args.trials, args.minutes, args.storage, args.study, args.sampler_seed,
                            reuse=args.reuse)
    print(report.summary(study, args.out))
    if args.validate_seed is not None:
        record = search.validate(study, setup, args.out, args.validate_seed, args.validate_laps, reuse=args.reuse)
        print(report.validation_markdown(record))
        if args.validate_course is not None:
            record = search.validate(study, setup, args.out, args.validate_seed, args.validate_laps,
                                     reuse=args.reuse, course=args.validate_course)
            print(report.validation_markdown(record))
    return 0
