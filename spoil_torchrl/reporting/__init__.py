"""Reading finished runs back across run directories, for the reports: a paper experiment collected from its
cells (``experiments``: :func:`~spoil_torchrl.reporting.experiments.load_experiment`,
:func:`~spoil_torchrl.reporting.experiments.finished_results`) and the small files of a sweep's finished runs kept
apart to commit or share (``keep``: :func:`~spoil_torchrl.reporting.keep.keep_finished`). It reads what the run
lifecycle (:mod:`spoil_torchrl.runs`) writes and never writes into a run directory.

Import the module you need, e.g. ``from spoil_torchrl.reporting.experiments import load_experiment``.
"""
