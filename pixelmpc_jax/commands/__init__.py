"""The parsers and handlers of the ``pixelmpc`` command's jobs, one module per command, each adding its parser with
``add_<command>(sub)``; :func:`pixelmpc_jax.cli.build_parser` builds the one parser from them, and
:func:`pixelmpc_jax.cli.main` runs every job under one contract (arguments checked as parsed, one line and exit code
2 for bad input, 130 when interrupted). A handler returns one of the exit codes here, or 0 when done."""

EXIT_FAILED = 1  # the run completed but failed (no lap succeeded, the demo missed its waypoint, a runtime error)
EXIT_USAGE = 2  # bad input (one line names it)
EXIT_INTERRUPTED = 130  # interrupted (what had finished is saved)
