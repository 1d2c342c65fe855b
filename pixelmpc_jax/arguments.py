"""The ``pixelmpc`` command's argument types: each checks one argument as it is parsed and returns its value, or
raises ``argparse.ArgumentTypeError`` with the accepted range (one line, before anything runs); the check of a
lap's seeds (:func:`seed_range`), which spans two arguments; and the one convention by which a flag sets a field of
the configuration a command builds (:class:`FieldFlag`, :func:`fields_given`), a setting's flag made from its field's
description (:func:`setting_flag`)."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import NamedTuple

from pixelmpc_jax import settings
from pixelmpc_jax.settings import MAX_TIME_RANGE, SEED_RANGE, TARGET_SPEED_RANGE

# The bounds the commands' help names, from the settings' one range (pixelmpc_jax.settings)
SEED_MAX = SEED_RANGE.hi
TARGET_SPEED_MAX = TARGET_SPEED_RANGE.hi
MAX_TIME_S = MAX_TIME_RANGE.hi


def float_in(lo: float, hi: float, *, lo_open: bool = False, unit: str = ""):
    """An argparse type: a finite number in [lo, hi] ((lo, hi] with ``lo_open``)."""
    interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {interval}, got {text!r}") from None
        if not (math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi):
            raise argparse.ArgumentTypeError(f"must be a finite number in {interval}, got {text}")
        return value

    return parse


def float_range(setting_range):
    """An argparse type from a setting's one range (a :class:`~pixelmpc_jax.settings.Range`: ``lo``, ``hi``,
    ``lo_open``, ``unit``), the range its configuration checks: the flag and the configuration refuse the same
    values."""
    return float_in(setting_range.lo, setting_range.hi, lo_open=setting_range.lo_open, unit=setting_range.unit)


def int_range(setting_range):
    """An argparse type from an integer setting's one range (a :class:`~pixelmpc_jax.settings.Range` with
    ``integer``), the range its configuration checks."""
    interval = setting_range.interval

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer in {interval}, got {text!r}") from None
        if not setting_range.holds(value):
            raise argparse.ArgumentTypeError(f"must be an integer in {interval}, got {text}")
        return value

    return parse


def range_type(setting_range):
    """The argparse type of a setting's range: :func:`int_range` for an integer one, else :func:`float_range`."""
    return int_range(setting_range) if setting_range.integer else float_range(setting_range)


def int_in(lo: int, hi: int, *, odd: bool = False):
    """An argparse type: an integer in [lo, hi] (odd with ``odd``)."""
    what = f"{'an odd integer' if odd else 'an integer'} in [{lo}, {hi}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not lo <= value <= hi or (odd and value % 2 == 0):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text}")
        return value

    return parse


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from err
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def widths(text: str) -> tuple[int, ...]:
    """An argparse type: a network's hidden layer widths, comma-separated integers in [1, 4096] (``32,32``)."""
    parts = [part.strip() for part in text.split(",")]
    if not all(part.isdigit() and 1 <= int(part) <= 4096 for part in parts):
        raise argparse.ArgumentTypeError(f"expected comma-separated widths, each an integer in [1, 4096], "
                                         f"got {text!r}")
    return tuple(int(part) for part in parts)


seed = int_range(SEED_RANGE)
target_speed = float_range(TARGET_SPEED_RANGE)  # a race's target speed
SPEEDS_MAX = 200  # the most target speeds one range may name


def target_speeds(text: str) -> tuple[float, ...]:
    """An argparse type: target speeds, one (``8.5``) or a range ``LO:HI:STEP`` (``6:9:0.25``: 6, 6.25, ..., 9; HI
    is in it where the steps land on it), each a :data:`target_speed`; at most :data:`SPEEDS_MAX` of them."""
    parts = text.split(":")
    if len(parts) == 1:
        return (target_speed(text),)
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected a speed or a range LO:HI:STEP (e.g. 6:9:0.25), got {text!r}")
    low, high, step = (target_speed(part) for part in parts)
    if high < low:
        raise argparse.ArgumentTypeError(f"range {text!r}: HI must be at least LO")
    count = math.floor((high - low) / step + 1e-9) + 1
    if count > SPEEDS_MAX:
        raise argparse.ArgumentTypeError(f"range {text!r} names {count} speeds, at most {SPEEDS_MAX}")
    return tuple(round(low + i * step, 6) for i in range(count))  # 6.3, not 6.300000000000001: the cells' names


def unwritable_reason(out: Path) -> str | None:
    """Why ``out`` could not be used as an output folder, or None; looks only (creates nothing)."""
    probe = out
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        return f"{probe} is not a directory"
    if not os.access(probe, os.W_OK | os.X_OK):
        return f"{probe} is not writable"
    return None


def writable_dir(path: str) -> Path:
    """An argparse type: an output folder that exists and is writable or could be created there. It is
    made (by the command's ``main``) only after every argument has been checked."""
    out = Path(path)
    reason = unwritable_reason(out)
    if reason is not None:
        raise argparse.ArgumentTypeError(f"output directory {path!r} cannot be written: {reason}")
    return out


def output_file(path: str) -> Path:
    """An argparse type: a file that can be written (its folder exists or can be made; it is not a folder)."""
    file = Path(path)
    if file.is_dir():
        raise argparse.ArgumentTypeError(f"output file {path!r} is a directory")
    reason = unwritable_reason(file.parent)
    if reason is not None:
        raise argparse.ArgumentTypeError(f"output file {path!r} cannot be written: {reason}")
    return file


def make_output_dir(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    probe = out / ".write_test"
    probe.write_text("")
    probe.unlink()


def dataset_dir(path: str) -> Path:
    """An argparse type: a DOF dataset folder (one holding the manifest ``collect`` writes)."""
    root = Path(path)
    hint = f"collect one with `pixelmpc collect --out {path}`"
    if not root.is_dir():
        raise argparse.ArgumentTypeError(f"no DOF dataset at {path!r}: the directory does not exist ({hint})")
    if not (root / "manifest.json").is_file():
        raise argparse.ArgumentTypeError(f"no DOF dataset at {path!r}: manifest.json is missing ({hint})")
    return root


def grid_dir(path: str) -> Path:
    """An argparse type: a grid's output folder (one holding the ``results.json`` its cells write)."""
    folder = Path(path)
    if not (folder / "results.json").is_file():
        reason = "the directory does not exist" if not folder.is_dir() else "it holds no results.json"
        raise argparse.ArgumentTypeError(f"no grid at {path!r}: {reason}")
    return folder


def _existing_file(path: str, what: str) -> Path:
    """``path`` as a Path if a file is there; else an argparse error ``no {what} at {path}: {why}``."""
    file = Path(path)
    if not file.is_file():
        reason = "it is a directory" if file.is_dir() else "no such file"
        raise argparse.ArgumentTypeError(f"no {what} at {path!r}: {reason}")
    return file


def grid_file(path: str) -> Path:
    """An argparse type: a grid file that exists (its contents are read and checked before anything flies:
    :func:`~pixelmpc_jax.apps.racing.grid_file.read_grid_file`)."""
    return _existing_file(path, "grid file")


def result_dir(path: str) -> Path:
    """An argparse type: a result folder, a grid's (``results.json``) or a race's (``metrics.json``)."""
    folder = Path(path)
    if not ((folder / "results.json").is_file() or (folder / "metrics.json").is_file()):
        reason = "the directory does not exist" if not folder.is_dir() else "it holds no results.json or metrics.json"
        raise argparse.ArgumentTypeError(f"no result folder at {path!r}: {reason}")
    return folder


def checkout_dir(path: str) -> Path:
    """An argparse type: a checkout of the project (a folder holding ``README.md`` and ``experiments/results``)."""
    root = Path(path)
    missing = [name for name in ("README.md", "experiments/results") if not (root / name).exists()]
    if missing:
        raise argparse.ArgumentTypeError(f"{path!r} is not a checkout of the project: it lacks {', '.join(missing)}")
    return root


def ticks_dir(path: str) -> Path:
    """An argparse type: a folder holding a race's or a grid's per-tick records (``ticks_<race>.npz``)."""
    folder = Path(path)
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"no folder at {path!r}")
    if not [p for p in folder.glob("ticks_*.npz") if p.name != "ticks_compact.npz"]:
        raise argparse.ArgumentTypeError(f"{path!r} holds no per-tick record (ticks_<race>.npz)")
    return folder


def ticks_file(path: str) -> Path:
    """An argparse type: a per-tick record (``ticks_<race>.npz``) with the states, targets and gates of its laps."""
    import numpy as np

    needed = ("states", "target", "num_ticks", "seed", "gate_centre", "camera_fx")
    try:
        with np.load(path) as data:
            missing = [key for key in needed if key not in data.files]
    except (OSError, ValueError) as err:
        raise argparse.ArgumentTypeError(f"no per-tick record at {path!r}: {err}") from None
    if missing:
        raise argparse.ArgumentTypeError(f"{path!r} is not a per-tick record: it lacks {', '.join(missing)}")
    return Path(path)


def weights_file(path: str) -> Path:
    """An argparse type: an existing file (its contents are checked before anything runs)."""
    return _existing_file(path, "DOF weights file")


def fault(text: str) -> dict:
    """A fault, ``NAME=VALUE``: a field of :class:`~pixelmpc_jax.sim.faults.Faults` and its value (``wind=3,0,0``,
    three numbers for a vector; ``latency_ticks=2``), or a named fault of
    :data:`~pixelmpc_jax.sim.faults.FAULT_LEVELS` at a level (``gust=moderate``, ``combined=severe``). Returns the
    ``{field: value}`` it sets; a bad entry is one line naming it and what the fault takes."""
    import dataclasses

    from pixelmpc_jax.sim import faults as faults_lib

    name, sep, value = (part.strip() for part in text.partition("="))
    named = (*faults_lib.FAULT_LEVELS, faults_lib.COMBINED)
    fields = [f.name for f in dataclasses.fields(faults_lib.Faults)]
    if not sep or not name or not value:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    if name in named and value in faults_lib.LEVELS:
        level = faults_lib.fault_level(name, value)
        return {field: getattr(level, field) for field in level.active()}
    if name not in fields:
        raise argparse.ArgumentTypeError(
            f"unknown fault {name!r} in {text!r}; choose a setting ({', '.join(fields)}) or a named fault "
            f"({', '.join(named)}) at {' or '.join(faults_lib.LEVELS)}")
    if name in faults_lib.VECTOR_FIELDS and len(value.split(",")) != 3:
        raise argparse.ArgumentTypeError(f"{text!r}: fault {name} takes 3 numbers x,y,z, comma-separated")
    try:
        parsed = tuple(float(v) for v in value.split(",")) if name in faults_lib.VECTOR_FIELDS else float(value)
        if name in faults_lib.INT_FIELDS and parsed.is_integer():
            parsed = int(parsed)
        faults_lib.Faults(**{name: parsed})
    except ValueError as err:
        message = str(err) if "fault" in str(err) else f"fault {name} takes a number, got {value!r}"
        raise argparse.ArgumentTypeError(f"{text!r}: {message}") from None
    return {name: parsed}


def imu_bias_std(text: str) -> tuple:
    """``ACCEL,GYRO``: two positive stds of the filter's IMU bias states, m/s^2 and rad/s, checked by
    :class:`~pixelmpc_jax.perception.filter_guards.GuardConfig` itself."""
    from pixelmpc_jax.perception.filter_guards import GuardConfig

    try:
        return GuardConfig(imu_bias_std=tuple(float(v) for v in text.split(","))).imu_bias_std
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: takes two positive numbers ACCEL,GYRO (m/s^2, rad/s), "
                                         "e.g. 0.3,0.02") from None


def course(text: str) -> str:
    """A course: one known by name (:data:`~pixelmpc_jax.world.course.COURSES`) or an existing course file (its
    contents are checked before anything runs, once the process is set up: reading it makes JAX arrays)."""
    from pixelmpc_jax.world.course import COURSES

    if text in COURSES:
        return text
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"no course {text!r}: choose {' or '.join(COURSES)}, or give a course file")
    return text


def seed_range(args) -> str | None:
    """Lap i flies seed + i: the last seed must still be a seed (a command's ``validate``: the problem, or None)."""
    laps = 10 if getattr(args, "paper", False) else args.laps or 1  # collect --paper flies the paper's 10 laps
    last = (args.seed or 0) + laps - 1
    if last > SEED_MAX:
        return (f"argument --seed: --seed + --laps - 1 must be at most {SEED_MAX} (lap i uses seed + i), "
                f"got {last}")
    return None


class FieldFlag(NamedTuple):
    """A flag and the field of the configuration it sets: ``field`` a dotted path into the configuration the command
    builds ("speed", "config.mppi.temperature"), or None for a flag that sets none (how the command runs: its output,
    a batch). ``options`` are its other ``add_argument`` keywords. A flag with a field is None when left out: the
    field keeps the value of the configuration the command starts from."""

    flag: str
    field: str | None
    help: str
    options: dict

    @property
    def dest(self) -> str:
        """Where argparse keeps the flag's value (its name: ``--t-f`` -> ``t_f``)."""
        return self.flag.lstrip("-").replace("-", "_")

    def add_to(self, parser, help: str | None = None) -> None:
        """Add the flag to ``parser`` (a parser or an argument group), with ``help`` in place of its own."""
        default = {} if self.field is None else {"default": None}
        parser.add_argument(self.flag, help=self.help if help is None else help, **default, **self.options)


def setting_flag(flag: str, config, field: str, **options) -> FieldFlag:
    """The flag ``flag`` of the setting at the dotted path ``field`` of the configuration ``config`` (an instance),
    described by the field's metadata (:func:`pixelmpc_jax.settings.setting`): its help with the range's interval,
    and an argparse type of that range (:func:`range_type`), its choices, or ``store_true`` for a bool, so the flag
    refuses what the configuration refuses. ``options`` add to those keywords or replace them (a metavar, a parser
    of its own); a ValueError names a field that is not a described setting."""
    described, _ = settings.field_at(config, field)
    if not settings.described(described):
        raise ValueError(f"{flag}: {field} is not a setting described by pixelmpc_jax.settings.setting")
    meta = described.metadata
    generated = {}
    if isinstance(described.default, bool):
        generated["action"] = "store_true"
    elif meta["range"] is not None:
        generated["type"] = range_type(meta["range"])
    elif meta["choices"] is not None:
        generated["choices"] = meta["choices"]
    return FieldFlag(flag, field, settings.help_text(described), {**generated, **options})


def fields_given(args, flags) -> dict:
    """``{field: value}`` of each of ``flags`` with a field that ``args`` gives (not None), in the flags' order."""
    return {flag.field: getattr(args, flag.dest) for flag in flags
            if flag.field is not None and getattr(args, flag.dest) is not None}
