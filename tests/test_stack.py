"""Every dataset and result records its software stack; data or runs from another stack are refused, made
again or flagged, never silently mixed."""

from __future__ import annotations

import json
import shutil

import h5py
import pytest

from spoil_torchrl.stack import (
    DEFAULT_STACK,
    LEGACY_STACK,
    current_stack,
    stack_differences,
    stack_label,
    stack_name,
)


def other_stack() -> dict:
    """This stack with the simulator and gymnasium of the other supported stack."""
    here = current_stack()
    other = LEGACY_STACK if stack_name(here) != "legacy" else DEFAULT_STACK
    return dict(here, mujoco=other["mujoco"], gymnasium=other["gymnasium"])


def test_the_current_stack_names_the_versions_that_decide_the_numbers():
    stack = current_stack()
    assert set(stack) == {"mujoco", "gymnasium", "numpy", "torch", "safety_gymnasium", "python"}
    import numpy
    import torch

    assert stack["numpy"] == numpy.__version__ and stack["torch"] == torch.__version__
    assert stack_differences(stack) == []
    assert stack_differences(None)  # no record: differs
    assert [d.split()[0] for d in stack_differences(other_stack())] == ["mujoco", "gymnasium"]
    assert stack_label(other_stack()).startswith("mujoco ")


def _restack(path, stack):
    from spoil_torchrl.data.hdf5 import METADATA_ATTR

    with h5py.File(path, "r+") as f:
        meta = json.loads(f.attrs[METADATA_ATTR])
        meta["stack"] = stack
        f.attrs[METADATA_ATTR] = json.dumps(meta)


def test_a_file_from_another_stack_is_flagged_and_recorded(tmp_path, tiny_pc1_dataset):
    from spoil_torchrl.data.hdf5 import read_metadata
    from spoil_torchrl.data.prepare import prepare_dataset

    assert read_metadata(tiny_pc1_dataset)["stack"] == current_stack()
    cfg = {"source": f"file:{tiny_pc1_dataset}", "scheme": "controlled", "n_safe": 2, "performance": 0.5,
           "n_performant": 2, "safeness": 0.5, "n_unlabeled": None}  # fmt: skip
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        same = prepare_dataset(cfg, env_id="SafetyPointCircle1-v0")
    assert same.summary()["stack"] == current_stack()
    other = tmp_path / "other.hdf5"
    shutil.copy(tiny_pc1_dataset, other)
    _restack(other, other_stack())
    with pytest.warns(UserWarning, match="made on another software stack"):
        data = prepare_dataset(dict(cfg, source=f"file:{other}"), env_id="SafetyPointCircle1-v0")
    assert data.summary()["stack"] == other_stack()


def test_a_run_does_not_resume_on_another_stack():
    from spoil_torchrl.runs.checkpoint import CheckpointError
    from spoil_torchrl.runs.resume import check_resumable

    check_resumable({"config_yaml": "seed: 0", "results": {"stack": current_stack()}}, "seed: 0", "run")
    check_resumable({"config_yaml": "seed: 0", "results": {}}, "seed: 0", "run")  # made before records
    with pytest.raises(CheckpointError, match="another software stack.*STACK=legacy"):
        check_resumable({"config_yaml": "seed: 0", "results": {"stack": other_stack()}}, "seed: 0", "run")
    with pytest.raises(CheckpointError, match="other settings"):
        check_resumable({"config_yaml": "seed: 1", "results": {}}, "seed: 0", "run")


def test_the_report_names_each_tables_stack_and_warns_when_they_mix():
    from spoil_torchrl.recipes.report import markdown, stack_warnings, summarize

    def results(seed, stack, data_stack=None):
        return {
            "algo": "bc", "dataset": "d", "seed": seed, "total_seconds": 1.0, "stack": stack,
            "data": {"stack": data_stack or stack},
            "aggregate": {"normalized_feasible_return": 0.5, "normalized_cost": 0.5, "normalized_return": 0.5},
        }  # fmt: skip

    here = current_stack()
    same = {("d", "bc"): [results(0, here), results(1, here)]}
    assert stack_warnings(same) == []
    assert f"Stack: {stack_name(here)} ({stack_label(here)})." in markdown(summarize(same))
    unrecorded = {("d", "bc"): [dict(results(0, here), stack=None)]}
    assert "Stack: not recorded (made before runs recorded their stack: the legacy stack)." in markdown(
        summarize(unrecorded)
    )
    mixed = {("d", "bc"): [results(0, here), results(1, other_stack())]}
    (warning,) = stack_warnings(mixed)
    assert "the runs on d come from 2 software stacks" in warning
    crossed = {("d", "bc"): [results(0, here, data_stack=other_stack())]}
    (warning,) = stack_warnings(crossed)
    assert "trained on data made on" in warning
    parts = [
        {"stage": "pre-training", "host": "a", "cpu": "EPYC"},
        {"stage": "main", "from_step": 0, "host": "a", "cpu": "EPYC"},
        {"stage": "main", "from_step": 5000, "host": "b", "cpu": "Xeon"},
    ]
    moved = {("d", "bc"): [dict(results(0, here), ran_on=parts, resumed_elsewhere=True), results(1, here)]}
    (warning,) = stack_warnings(moved)
    assert warning == (
        "bc seed 0 on d was resumed elsewhere: pre-training on a (EPYC); main from step 0 on a (EPYC); "
        "main from step 5000 on b (Xeon)"
    )
