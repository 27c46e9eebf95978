"""Experiment tracking: labels, hyper-parameters reaching TensorBoard and W&B, missing packages refused early."""

from __future__ import annotations

import importlib.util

import pytest

from spoil_torchrl.runs.settings import SettingsError
from spoil_torchrl.runs.tracking import (
    LOGGER_PACKAGES,
    NO_LOGGER,
    check_logger_available,
    flat_hparams,
    make_logger,
    tracking_labels,
)

SETTINGS = {
    "task": {"env_id": "SafetyPointCircle1-v0", "eval_num_envs": 10},
    "dataset": {"name": "point-circle1-mixed", "n_safe": 10, "return_range": None},
    "algo": {"name": "spoildice", "hidden_cells": [256, 256], "kappa": 0.3},
    "logger": {"type": "csv"},
    "train": {"steps": 10000, "lr": 3e-4, "checkpoint": True},
    "seed": 4,
    "resume": False,
}


def settings(**logger):
    return {**SETTINGS, "logger": logger}


def test_flat_hparams_dotted_scalars():
    flat = flat_hparams(SETTINGS)
    assert flat["algo.name"] == "spoildice" and flat["train.lr"] == 3e-4 and flat["seed"] == 4
    assert flat["algo.hidden_cells"] == "[256, 256]" and flat["dataset.return_range"] == "null"
    assert flat["train.checkpoint"] is True
    assert all(isinstance(v, bool | int | float | str) for v in flat.values())
    assert len(flat) == 14  # every leaf, once


def test_tracking_labels_derived_and_overridden():
    labels = tracking_labels(SETTINGS)
    assert labels == {
        "name": "spoildice_point-circle1-mixed_seed4",
        "project": "spoil_torchrl",
        "group": "point-circle1-mixed/spoildice",
        "tags": ["spoildice", "point-circle1-mixed", "SafetyPointCircle1-v0", "seed4"],
    }
    labels = tracking_labels(settings(type="wandb", project="mine", group="sweep1", tags=["a"]))
    assert (labels["project"], labels["group"], labels["tags"][-1]) == ("mine", "sweep1", "a")


def test_unknown_logger_refused():
    with pytest.raises(SettingsError, match="'tensorbord' is not a logger"):
        check_logger_available("tensorbord")
    for kind in ("csv", "none", None):
        check_logger_available(kind)


@pytest.mark.parametrize(
    "kind,install",
    [
        ("tensorboard", r"pip install 'spoil_torchrl\[tensorboard\]'"),
        ("wandb", r"pip install 'spoil_torchrl\[wandb\]'"),
        ("mlflow", r"pip install 'spoil_torchrl\[mlflow\]' \(or choose logger=csv\)"),
    ],
)
def test_missing_logger_package_refused_with_its_install(monkeypatch, kind, install):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == kind else real(name, *a)
    )
    with pytest.raises(SettingsError, match=install):
        check_logger_available(kind)
    with pytest.raises(SettingsError):  # make_logger checks too, before creating anything
        make_logger(settings(type=kind), "unused")


def test_no_logger():
    assert make_logger(settings(type="none"), "unused") == (None, {})


def test_csv_logger_gets_hparams(tmp_path):
    logger, tracking = make_logger(settings(type="csv"), tmp_path)
    assert tracking == {}
    logger.log_scalar("x", 1.0, step=1)
    (text,) = tmp_path.rglob("hparams*.txt")
    lines = text.read_text().splitlines()
    assert "algo.name: spoildice" in lines and "seed: 4" in lines
    assert not any(line.startswith("resume") for line in lines)


def test_tensorboard_records_hparams(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    logger, _ = make_logger(settings(type="tensorboard"), tmp_path)
    logger.log_scalar("loss", 0.5, step=10)
    logger.experiment.flush()
    hparams = {}
    for events in tmp_path.rglob("events.out.tfevents.*"):
        acc = EventAccumulator(str(events.parent))
        acc.Reload()
        try:
            contents = acc.PluginTagToContent("hparams").values()
        except KeyError:  # the scalars' file; add_hparams writes a file of its own
            continue
        for content in contents:
            data = plugin_data_pb2.HParamsPluginData.FromString(content)
            if data.HasField("session_start_info"):
                info = data.session_start_info.hparams
                hparams = {k: v.string_value or v.number_value or v.bool_value for k, v in info.items()}
    assert hparams["algo.name"] == "spoildice"
    assert hparams["dataset.name"] == "point-circle1-mixed"
    assert hparams["train.lr"] == pytest.approx(3e-4) and hparams["seed"] == 4
    assert "resume" not in hparams


def test_every_logger_config_names_a_logger_the_run_accepts():
    # each configs/logger/<name>.yaml is a logger= choice; its type is one check_logger_available knows
    from pathlib import Path

    from omegaconf import OmegaConf

    folder = Path(__file__).resolve().parents[2] / "configs" / "logger"
    kinds = {path.stem: OmegaConf.load(path).type for path in folder.glob("*.yaml")}
    assert set(kinds) == {"csv", "none", "tensorboard", "wandb", "mlflow"}
    for name, kind in kinds.items():
        assert kind == name or (name == "none" and kind in NO_LOGGER)
        assert kind in {"csv", *LOGGER_PACKAGES} or kind in NO_LOGGER


def test_mlflow_records_params(tmp_path):
    mlflow = pytest.importorskip("mlflow")
    logger, _ = make_logger(settings(type="mlflow"), tmp_path)
    logger.log_scalar("loss", 0.5, step=10)
    run = mlflow.get_run(logger.experiment.info.run_id)  # TorchRL's experiment is the active MLflow run
    assert run.data.params["algo.name"] == "spoildice" and run.data.params["seed"] == "4"


def test_wandb_offline_records_config_and_labels(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_MODE", "offline")
    logger, tracking = make_logger(settings(type="wandb", offline=True, tags=["extra"]), tmp_path)
    run = logger.experiment
    try:
        assert run.config["algo"]["name"] == "spoildice" and run.config["seed"] == 4
        assert run.config["train"]["lr"] == pytest.approx(3e-4) and "resume" not in run.config
        assert run.project == "spoil_torchrl" and run.group == "point-circle1-mixed/spoildice"
        assert set(run.tags) == {
            "spoildice",
            "point-circle1-mixed",
            "SafetyPointCircle1-v0",
            "seed4",
            "extra",
        }
        assert run.id == tracking["wandb_id"]
    finally:
        run.finish()
    assert list(tmp_path.rglob(f"run-{tracking['wandb_id']}.wandb"))  # the offline record, for `wandb sync`
    # a resumed start continues the same W&B run
    logger, again = make_logger(settings(type="wandb", offline=True), tmp_path / "again", tracking=tracking)
    try:
        assert again == tracking and logger.experiment.id == tracking["wandb_id"]
    finally:
        logger.experiment.finish()
