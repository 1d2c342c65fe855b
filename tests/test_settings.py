"""A setting's range, choices and help live once, in its dataclass field (``pixelmpc_jax.settings``): the
configuration's check and the ``pixelmpc race`` flag that sets it refuse exactly the same values."""

import dataclasses
import inspect
import math
import re

import numpy as np
import pytest

from pixelmpc_jax import arguments as arg
from pixelmpc_jax import cli, settings
from pixelmpc_jax.apps.racing.spec import RaceSpec
from pixelmpc_jax.commands import race as race_command
from pixelmpc_jax.settings import Range, setting

FIELD_FLAGS = [flag for flag in race_command.RACE_FLAGS
               if flag.field is not None and settings.described(settings.field_at(RaceSpec(), flag.field)[0])]
RANGED = [flag for flag in FIELD_FLAGS if settings.field_at(RaceSpec(), flag.field)[0].metadata["range"] is not None]
CHOSEN = [flag for flag in FIELD_FLAGS if settings.field_at(RaceSpec(), flag.field)[0].metadata["choices"]]


def _edges(value_range: Range) -> tuple[list, list]:
    """Values just inside each end of ``value_range`` and just outside it (the next float, or the next integer)."""
    if value_range.integer:
        inside, outside = [value_range.lo, value_range.hi], [value_range.lo - 1, value_range.hi + 1]
    else:
        lo_in = math.nextafter(value_range.lo, math.inf) if value_range.lo_open else value_range.lo
        lo_out = value_range.lo if value_range.lo_open else math.nextafter(value_range.lo, -math.inf)
        inside, outside = [lo_in, value_range.hi], [lo_out, math.nextafter(value_range.hi, math.inf)]
    if math.isinf(value_range.hi):  # no upper end
        inside, outside = inside[:1], outside[:1]
    return inside, outside


def _flag_accepts(flag, text: str) -> bool:
    try:
        cli.build_parser().parse_args(["race", f"{flag.flag}={text}"])  # "=": a negative number is no option
    except SystemExit:
        return False
    return True


def _python_accepts(field: str, value) -> bool:
    try:
        RaceSpec().with_fields({field: value})
    except ValueError:
        return False
    return True


def test_the_race_flags_cover_the_described_settings():
    assert len(RANGED) >= 20 and len(CHOSEN) >= 10  # the table is read: numbers and names alike
    assert {flag.flag for flag in RANGED} >= {"--t-f", "--samples", "--model-latency", "--detection-gate",
                                              "--pf-recover", "--pf-recover-after", "--eskf-map-sigma", "--eskf-align",
                                              "--eskf-noise-adapt-rate", "--max-time", "--camera-tilt", "--speed",
                                              "--seed", "--laps", "--temperature", "--clearance"}


@pytest.mark.parametrize("flag", RANGED, ids=lambda flag: flag.flag)
def test_a_flag_and_its_configuration_refuse_the_same_values(flag, capsys):
    """Just inside each end of the field's range both take the value; just outside, both refuse it, the flag with
    the field's interval."""
    value_range = settings.field_at(RaceSpec(), flag.field)[0].metadata["range"]
    assert value_range.interval in flag.help  # the help names the one range
    inside, outside = _edges(value_range)
    for value in inside:
        assert _flag_accepts(flag, repr(value)), f"{flag.flag} {value!r}"
        assert _python_accepts(flag.field, value), f"{flag.field}={value!r}"
    for value in outside:
        assert not _flag_accepts(flag, repr(value)), f"{flag.flag} {value!r}"
        assert f"in {value_range.interval}, got" in capsys.readouterr().err
        assert not _python_accepts(flag.field, value), f"{flag.field}={value!r}"
    if value_range.integer:  # a whole float is no integer, in Python as on the command line
        assert not _flag_accepts(flag, "1.0") and not _python_accepts(flag.field, 1.0)


@pytest.mark.parametrize("flag", CHOSEN, ids=lambda flag: flag.flag)
def test_a_flag_and_its_configuration_take_the_same_names(flag):
    choices = settings.field_at(RaceSpec(), flag.field)[0].metadata["choices"]
    assert tuple(flag.options["choices"]) == choices
    assert all(_flag_accepts(flag, name) and _python_accepts(flag.field, name) for name in choices)
    assert not _flag_accepts(flag, "nonesuch") and not _python_accepts(flag.field, "nonesuch")


def test_the_race_command_writes_no_range_of_its_own():
    """The flag table names flags and fields; every number it parses comes from a field's description."""
    source = inspect.getsource(race_command)
    for written in ("float_in(", "int_in(", "float_range(", "_RANGE", "_MAX"):
        assert written not in source, written


def test_a_setting_is_checked_with_its_field_name_value_and_interval():
    @dataclasses.dataclass(frozen=True)
    class Probe:
        gain: float = setting(1.0, range=Range(0.0, 2.0, lo_open=True, unit="s"), help="a gain")
        count: int = setting(3, range=Range(1, math.inf, integer=True), help="a count")
        mode: str = setting("a", choices=("a", "b"), help="a mode")
        gate: float | None = setting(None, range=Range(0.0, 1.0), none="off", help="a gate, in {range}, or off")

        def __post_init__(self):
            settings.check(self)

    Probe(gain=np.float32(2.0), count=np.int64(7), gate=None)  # numpy numbers are numbers
    for changes, message in (({"gain": 0.0}, "Probe.gain must be a finite number in (0, 2] s, got 0.0"),
                             ({"gain": float("nan")}, "Probe.gain must be a finite number in (0, 2] s, got nan"),
                             ({"gain": True}, "Probe.gain must be a finite number"),
                             ({"count": 0}, "Probe.count must be an integer in [1, inf), got 0"),
                             ({"count": 2.0}, "Probe.count must be an integer"),
                             ({"mode": "c"}, "Probe.mode must be one of a, b, got 'c'"),
                             ({"gate": 1.5}, "Probe.gate must be a finite number in [0, 1], got 1.5")):
        with pytest.raises(ValueError, match=f"^{re.escape(message)}"):
            Probe(**changes)
    fields = {field.name: field for field in dataclasses.fields(Probe)}
    assert settings.help_text(fields["gain"]) == "a gain, in (0, 2] s"
    assert settings.help_text(fields["gate"]) == "a gate, in [0, 1], or off"
    with pytest.raises(ValueError, match="count must be an integer"):  # None only where the field says what it means
        Probe(count=None)


def test_a_flag_is_made_only_from_a_described_setting():
    flag = arg.setting_flag("--samples", RaceSpec(), "config.mppi.num_samples", metavar="N")
    assert flag.options["metavar"] == "N" and flag.options["type"]("1024") == 1024
    with pytest.raises(ValueError, match="--noise-sigma: config.mppi.noise_sigma is not a setting described"):
        arg.setting_flag("--noise-sigma", RaceSpec(), "config.mppi.noise_sigma")
    with pytest.raises(ValueError, match="config.mppi.temprature: MPPIConfig has no field 'temprature'"):
        arg.setting_flag("--temperature", RaceSpec(), "config.mppi.temprature")


def test_a_race_hands_its_environment_the_same_setting():
    from pixelmpc_jax.sim.env import EnvConfig

    for name in ("detector", "estimator", "gate_switch", "max_time_s"):
        race, env = settings.field_at(RaceSpec(), name)[0], {f.name: f for f in dataclasses.fields(EnvConfig)}[name]
        assert race.metadata == env.metadata and race.default == env.default
