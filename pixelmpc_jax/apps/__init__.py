"""The jobs on top of the library, one sub-package per kind of job:

- ``racing``: what flies and records a race (``spec.RaceSpec``, the presets, the laps of a race, resumable grids,
  PixelMPC beside nominal MPPI, the onboard video, the waypoint demo);
- ``experiments``: the paper's tables and figures, the speed frontier, the robustness grid, the fault curves, the
  probes and ``pixelmpc reproduce``, each filling in one skeleton (``experiments.skeleton``);
- ``tuning``: ``pixelmpc tune``, the search against the speed frontier, its space and its report;
- ``bench``: the runtime harness.

They write files and draw plots; the library core (dynamics, world, perception, control, sim, learn) never
imports them.
"""
