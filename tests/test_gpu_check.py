"""``benchmarks/gpu_check.sh``, the GPU measurements in one go, and the bench's ``--device``: run here on the CPU
(its ``DEVICE`` argument), since the project's machines have no GPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from tests.cli import ROOT

SCRIPT = ROOT / "benchmarks" / "gpu_check.sh"


def _gpu_check(out, **env) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable, **env}
    return subprocess.run(["bash", str(SCRIPT), str(out), "cpu"], env=env, capture_output=True, text=True)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without a GPU")
def test_the_bench_refuses_a_device_this_machine_lacks_in_one_line():
    proc = subprocess.run(
        [sys.executable, "benchmarks/bench_losses.py", "--device", "cuda"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    assert "this machine has no CUDA device" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.runs
def test_a_failing_part_is_reported_and_the_status_is_one(tmp_path):
    proc = _gpu_check(tmp_path, PARTS="run", RUN_ARGS="preset=smoke algo=no_such_algo")
    assert proc.returncode == 1
    assert "gpu_check: the run failed" in (tmp_path / "run.txt").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["env.txt", "run.txt"]
    assert "torch" in (tmp_path / "env.txt").read_text()


@pytest.mark.slow
def test_the_gpu_check_measures_the_bench_and_the_default_run_on_its_device(tmp_path):
    proc = _gpu_check(
        tmp_path / "out",
        BENCH_ARGS="--threads 1 --steps 3 --repeats 1 --seeds 2",
        RUN_ARGS="preset=smoke",
        RUN_DIR=str(tmp_path / "run"),
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    out = tmp_path / "out"
    names = {"env.txt", "bench.txt", "run.txt", "results.json", "config.yaml", "breakdown.txt"}
    assert {p.name for p in out.iterdir()} == names
    bench = (out / "bench.txt").read_text()
    assert "on cpu" in bench and "compiled, relu_chain" in bench and "2 seeds vmapped" in bench
    results = json.loads((out / "results.json").read_text())
    assert results["status"] == "finished" and "\ndevice: cpu\n" in (out / "config.yaml").read_text()
    assert "main stage" in (out / "breakdown.txt").read_text()
