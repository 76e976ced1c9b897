"""Offline Monte Carlo studies: scenario files -> runs -> metrics, figures and a report.

* :mod:`.scenario` - TOML scenario files validated into frozen dataclasses (errors name file, line and key).
* :mod:`.model` - builds the truth, the per-run IMU / initial / sensor errors and the estimators from a scenario.
* :mod:`.runner` - runs N seeds serially, in processes or on Dask; writes ``metrics.json``, ``runs.nc``, figures.
* :mod:`.metrics` - error series, NEES, fix statistics, the divergence test, aggregation over runs.
* :mod:`.plots`, :mod:`.reports` - PNG figures and ``report.md``.

The command is ``magnav-ins run SCENARIO.toml`` (:mod:`magnav_ins.commands.run`).
"""
