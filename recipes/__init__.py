"""The recipes, runnable as scripts (``python recipes/spoildice_dsrl.py``) and, in an installed copy, as the
package ``spoil_torchrl.recipes`` behind the console scripts (``spoil-train``, ``spoil-report``, ...; see
``pyproject.toml``). Their Hydra configs ship as ``spoil_torchrl.configs``: ``config_path="../configs"``
resolves to the repository's ``configs/`` for a script and to that package for an installed copy."""
