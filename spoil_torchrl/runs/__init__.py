"""The run lifecycle, shared by every recipe: a run directory claimed under a lock (``directory``), settings checked
before anything is loaded (``settings``), checkpoints and exact resumption (``checkpoint``, ``resume``),
``results.json`` and its aggregate (``results``), the TorchRL logger (``tracking``), one-line endings for a user's
error, a divergence or Ctrl-C (``outcome``), and the seed runner of the main recipe: the claim of its run
directories (``claim``), the input of Algorithm 1 and the pre-training (``lifecycle``), the values one seed's
stages hand on and its bookkeeping (``seed_run``) and the main stage (``training``).

The package imports nothing on its own: expert training and the reports read ``directory`` and ``checkpoint``
without loading the seed runner, and the reports read finished runs back through :mod:`spoil_torchrl.reporting`.
Import the module you need, e.g. ``from spoil_torchrl.runs.lifecycle import claim_runs, open_runs, pretrain``.
"""
