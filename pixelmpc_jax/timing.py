"""The loop's clock, defined once: the control tick (the paper's 40 Hz, also the camera's frame interval) and
the simulated vehicle's rate (960 Hz, FlightGoggles-like), with the plant substeps per tick, and the time a lap may
take before its episode ends.

Imports nothing; every layer may import it. The frame interval of the flow data and the DOF (``perception.flow``,
``learn``), the closed loop's tick and the default ``PFConfig.dt`` are ``CONTROL_DT``.
"""

CONTROL_HZ = 40
PLANT_HZ = 960

CONTROL_DT = 1.0 / CONTROL_HZ  # s, one control tick = one camera frame (0.025)
PLANT_DT = 1.0 / PLANT_HZ  # s, one plant substep
SUBSTEPS_PER_TICK = PLANT_HZ // CONTROL_HZ  # 24
assert SUBSTEPS_PER_TICK * CONTROL_HZ == PLANT_HZ, "the plant rate must be a multiple of the control rate"
LAP_TIME_LIMIT_S = 60.0  # s, an episode's length unless a race says otherwise (a lap of the course takes 20-35 s)
