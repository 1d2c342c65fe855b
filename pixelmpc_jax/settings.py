"""A configuration's setting described once, in its dataclass field: its default, its range or choices, its help.

:func:`setting` makes the field. The configuration's own check (:func:`check`, from its ``__post_init__``) refuses a
value out of the field's range or choices with a ValueError naming the field, the value and the interval; the
command line's flag of the setting (:func:`pixelmpc_jax.arguments.setting_flag`) reads the same field's range,
choices and help. So a range lives in one place, and Python and the command line refuse the same values with the
same interval.

The ranges of settings that several configurations and commands share (a PRNG seed, a race's target speed, a lap's
timeout) are defined here too, once.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np


def is_number(value) -> bool:
    """Whether ``value`` is a real number (a Python or numpy int or float), not a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


class Range(NamedTuple):
    """The one range of a numeric setting, checked by its configuration (:meth:`check`) and parsed with by its
    command-line flag.

    Attributes:
        lo, hi: the bounds, ``hi`` included (``math.inf``: no upper bound).
        lo_open: ``lo`` excluded.
        unit: the unit named after the interval ("s", "m"), or "".
        integer: the setting is an integer (a float, even a whole one, is refused).
    """

    lo: float
    hi: float
    lo_open: bool = False
    unit: str = ""
    integer: bool = False

    @property
    def interval(self) -> str:
        """``[lo, hi] unit`` (``(lo, hi]`` with ``lo_open``, ``[lo, inf)`` without an upper bound)."""
        def number(x) -> str:
            return str(int(x)) if self.integer else f"{x:g}"

        upper = "inf)" if math.isinf(self.hi) else f"{number(self.hi)}]"
        return f"{'(' if self.lo_open else '['}{number(self.lo)}, {upper}" + (f" {self.unit}" if self.unit else "")

    @property
    def kind(self) -> str:
        """What a value must be: "an integer" or "a finite number"."""
        return "an integer" if self.integer else "a finite number"

    def holds(self, value) -> bool:
        """Whether ``value`` is a number (not a bool; an integer for an integer range) within the range (NaN and inf
        are not)."""
        if not is_number(value) or (self.integer and not isinstance(value, (int, np.integer))):
            return False
        return bool((value > self.lo if self.lo_open else value >= self.lo) and value <= self.hi
                    and math.isfinite(value))

    def check(self, name: str, value) -> float | int:
        """``value`` as a float (an int for an integer range); a ValueError ``{name} must be a finite number in
        {interval}, got {value}``."""
        if not self.holds(value):
            raise ValueError(f"{name} must be {self.kind} in {self.interval}, got {value!r}")
        return int(value) if self.integer else float(value)


SEED_RANGE = Range(0, 2**31 - 1, integer=True)  # a PRNG seed is a non-negative int32 (a larger one wraps onto another)
# m/s, a race's target; the vehicle's top speed is about 19 m/s (36.98 N against 0.1 |v| v)
TARGET_SPEED_RANGE = Range(0.0, 50.0, lo_open=True, unit="m/s")
MAX_TIME_RANGE = Range(0.0, 600.0, lo_open=True, unit="s")  # a lap's timeout (a lap of the course takes 20-35 s)
# deg, the onboard camera's upward tilt on its mount (0: the paper's); racing drones mount it tilted up 20-50 deg
CAMERA_TILT_RANGE = Range(0.0, 60.0, unit="deg")


def setting(default=dataclasses.MISSING, *, help: str, range: Range | None = None, choices: tuple | None = None,
            none: str | None = None, default_factory=dataclasses.MISSING):
    """A dataclass field that carries its setting's description in its metadata.

    Args:
        default, default_factory: as :func:`dataclasses.field`'s.
        help: what the setting does, one phrase in the command line's words; ``{range}`` in it is replaced by the
            range's interval (else the interval is appended).
        range: the values a number may take (:class:`Range`), or None.
        choices: the values a name may take, or None.
        none: what None means for the setting ("off", "no model"); None is a value only when this says so.
    """
    if range is not None and choices is not None:
        raise ValueError("a setting has a range or choices, not both")
    metadata = {"help": help, "range": range, "choices": None if choices is None else tuple(choices), "none": none}
    return dataclasses.field(default=default, default_factory=default_factory, metadata=metadata)


def like(config_class, name: str):
    """A field that is the setting ``name`` of the dataclass ``config_class`` again, its default and description
    with it, for a configuration that hands the setting on (a race's detector to its environment's)."""
    fields = {field.name: field for field in dataclasses.fields(config_class)}
    if name not in fields or not described(fields[name]):
        raise ValueError(f"{config_class.__name__} has no setting {name!r}")
    field = fields[name]
    return dataclasses.field(default=field.default, default_factory=field.default_factory, metadata=field.metadata)


def described(field: dataclasses.Field) -> bool:
    """Whether ``field`` was made by :func:`setting`."""
    return "help" in field.metadata


def help_text(field: dataclasses.Field) -> str:
    """The setting's help with its range's interval in it (``{range}`` replaced, else ``, in [lo, hi]`` appended)."""
    text, value_range = field.metadata["help"], field.metadata["range"]
    if value_range is None:
        return text
    return text.replace("{range}", value_range.interval) if "{range}" in text else f"{text}, in {value_range.interval}"


def check_value(owner: str, field: dataclasses.Field, value) -> None:
    """Refuse ``value`` for the setting ``field`` of the configuration class named ``owner`` when it lies outside the
    field's range or choices (None passes where the field says what None means): a ValueError
    ``{owner}.{field} must be ... in {interval}, got {value}``."""
    meta = field.metadata
    if value is None and meta["none"] is not None:
        return
    name = f"{owner}.{field.name}"
    if meta["range"] is not None:
        meta["range"].check(name, value)
    elif meta["choices"] is not None and (not isinstance(value, str) or value not in meta["choices"]):
        raise ValueError(f"{name} must be one of {', '.join(meta['choices'])}, got {value!r}")


def check(config) -> None:
    """Check every field of the dataclass ``config`` made by :func:`setting` against its range or choices (its
    ``__post_init__`` calls this first); a ValueError names the first field refused, its value and its interval."""
    owner = type(config).__name__
    for field in dataclasses.fields(config):
        if described(field):
            check_value(owner, field, getattr(config, field.name))


def field_at(config, path: str) -> tuple[dataclasses.Field, object]:
    """The field of the dataclass instance ``config`` at the dotted ``path`` ("config.mppi.temperature") and its
    value there; a ValueError names the first part of the path that is not a field."""
    *parents, name = path.split(".")
    node = config
    for part in [*parents, name]:
        fields = {field.name: field for field in dataclasses.fields(node)} if dataclasses.is_dataclass(node) else {}
        if part not in fields:
            raise ValueError(f"{path}: {type(node).__name__} has no field {part!r}")
        field, node = fields[part], getattr(node, part)
    return field, node
