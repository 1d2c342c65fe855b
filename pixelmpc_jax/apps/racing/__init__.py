"""What flies and records a race: one race frozen (``spec``), the named races (``presets``), the laps of a race
(``race``), resumable grids of races (``grid``), PixelMPC beside nominal MPPI (``compare``, the main job), the
onboard video (``video``) and the waypoint demo (``waypoint``)."""
