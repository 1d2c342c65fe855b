#!/bin/sh
# The device suite on a GPU, in under 8 minutes on one card: the DOF, vdof and nominal MPPI steps at 512 x 80
# (Table I), the DOF step from 512 to 16,384 samples at T = 80, and a batch of 64 laps of the best race on the true
# state. Writes OUT_DIR/device.json (rewritten after each part) and OUT_DIR/device_scaling.png (the goals marked:
# the DOF step at most 1 ms at 512 x 80 and 2 ms at 16,384 x 80).
#
#     benchmarks/device.sh OUT_DIR
#
# Needs JAX with its GPU plugin (JAX's install guide names the package for the card's CUDA) and this package
# installed (`pip install -e .`). The same as `pixelmpc bench device --out OUT_DIR` at its defaults; its --help
# lists the flags that shrink it for a CPU.
exec pixelmpc bench device --out "${1:?usage: benchmarks/device.sh OUT_DIR}"
