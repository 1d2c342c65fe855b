"""One race's settings, frozen: :class:`RaceSpec`. The ``pixelmpc race`` command builds one from its arguments,
:func:`~pixelmpc_jax.apps.racing.race.run_laps` flies it, and an experiment grid keeps a finished cell only while its
:meth:`RaceSpec.key` is unchanged.

The controller's settings are its configuration as the library takes it, whole: one
:class:`~pixelmpc_jax.control.pixelmpc.ControllerConfig`, whose ``mppi``
(:class:`~pixelmpc_jax.control.mppi.MPPIConfig`), ``racing`` (:class:`~pixelmpc_jax.control.costs.RacingCostConfig`),
latency and disturbance model configure nominal MPPI too. Every setting lives in one field of one configuration;
the record, the key and the policy are derived from it.

Settings that do not change a lap stay out of it: the batch size, the progress bar, the output folder, the
video, and how a step runs (:class:`~pixelmpc_jax.devices.Execution`: how many devices its samples are split
over). The DOF weights enter as their fingerprint
(:func:`~pixelmpc_jax.dynamics.network_weights.dof_weights_hash`); the weights themselves are passed beside the
spec, or, for weights shipped in the package (:data:`PACKAGED_WEIGHTS`), named: by default those trained for the race's
camera.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pixelmpc_jax.control.pixelmpc import LEARNED_PIXEL_MODELS, ControllerConfig
from pixelmpc_jax.dynamics import dof, vdof
from pixelmpc_jax.dynamics.network_weights import (
    dof_weights_hash,
    packaged_camera_tilt_deg,
    trained_camera_tilt_deg,
    variant_for_camera,
    weights_record,
)
from pixelmpc_jax.perception.association import AssociationConfig
from pixelmpc_jax.perception.eskf import ESKFConfig
from pixelmpc_jax.perception.filter_guards import GuardConfig
from pixelmpc_jax.settings import CAMERA_TILT_RANGE, SEED_RANGE, TARGET_SPEED_RANGE, Range, check, like, setting
from pixelmpc_jax.sim.controllers import CONTROLLERS
from pixelmpc_jax.sim.env import EnvConfig
from pixelmpc_jax.sim.episode import EpisodeConfig
from pixelmpc_jax.sim.faults import Faults
from pixelmpc_jax.world.course import COURSES

MAPS = ("surveyed", "known")


class PackagedWeights(NamedTuple):
    """A learned pixel model's weights shipped in the package: ``variants`` ``{name: weights file}`` (the model's
    default first, each with its record beside it), ``load(name)`` their parameters, ``fingerprint(name)`` their
    :func:`~pixelmpc_jax.dynamics.network_weights.dof_weights_hash`."""

    variants: Mapping[str, Path]
    load: Callable
    fingerprint: Callable[[str], str]


# Each learned pixel model's packaged weights; a race names one by its name (RaceSpec.dof_weights), or by default flies
# the first whose record states the race's camera tilt.
PACKAGED_WEIGHTS = {
    "dof": PackagedWeights(dof.PACKAGED_VARIANTS, dof.load_packaged_dof, dof.packaged_dof_hash),
    "vdof": PackagedWeights(vdof.PACKAGED_VARIANTS, vdof.load_packaged_vdof, vdof.packaged_vdof_hash),
}
PACKAGED_NAMES = tuple(name for packaged in PACKAGED_WEIGHTS.values() for name in packaged.variants)


def _default_config() -> ControllerConfig:
    return ControllerConfig()


# Settings added after races were recorded and keyed: left out of the key at their defaults, so that a recorded
# race (which flew them at their defaults) keeps its key and its cells are reused.
KEYED_ONLY_OFF_DEFAULT = ("gate_paint", "association", "imu", "start_error", "gates", "survey_error")


@dataclasses.dataclass(frozen=True)
class RaceSpec:
    """Everything that decides a race's laps; lap i flies PRNG seed ``seed + i``.

    Attributes:
        controller: "mppi" (nominal MPPI) or "pixelmpc".
        config: the controller's configuration. Nominal MPPI flies its ``mppi``, ``racing``,
            ``model_latency_ticks`` and ``disturbance_time_constant_s``; its PixelMPC fields are reset to their
            defaults for a nominal race (they fly nothing there).
        speed: target speed, m/s.
        laps: number of laps.
        seed: seed of the first lap.
        perturb: each lap's gates perturbed within the AlphaPilot bounds (with the lap's seed).
        course: "alphapilot", "straight" or the path of a course file in the AlphaPilot file's format
            (:func:`~pixelmpc_jax.world.course.make_course`); a file enters the key by its contents.
        detector: "clipped" (the projection cut at the image border, as a camera's detector reports it), "ideal"
            (the projection, in the image or not) or "image" (see :class:`~pixelmpc_jax.sim.env.EnvConfig`); nominal
            MPPI on the true state uses no detection, and its key is one for both geometric detectors.
        estimator: "truth", "pf" (the particle filter) or "eskf" (the error-state Kalman filter).
        max_time_s: timeout per lap, s.
        dof_weights: the learned pixel model's weights flown: the name of weights shipped in the package for it
            (:data:`PACKAGED_WEIGHTS`: the DOF's "flown", "turned", "paper_tilt30", vdof's "vdof_tilt30"), or the
            fingerprint (:func:`~pixelmpc_jax.dynamics.network_weights.dof_weights_hash`) of other weights; None for
            the model's packaged weights trained for the race's camera (:meth:`packaged_variant`; the name of those
            is spelled None). Always None for a race that does not evaluate a learned pixel model.
        guards: the particle filter's guards (:class:`~pixelmpc_jax.perception.filter_guards.GuardConfig`); reset
            to none for a race on the true state.
        eskf: the error-state Kalman filter's settings (:class:`~pixelmpc_jax.perception.eskf.ESKFConfig`); reset
            to the defaults for a race on another estimator.
        faults: what the world does beyond the controller's model (:class:`~pixelmpc_jax.sim.faults.Faults`;
            none by default).
        camera_tilt_deg: the onboard camera's upward tilt on its mount, deg (0: the paper's), in
            :data:`CAMERA_TILT_RANGE`; the detector, the controller and the visibility measure all see through
            it. A learned pixel model flies weights trained for the tilt: by default the packaged ones whose record
            states it (the untilted camera's and the racing camera's, 30 deg, ship); at a tilt none was trained for,
            a race flies the projection pixel model, nominal MPPI, or weights of its own (another camera's weights
            are refused where a learned model is flown: :meth:`check_weights`).
        map: with ``perturb``, what the controller and the filter read: "surveyed", the nominal course, while the
            world flies the perturbed gates; or "known", the perturbed course itself (a perturbed course perfectly
            known, as every perturbed race flew before the setting). Without ``perturb`` the map is the course:
            "surveyed".
        gate_switch: on a filter, when the controller's target moves on (:class:`~pixelmpc_jax.sim.env.EnvConfig`):
            "estimate", when the estimate crosses the map's gate, or "truth", the world's switch (as every race on a
            filter flew before the setting). On the true state: "estimate" (the two are one).
        gate_paint: with the image detector, how the gates are painted (:class:`~pixelmpc_jax.sim.env.EnvConfig`):
            "hues", each its own (the detector knows the gate), or "alike", one paint (the estimator names the gate);
            reset to "hues" for a geometric detector, which sees no paint.
        association: with gates painted alike, how the estimator names the gate
            (:class:`~pixelmpc_jax.perception.association.AssociationConfig`); reset to the defaults otherwise.
        imu: on a filter, the racing flight controller IMU its readings come from (:mod:`pixelmpc_jax.sim.imu`:
            biases drawn per lap, noise at the datasheet's density, the Kalman filter told the datasheet), or None,
            the simulator's IMU; reset to None on the true state.
        start_error: on a filter, it starts each lap off the true start by an error drawn per lap
            (:mod:`pixelmpc_jax.sim.start_error`); reset to False on the true state.
        gates: on the Kalman filter, "map" (the map's gates as they are) or "estimated": the filter estimates each
            gate's offset from the map, its prior what the drone was told (the perturbation bounds with ``perturb``
            on a surveyed map, else the survey's error: ``course.gate_prior_std``), and the controller follows the
            estimated gates (:class:`~pixelmpc_jax.sim.env.EnvConfig`); reset to "map" on another estimator.
        survey_error: without ``perturb``, each lap's gates stand off the map by a survey's error drawn with the
            lap's seed (``course.SURVEY_SIGMA``: 0.1 m across, 0.05 m up, 1 deg of yaw); reset to False with
            ``perturb`` (the gates are moved within their bounds instead).
    """

    controller: str = "mppi"
    config: ControllerConfig = dataclasses.field(default_factory=_default_config)
    speed: float = setting(14.0, range=TARGET_SPEED_RANGE, help="target speed")
    laps: int = setting(1, range=Range(1, math.inf, integer=True), help="laps per controller")
    seed: int = setting(0, range=SEED_RANGE, help="seed of the first lap, in {range}; lap i uses seed + i")
    perturb: bool = setting(False, help="perturb the gates per lap within the AlphaPilot bounds")
    course: str = setting("alphapilot", help="alphapilot, straight (five gates 20 m apart, the paper's straight lane) "
                          "or a course file in the format of pixelmpc_jax/data/alphapilot_course.json (`pixelmpc "
                          "course` makes one)")
    detector: str = like(EnvConfig, "detector")
    estimator: str = like(EnvConfig, "estimator")
    max_time_s: float = like(EnvConfig, "max_time_s")
    dof_weights: str | None = setting(
        None, none="the pixel model's packaged weights for the race's camera",
        help="the learned pixel model's weights: a packaged DOF variant (paper: command input; flown: the flown-rate "
             "weights; turned: trained with turned rows; paper_tilt30: the paper's for the camera tilted up 30 deg) "
             "or a weights file from `pixelmpc train`; with the vdof pixel model: vdof, the packaged vdof weights, "
             "vdof_tilt30, those for the camera tilted up 30 deg, or a file")
    guards: GuardConfig = dataclasses.field(default_factory=GuardConfig)
    eskf: ESKFConfig = dataclasses.field(default_factory=ESKFConfig)
    faults: Faults = dataclasses.field(default_factory=Faults)
    camera_tilt_deg: float = setting(
        0.0, range=CAMERA_TILT_RANGE, help="the onboard camera tilted up on its mount by DEG degrees, in {range}, for "
        "both controllers, the detector and the measure; a learned pixel model flies the packaged weights trained for "
        "that tilt (shipped for 0 and 30); at another tilt fly the projection pixel model or weights of your own")
    map: str = setting(
        "surveyed", choices=MAPS, help="with perturbed gates, what the controller and the filter read: surveyed, "
        "the nominal course, while the world flies the perturbed gates; known, the perturbed course itself (as "
        "perturbed races flew before)")
    gate_switch: str = like(EnvConfig, "gate_switch")
    gate_paint: str = like(EnvConfig, "gate_paint")
    association: AssociationConfig = dataclasses.field(default_factory=AssociationConfig)
    imu: str | None = like(EnvConfig, "imu")
    start_error: bool = like(EnvConfig, "start_error")
    gates: str = like(EnvConfig, "gates")
    survey_error: bool = setting(
        False, help="without --perturb, each lap's gates stand off the map by a survey's error drawn per lap (0.1 m "
                    "across, 0.05 m up, 1 deg of yaw, 1 sigma)")

    def __post_init__(self):
        if self.controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {self.controller!r}; choose one of {', '.join(CONTROLLERS)}")
        if self.course not in COURSES and not Path(self.course).is_file():
            raise ValueError(f"unknown course {self.course!r}; choose one of {', '.join(COURSES)} or a course file")
        if not isinstance(self.config, ControllerConfig):
            raise ValueError(f"config must be a ControllerConfig, got {type(self.config).__name__}")
        check(self)  # each setting in its field's range or choices
        # one spelling per race: floats as floats, no settings that fly nothing, no runtime-only settings
        for name in ("speed", "max_time_s", "camera_tilt_deg"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.controller == "mppi":
            object.__setattr__(self, "config", ControllerConfig(
                mppi=self.config.mppi, racing=self.config.racing, model_latency_ticks=self.config.model_latency_ticks,
                disturbance_time_constant_s=self.config.disturbance_time_constant_s))
        if not isinstance(self.faults, Faults) or not isinstance(self.guards, GuardConfig):
            raise ValueError(f"faults must be a Faults and guards a GuardConfig, got {type(self.faults).__name__} "
                             f"and {type(self.guards).__name__}")
        if not isinstance(self.eskf, ESKFConfig):
            raise ValueError(f"eskf must be an ESKFConfig, got {type(self.eskf).__name__}")
        if self.estimator != "pf":  # the filter's guards fly nothing on the true state
            object.__setattr__(self, "guards", GuardConfig())
        if self.estimator != "eskf":  # nor the Kalman filter's settings on another loop
            object.__setattr__(self, "eskf", ESKFConfig())
        # the map flies nothing on an unperturbed course; the switch, the filter's IMU and its start on the truth
        for name in ("map", "gate_switch", "imu", "start_error", "gates", "survey_error"):
            if not self.flies(name):
                object.__setattr__(self, name, RaceSpec.__dataclass_fields__[name].default)
        if not isinstance(self.association, AssociationConfig):
            raise ValueError(f"association must be an AssociationConfig, got {type(self.association).__name__}")
        if self.detector != "image":  # only the rendered gates wear paint
            object.__setattr__(self, "gate_paint", RaceSpec.__dataclass_fields__["gate_paint"].default)
        if self.gate_paint != "alike":  # the association names the candidates of gates painted alike only
            object.__setattr__(self, "association", AssociationConfig())
        if self._default_weights_named():  # one spelling of the packaged weights for the camera: None
            object.__setattr__(self, "dof_weights", None)

    def _default_weights_named(self) -> bool:
        """Whether ``dof_weights`` names what None names: no weights where no learned pixel model flies, another
        model's packaged weights (they name none of this model's), or this model's packaged weights for the race's
        camera."""
        if not self.uses_dof or self.dof_weights is None:
            return True
        if self.dof_weights not in PACKAGED_WEIGHTS[self.config.pixel_model].variants:
            return self.dof_weights in PACKAGED_NAMES
        return self.dof_weights == self._camera_variant()

    def packaged_variant(self) -> str | None:
        """The name of the packaged weights the race flies (:data:`PACKAGED_WEIGHTS`): the one ``dof_weights`` names,
        or for None the first of the model's whose record states the race's camera tilt (the model's default, which
        :meth:`check_weights` refuses, where the package ships none for that camera); None for weights named by a
        fingerprint and for a race without a learned pixel model."""
        if not self.uses_dof:
            return None
        if self.dof_weights is None:
            return self._camera_variant()
        return self.dof_weights if self.dof_weights in PACKAGED_WEIGHTS[self.config.pixel_model].variants else None

    def _camera_variant(self) -> str:
        """The learned pixel model's packaged weights for the race's camera: the first whose record states its tilt,
        else the model's default."""
        variants = PACKAGED_WEIGHTS[self.config.pixel_model].variants
        return variant_for_camera(variants, self.camera_tilt_deg) or next(iter(variants))

    def flies(self, name: str) -> bool:
        """Whether the setting ``name`` ("map", "gate_switch", "imu", "start_error", "gates" or "survey_error")
        changes a lap: the map with ``perturb``, the survey's error without, the estimated gates on the Kalman filter,
        the others on a filter."""
        if name == "map":
            return bool(self.perturb)
        if name == "survey_error":
            return not self.perturb
        if name == "gates":
            return self.estimator == "eskf"
        return self.estimator != "truth"

    def episode_config(self) -> EpisodeConfig:
        """The environment and driver the race's laps fly in (:class:`~pixelmpc_jax.sim.episode.EpisodeConfig`)."""
        return EpisodeConfig(max_time_s=self.max_time_s, detector=self.detector, estimator=self.estimator,
                             guards=self.guards, eskf=self.eskf, faults=self.faults, gate_switch=self.gate_switch,
                             imu=self.imu, start_error=self.start_error, gate_paint=self.gate_paint,
                             association=self.association, gates=self.gates)

    @property
    def uses_dof(self) -> bool:
        """Whether the controller evaluates a learned pixel model (PixelMPC with the "dof" or "vdof" pixel model),
        whose weights ``dof_weights`` names."""
        return self.controller == "pixelmpc" and self.config.pixel_model in LEARNED_PIXEL_MODELS

    def replace(self, **changes) -> RaceSpec:
        return dataclasses.replace(self, **changes)

    def record(self) -> dict:
        """The spec in JSON types, every setting written: its fields, the configuration nested as its dataclasses
        (tuples as lists once written). :meth:`from_record` reads it back."""
        return dataclasses.asdict(self)

    def with_fields(self, fields: dict) -> RaceSpec:
        """The spec with each field of ``fields`` set: ``{dotted path: value}``, the path as :meth:`record` nests it
        ("speed", "config.mppi.temperature", "guards.detection_gate_px"). All are set at once and read back through
        :meth:`from_record`, so each configuration's checks see all of its new fields together (a ValueError names a
        setting one refuses)."""
        record = dataclasses.asdict(self)
        for path, value in fields.items():
            *parents, name = path.split(".")
            node = record
            for parent in parents:
                node = node[parent]
            node[name] = value
        return RaceSpec.from_record(record)

    @classmethod
    def from_record(cls, record: dict) -> RaceSpec:
        """The spec a :meth:`record` describes (read back from JSON). A setting the record lacks takes its
        default; an unknown one is a ValueError naming it, e.g. ``config.mppi.temprature``."""
        return _from_record(cls(), record, "")

    def changed_settings(self) -> dict:
        """The controller settings that differ from the defaults, as ``{dotted name: value}`` (for reports)."""
        default = RaceSpec(self.controller).record()["config"]
        return dict(_changed(self.record()["config"], default, ""))

    def dof_fingerprint(self) -> str | None:
        """The fingerprint of the learned pixel model's weights flown (the packaged weights' own for a packaged
        variant's name or None: :meth:`packaged_variant`); None without a learned pixel model."""
        variant = self.packaged_variant()
        if variant is None:
            return self.dof_weights
        return PACKAGED_WEIGHTS[self.config.pixel_model].fingerprint(variant)

    def packaged_dof(self):
        """The learned pixel model's weights the race flies, when they ship in the package (:meth:`packaged_variant`;
        None for a race without a learned pixel model); a ValueError for weights named by a fingerprint, which the
        caller must pass."""
        if not self.uses_dof:
            return None
        variant = self.packaged_variant()
        if variant is None:
            raise ValueError(f"the race flies DOF weights {self.dof_weights}: pass them as dof_params")
        return PACKAGED_WEIGHTS[self.config.pixel_model].load(variant)

    def key(self) -> str:
        """The cache key: 16 hex digits of the sha256 of :meth:`record` as canonical JSON (every number as a
        float), with the DOF weights as flown (None resolved to the packaged weights' fingerprint). Equal for the
        same race however it was written, and for the two geometric detectors under nominal MPPI on the true state,
        which uses no detection; any other setting, seed, number of laps or DOF weights gives another key."""
        record = {**self.record(), "dof_weights": self.dof_fingerprint(), "course": self.course_fingerprint()}
        for name in KEYED_ONLY_OFF_DEFAULT:  # a race that leaves them at their defaults keeps the key it had before
            field = RaceSpec.__dataclass_fields__[name]
            default = field.default if field.default is not dataclasses.MISSING else field.default_factory()
            if getattr(self, name) == default:
                del record[name]
        if self.controller == "mppi" and self.estimator == "truth" and self.detector == "clipped":
            record["detector"] = "ideal"  # no detection reaches nominal MPPI on the true state: the same laps
        text = json.dumps(_canonical(record), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def course_fingerprint(self) -> str:
        """The course's name, or ``file:`` and the first 16 hex digits of a course file's sha256."""
        if self.course in COURSES:
            return self.course
        return "file:" + hashlib.sha256(Path(self.course).read_bytes()).hexdigest()[:16]

    def policy(self, sample_devices: int = 1):
        """The controller as an episode Policy (:func:`~pixelmpc_jax.sim.controllers.make_policy`), its samples
        split over ``sample_devices`` devices (:class:`~pixelmpc_jax.devices.Execution`)."""
        from pixelmpc_jax.devices import Execution
        from pixelmpc_jax.sim.controllers import make_policy

        return make_policy(self.controller, self.config, Execution(sample_devices=sample_devices))

    def check_weights(self, dof_params, record: dict | None = None) -> None:
        """Raise a ValueError unless ``dof_params`` (None: the packaged weights) are the weights the spec names, and
        they suit its camera: the camera tilt their record states (``record``, that of weights read from a file; the
        packaged weights' own, read here; no tilt stated: the untilted camera). Where the race flies a learned pixel
        model only: nominal MPPI, or PixelMPC with the projection, flies any camera tilt."""
        if not self.uses_dof:
            return
        model, variant = self.config.pixel_model, self.packaged_variant()
        variants = PACKAGED_WEIGHTS[model].variants
        if variant is not None and record is None:
            record = weights_record(variants[variant])
        trained = None if record is None else trained_camera_tilt_deg(record)
        if trained is not None and abs(trained - self.camera_tilt_deg) > 1e-9:
            def camera(tilt: float) -> str:
                return f"the camera tilted up {tilt:g} deg" if tilt else "the untilted camera"

            shipped = sorted({packaged_camera_tilt_deg(path) for path in variants.values()})
            weights = f"packaged {model} weights {variant}" if variant is not None else f"{model} weights"
            raise ValueError(f"the {weights} were trained for {camera(trained)}: with camera_tilt_deg="
                             f"{self.camera_tilt_deg:g} fly the projection pixel model or weights trained for that "
                             f"camera (the package ships {model} weights for camera tilts "
                             f"{', '.join(f'{tilt:g}' for tilt in shipped)} deg)")
        if dof_params is None:
            if variant is None:
                raise ValueError(f"the race flies DOF weights {self.dof_weights}: pass them as dof_params")
            return
        flown = dof_weights_hash(dof_params)
        if flown != self.dof_fingerprint():
            raise ValueError(f"dof_params have fingerprint {flown}, the race names {self.dof_fingerprint()}")


def _canonical(value):
    """``value`` with every number as a float and every sequence as a list (one JSON spelling per value)."""
    if isinstance(value, dict):
        return {k: _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
        return float(value)
    return value


def _from_record(default, record: dict, where: str):
    """``default`` (a dataclass instance) with the settings of ``record``; nested dataclass fields recursively,
    lists as tuples."""
    cls = type(default)
    if not isinstance(record, dict):
        raise ValueError(f"setting {where.rstrip('.') or 'record'} must be a mapping, got {record!r}")
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(record) - fields)
    if unknown:
        raise ValueError(f"unknown setting {where}{unknown[0]}: {cls.__name__} has the fields "
                         f"{', '.join(sorted(fields))}")
    values = {}
    for name, value in record.items():
        nested = getattr(default, name)
        if dataclasses.is_dataclass(nested) and isinstance(value, dict):
            value = _from_record(nested, value, f"{where}{name}.")
        elif isinstance(value, list):
            value = tuple(value)
        values[name] = value
    try:
        return dataclasses.replace(default, **values)
    except TypeError as err:
        raise ValueError(f"setting {where.rstrip('.') or cls.__name__}: {err}") from None


def _changed(record: dict, default: dict, prefix: str):
    """``(dotted name, value)`` of every leaf of ``record`` that differs from ``default``."""
    for name, value in record.items():
        if isinstance(value, dict):
            yield from _changed(value, default.get(name, {}), f"{prefix}{name}.")
        elif _canonical(value) != _canonical(default.get(name)):
            yield f"{prefix}{name}", value
