"""A recipe of one's own: the main recipe's lifecycle called in-process on settings composed with Hydra's
compose API, as docs/usage.md shows it."""

from __future__ import annotations

import dataclasses
import json

import pytest

from spoil_torchrl.runs.directory import LOCK_NAME
from spoil_torchrl.runs.lifecycle import claim_runs, open_runs, pretrain
from spoil_torchrl.runs.seed_run import recorded_failure
from spoil_torchrl.runs.training import train_one
from tests.short_runs import composed_settings


def test_a_recipe_of_ones_own_trains_and_finishes_a_run(tmp_path, tiny_pc1_dataset):
    cfg = composed_settings(tiny_pc1_dataset, "algo=fbc", "train.checkpoint=false")
    with claim_runs(cfg, tmp_path) as claim:
        assert not claim.finished and not claim.vectorised
        assert (tmp_path / LOCK_NAME).is_file()  # held while the block runs
        runs = open_runs(claim)
        with recorded_failure(runs):
            pretrained = [pretrain(inputs) for inputs in runs]
            assert pretrained[0].training.diagnostics["support_share_performant"] > 0  # FBC's cut
            assert pretrained[0].inputs is runs[0]  # the stage's value holds the inputs it was given
            with pytest.raises(dataclasses.FrozenInstanceError):  # no stage changes another's value
                runs[0].checkpoint = {}
            with pytest.raises(dataclasses.FrozenInstanceError):
                pretrained[0].training = None
            results = train_one(pretrained[0])
    assert not (tmp_path / LOCK_NAME).exists()  # released at the end of the block
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert results["status"] == on_disk["status"] == "finished" and on_disk["algo"] == "fbc"
    assert [e["step"] for e in on_disk["evaluations"]] == [100, 200]
    assert (tmp_path / ".hydra" / "config.yaml").is_file()  # the settings, outside a Hydra job
    assert not (tmp_path / ".hydra" / "hydra.yaml").exists()

    # the same command again passes over the finished run (resume=auto) and claims nothing
    again = composed_settings(tiny_pc1_dataset, "algo=fbc", "train.checkpoint=false", "resume=auto")
    with claim_runs(again, tmp_path) as claim:
        assert claim.finished and claim.seeds == []
        assert not (tmp_path / LOCK_NAME).exists()
