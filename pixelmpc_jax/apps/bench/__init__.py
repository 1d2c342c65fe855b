"""The runtime harness behind ``pixelmpc bench`` (``suite.run_bench``): Table I, the controller step and its
scaling, the particle filter tick, peers on identical work (pytorch-mppi when the ``bench`` extra is
installed) and the matmul limit. The thin scripts in the repository's ``benchmarks/`` folder call it.
"""
