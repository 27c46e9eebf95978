"""Each algorithm of the main recipe as (optional) pre-training plus one main-stage stepper.

A builder ``build_<name>(cfg, context)`` takes the algorithm's settings (a mapping, e.g. the Hydra ``algo``
group) and the run's :class:`BuildContext` (the :class:`~spoil_torchrl.data.DualDemoBuffers`, the observation
and action sizes, the :class:`EpisodeConstraint`, the logger), does whatever must happen before the policy is
trained (SpoilDICE: stage 1 of Algorithm 1 -- the discriminators C_P and C_S, the support cut, and the one-time
annotation of the unlabeled storage), and returns :class:`PolicyTraining`: the losses and optimisers of the main
stage and the loss that owns the policy. ``ALGORITHMS`` maps the ``algo.name`` of the recipe to its builder;
adding a baseline means adding a builder (``imitation.py`` for BC-style ones, ``dice.py`` for a dual) and a
config in ``configs/algo/`` (a baseline that needs a role other than D_S, D_P, D_U lists it in the config's
``extra_roles``, as SafeDICE does with its non-preferred D_N).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from spoil_torchrl.algorithms.base import (
    BuildContext,
    EpisodeConstraint,
    PolicyTraining,
    fit_support,
    train_discriminators,
)
from spoil_torchrl.algorithms.dice import (
    build_coptidice,
    build_demodice_s,
    build_demodice_u,
    build_safedice,
    build_spoildice,
)
from spoil_torchrl.algorithms.imitation import build_bc, build_dwbc_s, build_fbc, build_jfbc

Builder = Callable[[Mapping[str, Any], BuildContext], PolicyTraining]

ALGORITHMS: dict[str, Builder] = {
    "spoildice": build_spoildice,
    "bc": build_bc,
    "fbc": build_fbc,
    "jfbc": build_jfbc,
    "demodice_s": build_demodice_s,
    "demodice_u": build_demodice_u,
    "safedice": build_safedice,
    "dwbc_s": build_dwbc_s,
    "coptidice": build_coptidice,
}

__all__ = [
    "ALGORITHMS",
    "BuildContext",
    "Builder",
    "EpisodeConstraint",
    "PolicyTraining",
    "fit_support",
    "train_discriminators",
]
