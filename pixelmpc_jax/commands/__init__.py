"""The parsers and handlers of the ``pixelmpc`` command's jobs that run experiments, benchmarks and the search, one
module per job (``experiment``, ``bench``, ``tune``); :func:`pixelmpc_jax.cli.build_parser` builds the one parser
from them beside its own commands, and :func:`pixelmpc_jax.cli.main` runs every job under one contract (arguments
checked as parsed, one line and exit code 2 for bad input, 130 when interrupted)."""
