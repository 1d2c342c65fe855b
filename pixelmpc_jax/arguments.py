"""The ``pixelmpc`` command's argument types: each checks one argument as it is parsed and returns its value, or
raises ``argparse.ArgumentTypeError`` with the accepted range (one line, before anything runs)."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

SEED_MAX = 2**31 - 1  # a PRNG seed is a non-negative int32 (a larger one would wrap onto another seed)




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


seed = int_in(0, SEED_MAX)


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


def weights_file(path: str) -> Path:
    """An argparse type: an existing file (its contents are checked before anything runs)."""
    file = Path(path)
    if not file.is_file():
        reason = "it is a directory" if file.is_dir() else "no such file"
        raise argparse.ArgumentTypeError(f"no DOF weights file at {path!r}: {reason}")
    return file


def course(text: str) -> str:
    """A course: "alphapilot", "straight", or an existing course file (its contents are checked before anything
    runs, once the process is set up: reading it makes JAX arrays)."""
    if text in ("alphapilot", "straight"):
        return text
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"no course {text!r}: choose alphapilot or straight, or give a course file")
    return text
