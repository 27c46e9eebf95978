"""Sweeps of the main recipe (``-m``) keep every job, with the basic launcher and with the Hydra launchers."""

from __future__ import annotations

import importlib.util
import json
import sys

import pytest

from tests.cli import run_command
from tests.short_runs import RECIPE

pytestmark = pytest.mark.runs


def _sweep(tmp_path, dataset, *overrides):
    cmd = [
        sys.executable,
        RECIPE,
        "-m",
        "preset=smoke",
        "algo=bc",
        "logger=none",
        "progress=false",
        f"dataset.source=file:{dataset}",
        "dataset.n_safe=2",
        "dataset.n_performant=2",
        f"hydra.sweep.dir={tmp_path}",
        *overrides,
    ]
    proc = run_command(cmd[1:])
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = sorted(tmp_path.rglob("results.json"))
    return [json.loads(p.read_text()) for p in runs], runs


def test_a_sweep_keeps_every_job(tmp_path, tiny_pc1_dataset):
    results, paths = _sweep(tmp_path, tiny_pc1_dataset, "train.lr=1e-4,3e-4")
    assert len(paths) == 2 and len({p.parent for p in paths}) == 2
    assert all(r["status"] == "finished" for r in results)
    lrs = sorted(
        float(line.split(":")[1])
        for p in paths
        for line in (p.parent / "config.yaml").read_text().splitlines()
        if line.strip().startswith("lr:") and line.startswith("  lr")
    )
    assert lrs == [1e-4, 3e-4]


@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_hydra_launchers_run_a_two_job_sweep(tmp_path, tiny_pc1_dataset, launcher):
    plugin = {
        "joblib": "hydra_plugins.hydra_joblib_launcher",
        "submitit_local": "hydra_plugins.hydra_submitit_launcher",
    }
    if importlib.util.find_spec(plugin[launcher]) is None:
        pytest.skip(f"the launchers extra is not installed ({plugin[launcher]})")
    extra = ["hydra.launcher.n_jobs=2"] if launcher == "joblib" else ["hydra.launcher.timeout_min=10"]
    results, paths = _sweep(tmp_path, tiny_pc1_dataset, f"hydra/launcher={launcher}", "seed=0,1", *extra)
    assert sorted(r["seed"] for r in results) == [0, 1] and all(r["status"] == "finished" for r in results)
