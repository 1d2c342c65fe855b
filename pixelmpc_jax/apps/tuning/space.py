"""The search space of ``pixelmpc tune``: named controller settings, each a range or a list of choices.

A space is a JSON object whose keys name fields of the :class:`~pixelmpc_jax.control.pixelmpc.ControllerConfig` a race
flies, dotted as :meth:`~pixelmpc_jax.apps.racing.spec.RaceSpec.record` nests them under ``"config"`` (``"c_pixel"``,
``"mppi.temperature"``, ``"racing.heading_weight"``), and whose values are either a range
``{"low": 2e6, "high": 3e7, "log": true}`` (``log`` optional, false by default) or ``{"choices": [...]}``::

    {"c_pixel": {"low": 2e6, "high": 3e7, "log": true},
     "mppi.noise_exponent": {"low": 0, "high": 2},
     "pixel_cost": {"choices": ["l1", "border"]}}

An integer field (``mppi.num_samples``) is searched over integers. Every entry is checked before anything runs:
each bad one gets one line of :class:`SpaceError` (an unknown field, low >= high, a log range from zero or below, a
range over a setting that is not a number, a bound or a choice the configuration refuses).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.control.pixelmpc import ControllerConfig

# "hand-tuned": around the hand-tuned settings the search started from (presets.HAND_TUNED_BEST: vdof, border cost,
# c_pixel 9e6, box size limit 0.5, t_f 1 s, lambda 200, white noise): the settings the hand tuning moved, each over
# the range the 4-lap probes spanned and somewhat beyond. The tuned `best` preset sits near two edges (lambda 747,
# border margin 0.076): a further search would widen those.
HAND_TUNED_SPACE = {
    "c_pixel": {"low": 2e6, "high": 3e7, "log": True},
    "border_margin": {"low": 0.05, "high": 0.3},
    "box_size_limit": {"low": 0.3, "high": 0.8},
    "mppi.temperature": {"low": 50.0, "high": 800.0, "log": True},
    "mppi.noise_exponent": {"low": 0.0, "high": 2.0},
    "t_f": {"low": 0.5, "high": 1.5},
}
SPACES = {
    "hand-tuned": HAND_TUNED_SPACE,
    # "levers": the same ranges, with the levers against the first second after a switch (docs/visibility.md) as
    # choices: the target's prior while undetected (the paper's none, the map's, the kept-alive pixel) and the
    # look-ahead's weight on the next gate (0, the paper's)
    "levers": {**HAND_TUNED_SPACE,
               "target_prior": {"choices": ["none", "map", "kept"]},
               "look_ahead": {"choices": [0.0, 1.0, 3.0]}},
    # "look-ahead": the search that chose today's `best`: the next gate's pixel projected from the map along the
    # horizon (look_ahead_model, fixed), its weight over a range, the hand-tuned ranges with the pixel weight from
    # 1e6 and the box size limit to 0.9 (the base preset's kept prior is not searched)
    "look-ahead": {**HAND_TUNED_SPACE,
                   "c_pixel": {"low": 1e6, "high": 3e7, "log": True},
                   "box_size_limit": {"low": 0.3, "high": 0.9},
                   "look_ahead": {"low": 0.25, "high": 3.0, "log": True},
                   "look_ahead_model": {"choices": ["projection"]}},
}
_NUMERIC = {"float": float, "float | None": float, "int": int, "int | None": int}  # annotations a range may take


class SpaceError(ValueError):
    """A search space with bad entries; ``problems`` holds one line per entry."""

    def __init__(self, problems: list[str]):
        super().__init__("\n".join(problems))
        self.problems = problems


@dataclasses.dataclass(frozen=True)
class Param:
    """One searched setting: ``name`` dotted into the configuration, a range [low, high] (``log``: sampled on a log
    scale; ``integer``: over integers) or ``choices``."""

    name: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    integer: bool = False
    choices: tuple | None = None

    def suggest(self, trial):
        """This setting's value for the Optuna ``trial``."""
        if self.choices is not None:
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.integer:
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, log=self.log)

    def record(self) -> dict:
        if self.choices is not None:
            return {"choices": list(self.choices)}
        return {"low": self.low, "high": self.high, "log": self.log}


def with_settings(base: RaceSpec, settings: dict) -> RaceSpec:
    """``base`` with each ``{dotted name: value}`` of ``settings`` set in its configuration (a ValueError names a value
    the configuration refuses)."""
    return base.with_fields({f"config.{name}": value for name, value in settings.items()})


def load_space(space: str, base: RaceSpec) -> dict[str, Param]:
    """The space named ``space`` (a key of :data:`SPACES`) or read from the JSON file ``space``, checked against the
    race ``base``; a :class:`SpaceError` lists every bad entry."""
    if space in SPACES:
        entries = SPACES[space]
    else:
        path = Path(space)
        if not path.is_file():
            raise SpaceError([f"search space {space!r} is neither a space name ({', '.join(SPACES)}) nor a file"])
        try:
            entries = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise SpaceError([f"search space {space}: not JSON: {err}"]) from None
    if not isinstance(entries, dict) or not entries:
        raise SpaceError([f"search space {space}: must be a non-empty JSON object of settings, got {entries!r}"])
    problems, params = [], {}
    for name, entry in entries.items():
        param, problem = check_entry(name, entry, base)
        if problem:
            problems.append(f"search space {space}: {problem}")
        else:
            params[name] = param
    if problems:
        raise SpaceError(problems)
    return params


def _field_annotation(name: str) -> tuple[str | None, str | None]:
    """The annotation of the configuration field ``name`` (dotted), or None and what is wrong with the name."""
    node = ControllerConfig()
    parts = name.split(".")
    for depth, part in enumerate(parts):
        fields = {f.name: f for f in dataclasses.fields(node)}
        if part not in fields:
            return None, f"unknown field {name!r}: {type(node).__name__} has {', '.join(sorted(fields))}"
        value, last = getattr(node, part), depth == len(parts) - 1
        if dataclasses.is_dataclass(value) and last:
            return None, f"{name!r} is a group of settings: name one of its fields ({name}.FIELD)"
        if not dataclasses.is_dataclass(value) and not last:
            return None, f"unknown field {name!r}: {'.'.join(parts[:depth + 1])} is a setting, not a group"
        if last:
            annotation = fields[part].type
            return annotation if isinstance(annotation, str) else getattr(annotation, "__name__", ""), None
        node = value
    return None, f"unknown field {name!r}"


def check_entry(name: str, entry, base: RaceSpec) -> tuple[Param | None, str | None]:
    """``(Param, None)`` for a good entry, ``(None, one line)`` for a bad one."""
    if not isinstance(name, str) or not name:
        return None, f"setting name must be a non-empty string, got {name!r}"
    annotation, problem = _field_annotation(name)
    if problem:
        return None, problem
    if not isinstance(entry, dict):
        return None, f'{name}: must be {{"low", "high"[, "log"]}} or {{"choices": [...]}}, got {entry!r}'
    if "choices" in entry:
        return _check_choices(name, entry, base)
    return _check_range(name, entry, annotation, base)


def _refused(name: str, value, base: RaceSpec) -> str | None:
    """Why the configuration refuses ``value`` for ``name`` (None when it takes it)."""
    try:
        with_settings(base, {name: value})
    except (ValueError, TypeError) as err:
        return str(err).splitlines()[0]
    return None


def _check_choices(name: str, entry: dict, base: RaceSpec) -> tuple[Param | None, str | None]:
    extra = sorted(set(entry) - {"choices"})
    if extra:
        return None, f"{name}: a choice entry has only \"choices\", got also {', '.join(extra)}"
    choices = entry["choices"]
    if not isinstance(choices, list) or not choices:
        return None, f"{name}: choices must be a non-empty list, got {choices!r}"
    for choice in choices:
        if not (choice is None or isinstance(choice, (bool, int, float, str))):
            return None, f"{name}: choice {choice!r} is not a number, a string, a boolean or null"
        refused = _refused(name, choice, base)
        if refused:
            return None, f"{name}: choice {choice!r} is not valid: {refused}"
    return Param(name, choices=tuple(choices)), None


def _check_range(name: str, entry: dict, annotation: str, base: RaceSpec) -> tuple[Param | None, str | None]:
    extra = sorted(set(entry) - {"low", "high", "log"})
    if extra or not {"low", "high"} <= set(entry):
        return None, f'{name}: a range is {{"low", "high"[, "log"]}}, got keys {", ".join(sorted(entry)) or "none"}'
    if annotation not in _NUMERIC:
        return None, f"{name}: a range needs a number setting, {name} is {annotation}: give it choices"
    low, high, log = entry["low"], entry["high"], entry.get("log", False)
    integer = _NUMERIC[annotation] is int
    kind = int if integer else (int, float)
    for label, value in (("low", low), ("high", high)):
        if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value):
            return None, f"{name}: {label} must be a finite {'integer' if integer else 'number'}, got {value!r}"
    if not isinstance(log, bool):
        return None, f"{name}: log must be true or false, got {log!r}"
    if low >= high:
        return None, f"{name}: low must be below high, got low {low!r} >= high {high!r}"
    if log and low <= 0:
        return None, f"{name}: a log range needs low > 0, got low {low!r}"
    for label, value in (("low", low), ("high", high)):
        refused = _refused(name, value, base)
        if refused:
            return None, f"{name}: {label} {value!r} is not valid: {refused}"
    return Param(name, float(low), float(high), log, integer), None
