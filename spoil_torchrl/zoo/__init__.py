"""Policy files and the committed zoo: the format a policy is saved in (:func:`save_policy`, :func:`load_policy`,
:func:`export_checkpoint`) and the expert policies committed with the package (``spoil_torchrl/zoo/<env_id>/``,
:func:`zoo_policy`, :func:`zoo_names`), from which the data layer makes datasets and the runs save their policies.
Training new experts is :mod:`spoil_torchrl.experts`."""

from spoil_torchrl.zoo.policy_files import (
    PolicyFileError,
    export_checkpoint,
    load_policy,
    save_policy,
    zoo_names,
    zoo_policy,
)

__all__ = ["PolicyFileError", "export_checkpoint", "load_policy", "save_policy", "zoo_names", "zoo_policy"]
