"""The main job: train SpoilDICE (or a baseline, ``algo=``) on an offline dataset and evaluate it in the task.

    python recipes/spoildice_dsrl.py                     # SpoilDICE on the embedded PointCircle1 dataset
    python recipes/spoildice_dsrl.py algo=bc seed=1
    python recipes/spoildice_dsrl.py preset=smoke        # plumbing check, well under a minute
    python recipes/spoildice_dsrl.py preset=paper        # Table J: 1M iterations, lr 3e-5
    python recipes/spoildice_dsrl.py hydra.run.dir=<run dir> resume=true   # continue a killed run
    python recipes/spoildice_dsrl.py seeds=[0,1,2,3,4]   # five seeds' main stages in one vectorised step

:func:`run` is Algorithm 1 of the SpoilDICE paper
(https://anonymous.4open.science/r/iclr2026_spoildice-214C),
for every seed:

1. Input: D_S, D_P, D_U and the initial states D_0, one TorchRL replay buffer each, states standardised with
   D_U's mean and standard deviation (``open_runs``).
2. Pre-train C_P and C_S, fit the kappa-quantile support cut, annotate D_U once (``pretrain``: the pre-training
   stage of ``algo.name`` in ``spoil_torchrl.algorithms``; a baseline pre-trains what it needs, or nothing).
   The run stores it, and a resumed run loads it instead of training again.
3. Optimise (nu, lambda) and pi with ``torchrl.trainers.Trainer``, evaluating every ``train.eval_interval``
   steps in the real environment (``train``: one seed, or every seed's main stage at once in one vmapped,
   compiled update).
4. Output: the run directory holds ``config.yaml`` (resolved), ``logs/`` (TorchRL logger), ``checkpoints/``,
   ``results.json`` (every evaluation, raw and normalised, and the paper's aggregate; for DICE methods the
   diagnostics of ``spoil_torchrl.eval.dice_diagnostics`` at every evaluation and a text report at the end)
   and ``rollouts.mcap`` (every evaluation episode; ``python -m spoil_torchrl.inspect <file>``).

``results.json`` is rewritten after every evaluation and the MCAP file is flushed after every episode, so an
interrupted run keeps both; ``checkpoints/training_state.pt`` lets it continue exactly (``resume=true``). A
start never overwrites a run: the directory is claimed first (``claim_runs``). ``seeds=[...]`` writes each
seed's single-seed run, with its settings, into ``seed<k>/`` of the run directory. The lifecycle lives in
``spoil_torchrl.runs``, so a recipe of one's own calls the same functions.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from spoil_torchrl.envs import log_mujoco_warnings
from spoil_torchrl.precision import training_precision
from spoil_torchrl.runs.lifecycle import claim_runs, open_runs, pretrain
from spoil_torchrl.runs.outcome import ended_in_one_line, is_sweep_job
from spoil_torchrl.runs.results import summary_table
from spoil_torchrl.runs.seed_run import note_precision, recorded_failure
from spoil_torchrl.runs.settings import name_dataset_by_source
from spoil_torchrl.runs.training import train
from spoil_torchrl.trainers import stop_on_signals

log = logging.getLogger(__name__)


def run(cfg: DictConfig, run_dir: Path) -> dict | list[dict]:
    """Algorithm 1 as configured (or the run in ``run_dir`` continued, ``resume=true``); returns the content of
    ``results.json`` (one per seed, in ``seed<k>/``, for ``seeds=[...]``), or ``[]`` when ``resume=auto`` finds
    the run finished with these settings."""
    with claim_runs(cfg, run_dir) as claim:  # settings checked, then the run directory (or directories) held
        if claim.finished:
            return []
        # 1. Input: D_S, D_P, D_U, D_0 in their buffers; the evaluator, the logger and results.json
        # (claim.seeds: each seed's settings, run directory and the checkpoint it continues from)
        runs = open_runs(claim)
        precision = cfg.train.get("matmul_precision", "highest")
        with recorded_failure(runs), training_precision(precision, runs[0].buffers.device):
            note_precision(runs)  # training's float32 products as configured (IEEE where the device would
            # take bfloat16 or TF32); every rollout's are IEEE
            # 2. Pre-train C_P and C_S, fit the support cut, annotate D_U (each seed from its own random stream;
            # stored in the run, and loaded, not trained again, when it resumes)
            pretrained = [pretrain(inputs) for inputs in runs]
            # 3.-4. Optimise (nu, lambda) and pi, evaluating as it goes; results.json with the aggregate
            results = train(pretrained, vectorised=claim.vectorised)
            return results if claim.vectorised else results[0]


@hydra.main(config_path="../configs", config_name="spoildice_dsrl", version_base="1.3")
def main(cfg: DictConfig) -> None:
    stop_on_signals()  # SIGTERM ends the run like Ctrl-C: marked "interrupted", its checkpoint intact
    logging.captureWarnings(True)  # warnings about the data or settings also go into the run's log
    log_mujoco_warnings()  # into the run's log, not MUJOCO_LOG.TXT in the working directory
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    name_dataset_by_source(cfg, HydraConfig.get().overrides.task)  # runs of another file get its name
    # a user's error, divergence, Ctrl-C; a sweep goes on past a diverged cell (recorded as failed)
    results = []
    with ended_in_one_line("recipes/spoildice_dsrl.py", run_dir, keep_going=is_sweep_job()):
        results = run(cfg, run_dir)
    if not results:  # passed over (finished already) or, in a sweep, diverged: said in one line
        return
    for one in results if isinstance(results, list) else [results]:
        log.info(summary_table(one))
        if "dice_report" in one:
            log.info(f"\n{one['dice_report']}")
    log.info(f"\nrun directory: {run_dir}")


if __name__ == "__main__":
    main()
