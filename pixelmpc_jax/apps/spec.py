"""One race's settings, frozen: :class:`RaceSpec`. The ``pixelmpc race`` command builds one from its arguments,
:func:`~pixelmpc_jax.apps.race.run_laps` flies it, and an experiment grid keeps a finished cell only while its
:meth:`RaceSpec.key` is unchanged.

Settings that do not change a lap stay out of it: the batch size, the progress bar, the output folder, the
video. The DOF weights enter as their fingerprint (:func:`dof_weights_hash`); the weights themselves are
passed beside the spec.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json

import numpy as np

from pixelmpc_jax.sim.controllers import CONTROLLERS

COURSES = ("alphapilot", "straight")
_FLOATS = ("speed", "t_f", "c_pixel", "max_time_s")


@dataclasses.dataclass(frozen=True)
class RaceSpec:
    """Everything that decides a race's laps; lap i flies PRNG seed ``seed + i``.

    Attributes:
        controller: "mppi" (nominal MPPI) or "pixelmpc".
        speed: target speed, m/s.
        laps: number of laps.
        seed: seed of the first lap.
        perturb: each lap's gates perturbed within the AlphaPilot bounds (with the lap's seed).
        course: "alphapilot" or "straight" (:func:`~pixelmpc_jax.apps.race.make_course`).
        detector: "geometry" or "image" (see :class:`~pixelmpc_jax.sim.episode.EpisodeConfig`).
        estimator: "truth" or "pf" (the particle filter).
        pixel_model: PixelMPC's pixel model, "dof" or "projection".
        t_f: PixelMPC's pixel-cost horizon, s.
        c_pixel: PixelMPC's pixel-cost weight.
        temperature: MPPI's lambda; None for the tuned default.
        num_samples: MPPI samples.
        max_time_s: timeout per lap, s.
        options: further controller settings as sorted ``(name, value)`` pairs (a mapping is accepted; see
            :func:`~pixelmpc_jax.sim.controllers.split_options`).
        dof_weights: fingerprint (:func:`dof_weights_hash`) of the DOF weights flown; None for the packaged
            paper weights. Always None for a race that does not evaluate the DOF.
    """

    controller: str = "mppi"
    speed: float = 14.0
    laps: int = 1
    seed: int = 0
    perturb: bool = False
    course: str = "alphapilot"
    detector: str = "geometry"
    estimator: str = "truth"
    pixel_model: str = "dof"
    t_f: float = 1.0
    c_pixel: float = 9e6
    temperature: float | None = None
    num_samples: int = 512
    max_time_s: float = 60.0
    options: tuple = ()
    dof_weights: str | None = None

    def __post_init__(self):
        if self.controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {self.controller!r}; choose one of {', '.join(CONTROLLERS)}")
        if self.course not in COURSES:
            raise ValueError(f"unknown course {self.course!r}; choose one of {', '.join(COURSES)}")
        if not (isinstance(self.speed, (int, float)) and 0 < self.speed < float("inf")):
            raise ValueError(f"speed must be a positive finite number of m/s, got {self.speed!r}")
        if not (isinstance(self.laps, int) and self.laps > 0):
            raise ValueError(f"laps must be a positive integer, got {self.laps!r}")
        # one spelling per setting, so that the same race always has the same key: floats as floats, the
        # options sorted by name, no DOF weights for a race that does not use them
        for name in _FLOATS:
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.temperature is not None:
            object.__setattr__(self, "temperature", float(self.temperature))
        object.__setattr__(self, "options", tuple(sorted((str(k), v) for k, v in dict(self.options).items())))
        if not self.uses_dof:
            object.__setattr__(self, "dof_weights", None)

    @property
    def uses_dof(self) -> bool:
        """Whether the controller evaluates the DOF network (PixelMPC with the "dof" pixel model)."""
        return self.controller == "pixelmpc" and self.pixel_model == "dof"

    def replace(self, **changes) -> RaceSpec:
        return dataclasses.replace(self, **changes)

    def record(self) -> dict:
        """The spec in JSON types (the options as a name -> value mapping)."""
        record = dataclasses.asdict(self)
        record["options"] = dict(self.options)
        return record

    def dof_fingerprint(self) -> str | None:
        """The fingerprint of the DOF weights flown (:func:`packaged_dof_hash` for None); None without the DOF."""
        if not self.uses_dof:
            return None
        return self.dof_weights or packaged_dof_hash()

    def key(self) -> str:
        """The cache key: 16 hex digits of the sha256 of :meth:`record` as canonical JSON, with the DOF weights
        as flown (None resolved to the packaged weights' fingerprint). Equal for the same race however it was
        written; any other setting, seed, number of laps or DOF weights gives another key."""
        record = {**self.record(), "dof_weights": self.dof_fingerprint()}
        return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]

    def policy(self, sample_devices: int = 1):
        """The controller as an episode Policy (:func:`~pixelmpc_jax.sim.controllers.make_policy`), its samples
        split over ``sample_devices`` devices (``MPPIConfig.sample_devices``: how the step runs, not what it
        computes, so not part of the spec)."""
        from pixelmpc_jax.sim.controllers import make_policy

        options = dict(self.options)
        if sample_devices != 1:
            options["mppi.sample_devices"] = sample_devices
        return make_policy(self.controller, self.temperature, self.num_samples, self.pixel_model, self.t_f,
                           self.c_pixel, options)

    def check_weights(self, dof_params) -> None:
        """Raise a ValueError unless ``dof_params`` (None: the packaged weights) are the weights the spec names."""
        if not self.uses_dof:
            return
        if dof_params is None:
            if self.dof_weights is not None:
                raise ValueError(f"the race flies DOF weights {self.dof_weights}: pass them as dof_params")
            return
        flown = dof_weights_hash(dof_params)
        if flown != self.dof_fingerprint():
            raise ValueError(f"dof_params have fingerprint {flown}, the race names {self.dof_fingerprint()}")


def dof_weights_hash(params) -> str:
    """A short fingerprint of DOF weights: the first 16 hex digits of the sha256 of every leaf's dtype, shape
    and bytes (in ``jax.tree_util.tree_leaves`` order)."""
    import jax

    digest = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(params):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()[:16]


def packaged_dof_hash() -> str:
    """:func:`dof_weights_hash` of the DOF weights shipped inside the package (computed again only when the
    weights file changes)."""
    from pixelmpc_jax.dynamics import dof

    path = dof.PACKAGED_VARIANTS["paper"]
    stat = path.stat() if path.exists() else None
    return _packaged_hash(str(path), stat and (stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=4)
def _packaged_hash(path: str, version) -> str:
    """The packaged weights' fingerprint, cached by the file's ``path`` and ``version`` (mtime, size)."""
    from pixelmpc_jax.dynamics import dof

    return dof_weights_hash(dof.load_packaged_dof())
