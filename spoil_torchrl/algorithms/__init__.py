"""Each algorithm of the main recipe as its two stages: a pre-training that returns an immutable value and a
main stage built from it.

An :class:`Algorithm` pairs ``pretrain(cfg, context) -> Pretraining`` with ``main(cfg, context, pretraining) ->
PolicyTraining``. Both take the algorithm's settings (a mapping, e.g. the Hydra ``algo`` group) and the run's
:class:`BuildContext` (the :class:`~spoil_torchrl.data.DualDemoBuffers`, the observation and action sizes, the
:class:`EpisodeConstraint`, the logger). The pre-training does whatever must happen before the policy is trained
(SpoilDICE: stage 1 of Algorithm 1 -- the discriminators C_P and C_S, the support cut, and the one-time
annotation of the unlabeled storage) and returns a :class:`Pretraining`: the annotations it wrote, its
diagnostics and its frozen networks, which a run stores and a resumed run loads instead of training again
(:mod:`spoil_torchrl.runs.pretraining`). The main stage returns :class:`PolicyTraining`: the losses and
optimisers of the main stage and the loss that owns the policy. ``ALGORITHMS`` maps the ``algo.name`` of the
recipe to its algorithm; calling one (``ALGORITHMS[name](cfg, context)``) runs both stages. Adding a baseline
means adding its two functions (``imitation.py`` for BC-style ones, ``dice.py`` for a dual; :func:`no_pretraining`
where it pre-trains nothing) and a config in ``configs/algo/`` (a baseline that needs a role other than D_S,
D_P, D_U lists it in the config's ``extra_roles``, as SafeDICE does with its non-preferred D_N).
"""

from __future__ import annotations

from spoil_torchrl.algorithms.base import (
    NO_PRETRAINING,
    Algorithm,
    BuildContext,
    EpisodeConstraint,
    PolicyTraining,
    Pretraining,
    no_pretraining,
)
from spoil_torchrl.algorithms.dice import (
    build_coptidice,
    build_demodice_s,
    build_demodice_u,
    build_safedice,
    build_spoildice,
    pretrain_demodice_s,
    pretrain_demodice_u,
    pretrain_safedice,
    pretrain_spoildice,
)
from spoil_torchrl.algorithms.discriminators import fit_support, train_discriminators
from spoil_torchrl.algorithms.imitation import (
    build_bc,
    build_dwbc_s,
    build_fbc,
    build_jfbc,
    pretrain_fbc,
    pretrain_jfbc,
)

ALGORITHMS: dict[str, Algorithm] = {
    "spoildice": Algorithm(pretrain_spoildice, build_spoildice),
    "bc": Algorithm(no_pretraining, build_bc),
    "fbc": Algorithm(pretrain_fbc, build_fbc),
    "jfbc": Algorithm(pretrain_jfbc, build_jfbc),
    "demodice_s": Algorithm(pretrain_demodice_s, build_demodice_s),
    "demodice_u": Algorithm(pretrain_demodice_u, build_demodice_u),
    "safedice": Algorithm(pretrain_safedice, build_safedice),
    "dwbc_s": Algorithm(no_pretraining, build_dwbc_s),
    "coptidice": Algorithm(no_pretraining, build_coptidice),
}

__all__ = [
    "ALGORITHMS",
    "NO_PRETRAINING",
    "Algorithm",
    "BuildContext",
    "EpisodeConstraint",
    "PolicyTraining",
    "Pretraining",
    "fit_support",
    "no_pretraining",
    "train_discriminators",
]
