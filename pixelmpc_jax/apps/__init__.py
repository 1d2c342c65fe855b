"""The experiment apps on top of the library: racing laps (``race``, the laps of a ``spec.RaceSpec``), experiment
grids and the paper's tables and figures (``grid``, ``paper``, ``estimation``, ``frontier``), the onboard video,
the waypoint demo, ``pixelmpc reproduce`` and the runtime harness (``bench``).

They write files and draw plots; the library core (dynamics, world, perception, control, sim, learn) never
imports them.
"""
