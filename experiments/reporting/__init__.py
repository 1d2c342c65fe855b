"""The repository's reporting tools, beside the results they read: not part of the library, not installed with it.

``pixelmpc report --readme`` and ``--frontier-data`` import this package from a checkout (the command refuses
outside one): the results index (:mod:`~experiments.reporting.index`), the README's results table
(:mod:`~experiments.reporting.readme_table`) and the package's copy of nominal MPPI's committed frontier
(:mod:`~experiments.reporting.frontier_data`). The library never reads ``experiments/results/``.
"""
