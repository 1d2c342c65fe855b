"""The ``pixelmpc`` command: one parser built from the commands' modules (:mod:`pixelmpc_jax.commands`, one per
command, each with its arguments and its handler), and the process around the command it runs: the flags that set
up the process (devices, memory, hosts, tracebacks), the checks before anything runs, the output folders, and the
errors as one line. It defines no command of its own.

Bad input gets one line on stderr and exit code 2, never a traceback and never a run: every argument is
checked as it is parsed (finite, in range, an existing dataset or weights file), then by the command's
``validate`` (arguments that only make sense together) and ``precheck`` (the race and its controllers built, a
weights or course file read), and output folders are made only after all of that passed. A library
error reaching the command (ValueError, OSError) prints ``pixelmpc: error: ...``; ``--debug`` shows the
traceback instead. Exit codes: 0 done; 1 the run completed but failed (no lap succeeded, the demo missed
its waypoint, a runtime error); 2 bad input; 130 interrupted (what had finished is saved).
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
from pathlib import Path

from pixelmpc_jax import arguments as arg
from pixelmpc_jax.commands import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from pixelmpc_jax.commands.bench import add_bench
from pixelmpc_jax.commands.collect import add_collect
from pixelmpc_jax.commands.course import add_course
from pixelmpc_jax.commands.demo import add_demo
from pixelmpc_jax.commands.evaluate import add_evaluate
from pixelmpc_jax.commands.experiment import add_experiment
from pixelmpc_jax.commands.race import add_race
from pixelmpc_jax.commands.render import add_render
from pixelmpc_jax.commands.report import add_report
from pixelmpc_jax.commands.reproduce import add_reproduce
from pixelmpc_jax.commands.train import add_train
from pixelmpc_jax.commands.tune import add_tune
from pixelmpc_jax.commands.version import add_version

# every command, in the order `pixelmpc --help` lists them
COMMANDS = (add_version, add_demo, add_render, add_collect, add_train, add_evaluate, add_bench, add_reproduce, add_race,
            add_course, add_tune, add_experiment, add_report)

# the commands that split the CPU into devices by default
SPLIT_CPU_COMMANDS = ("race", "bench", "reproduce", "tune", "experiment")


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose error is one line on stderr (no usage block), exit code 2."""

    def error(self, message: str):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The one parser: the process flags, then each command of :data:`COMMANDS` as a sub-command."""
    parser = _Parser(
        prog="pixelmpc",
        description="PixelMPC in JAX: perception-aware MPPI with Deep Optical Flow dynamics.",
        epilog="Exit codes: 0 done; 1 the run completed but failed (no lap succeeded, the demo missed its "
               "waypoint); 2 bad input (one line names it); 130 interrupted (what finished is saved).",
    )
    _add_process_flags(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in COMMANDS:
        add(sub)
    return parser


def _add_process_flags(parser: argparse.ArgumentParser) -> None:
    """The flags that set up the process before any command: hosts, devices, memory, tracebacks."""
    parser.add_argument("--distributed", action="store_true",
                        help="join a multi-host run (jax.distributed.initialize: the cluster is detected under "
                             "SLURM, Open MPI or on TPU; elsewhere set JAX_COORDINATOR_ADDRESS, "
                             "JAX_NUM_PROCESSES, JAX_PROCESS_ID); run the same command on every host")
    parser.add_argument("--debug", action="store_true",
                        help="show the full traceback of an error instead of one line")
    from pixelmpc_jax.host import HOST_CPU_DEVICES_MAX  # imports JAX, starts no backend

    parser.add_argument("--cpu-devices", type=arg.int_in(1, 1024), default=None, metavar="N",
                        help="split the CPU into N JAX devices (default for race, bench, reproduce, tune and "
                             f"experiment: one per core, at most {HOST_CPU_DEVICES_MAX}; else 1). A lap's controller "
                             "splits its samples over them and batches of laps spread over them: XLA runs one "
                             "device's program on one core")
    parser.add_argument("--release-memory", action="store_true", help="leave glibc's defaults (the commands that "
                        "split the CPU otherwise keep freed memory for the next step: no page faults at large N)")


def _command_parser(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
    """The parser of the (sub-)command ``args`` ran: ``pixelmpc race``'s, ``pixelmpc experiment table2``'s."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return _command_parser(action.choices[getattr(args, action.dest)], args)
    return parser


def _make_output_dirs(args, command_parser: argparse.ArgumentParser) -> None:
    """Create every output folder the command was given (or defaults to), now that all else is checked."""
    for action in command_parser._actions:
        if action.type is not arg.writable_dir or getattr(args, action.dest, None) is None:
            continue
        out = Path(getattr(args, action.dest))
        try:
            arg.make_output_dir(out)
        except OSError as err:
            command_parser.error(f"argument {'/'.join(action.option_strings)}: output directory {str(out)!r} "
                                 f"cannot be written: {err}")


def _one_line(err: BaseException, limit: int = 600) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    text = " ".join(lines) or type(err).__name__
    return text if len(text) <= limit else text[:limit] + " ... (--debug shows all of it)"


def main(argv: list[str] | None = None, split_cpu: bool = False) -> int:
    """Run the command ``argv`` (default: the process's arguments). With ``split_cpu`` (the ``pixelmpc``
    command), race, bench, reproduce, tune and experiment split the CPU into one device per core unless
    ``--cpu-devices`` says otherwise, and keep freed memory (``host.keep_host_memory``) unless
    ``--release-memory``; called from Python, only ``--cpu-devices`` splits (and only before JAX has started)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 0
    if args.cpu_devices is not None or (split_cpu and args.command in SPLIT_CPU_COMMANDS):
        from pixelmpc_jax import host

        host.split_host_cpu(args.cpu_devices)
        if split_cpu and args.command in SPLIT_CPU_COMMANDS and not args.release_memory:
            host.keep_host_memory()
    command_parser = _command_parser(parser, args)
    if threading.current_thread() is threading.main_thread():
        from pixelmpc_jax import host

        host.stop_on_sigterm()
    validate = getattr(args, "validate", None)
    problem = validate(args) if validate is not None else None
    if problem:
        command_parser.error(problem)
    try:
        if args.distributed:
            _initialize_distributed()
        precheck = getattr(args, "precheck", None)
        if precheck is not None:
            precheck(args)
        _make_output_dirs(args, command_parser)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print("pixelmpc: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as err:  # bad input found by the library: a file, a setting
        if args.debug:
            raise
        print(f"pixelmpc: error: {_one_line(err)}", file=sys.stderr)
        return EXIT_USAGE
    except RuntimeError as err:  # the run itself failed (a lap too short to store, out of memory)
        if args.debug:
            raise
        print(f"pixelmpc: error: {_one_line(err)}", file=sys.stderr)
        return EXIT_FAILED


def _initialize_distributed() -> None:
    """``jax.distributed.initialize`` from the cluster's environment, or from the JAX_* variables."""
    import jax

    kwargs = {}
    if os.environ.get("JAX_COORDINATOR_ADDRESS"):
        missing = [name for name in ("JAX_NUM_PROCESSES", "JAX_PROCESS_ID") if name not in os.environ]
        if missing:
            raise ValueError(f"--distributed with JAX_COORDINATOR_ADDRESS also needs {' and '.join(missing)}")
        try:
            kwargs = {"coordinator_address": os.environ["JAX_COORDINATOR_ADDRESS"],
                      "num_processes": int(os.environ["JAX_NUM_PROCESSES"]),
                      "process_id": int(os.environ["JAX_PROCESS_ID"])}
        except ValueError as err:
            raise ValueError(f"--distributed: JAX_NUM_PROCESSES and JAX_PROCESS_ID must be integers ({err})") from None
    jax.distributed.initialize(**kwargs)
    print(f"process {jax.process_index()} of {jax.process_count()}: {jax.local_device_count()} local and "
          f"{jax.device_count()} global device(s)", flush=True)


def console_main() -> int:
    """The ``pixelmpc`` command."""
    return main(split_cpu=True)


if __name__ == "__main__":
    sys.exit(console_main())
