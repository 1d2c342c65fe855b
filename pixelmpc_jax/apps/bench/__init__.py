"""The runtime harness behind ``pixelmpc bench suite`` (``suite.run_bench``): Table I, the controller step and its
scaling, the particle filter tick, peers on identical work (pytorch-mppi when the ``bench`` extra is
installed) and the matmul limit; ``pixelmpc bench device`` (``device.run_device_suite``), the suite a GPU runs
(Table I's steps, the scaling to 16,384 samples, a batch of 64 laps); ``pixelmpc bench
mppi-step|closed-loop|pf-step|eskf-step|render`` time one part alone. The thin scripts in the repository's
``benchmarks/`` folder call those jobs.
"""
