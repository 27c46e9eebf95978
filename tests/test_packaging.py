"""The installable package: every subpackage listed, the recipes and configs inside the wheel, console scripts
that run from an installed copy with no clone."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.runs

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SCRIPTS = PYPROJECT["project"]["scripts"]


def test_every_subpackage_is_listed():
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    on_disk = {
        ".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "spoil_torchrl").rglob("__init__.py")
    }
    mapped = PYPROJECT["tool"]["setuptools"]["package-dir"]
    assert listed == on_disk | set(mapped), "update [tool.setuptools] packages in pyproject.toml"
    assert all((ROOT / folder / "__init__.py").exists() for folder in mapped.values())


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_console_scripts_point_at_callables(name):
    module, _, attr = SCRIPTS[name].partition(":")
    assert callable(getattr(importlib.import_module(module), attr))


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """A non-editable install of this checkout (no dependencies: the test environment has them)."""
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("wheel")
    cmd = [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation"]
    proc = subprocess.run([*cmd, "-w", str(build), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = build.glob("spoil_torchrl-*.whl")
    install = [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target)]
    proc = subprocess.run([*install, str(wheel)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return wheel, target


def test_the_wheel_carries_recipes_configs_and_experts(installed):
    wheel, _ = installed
    names = set(zipfile.ZipFile(wheel).namelist())
    for needed in (
        "spoil_torchrl/recipes/spoildice_dsrl.py",
        "spoil_torchrl/recipes/report.py",
        "spoil_torchrl/configs/spoildice_dsrl.yaml",
        "spoil_torchrl/configs/algo/spoildice.yaml",
        "spoil_torchrl/configs/hydra/job_logging/spoil.yaml",
        "spoil_torchrl/configs/hydra/launcher/slurm.yaml",
        "spoil_torchrl/zoo/SafetyPointCircle1-v0/safe-high.pt",
        "spoil_torchrl/dsrl_datasets.csv",
        "spoil_torchrl/env_tasks.csv",
    ):
        assert needed in names, needed
    configs = {n for n in names if n.startswith("spoil_torchrl/configs/") and n.endswith(".yaml")}
    assert len(configs) == len(list((ROOT / "configs").rglob("*.yaml")))


def test_the_installed_dsrl_table_is_the_checkouts(installed):
    """The installed package reads its DSRL table from the package data, with a header row of field names."""
    _, target = installed
    code = (
        "import spoil_torchrl.tasks as t; from importlib import resources; "
        "text = resources.files('spoil_torchrl').joinpath(t.DSRL_TABLE).read_text(); "
        "print(t.__file__); print(len(t.DSRL_DATASETS)); print(text.splitlines()[0])"
    )
    env = {**os.environ, "PYTHONPATH": str(target)}
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env, cwd=target
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    where, count, header = proc.stdout.splitlines()
    assert where.startswith(str(target)) and int(count) == 38
    assert header == (ROOT / "spoil_torchrl" / "dsrl_datasets.csv").read_text().splitlines()[0]
    assert header.split(",")[:6] == [
        "dataset_id",
        "suite",
        "file_name",
        "episode_length",
        "max_return",
        "min_return",
    ]


def test_installed_train_composes_its_config_from_the_package(installed, tmp_path):
    """``spoil-train`` of an installed copy, run outside any clone, finds its configs inside the package."""
    _, target = installed
    env = {**os.environ, "PYTHONPATH": str(target)}
    code = "import sys; from spoil_torchrl.recipes.spoildice_dsrl import main; sys.argv[0] = 'spoil-train'; main()"
    args = ["--cfg", "job", "algo=bc", "preset=smoke"]
    proc = subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "name: bc" in proc.stdout and "steps: 200" in proc.stdout
    where = [sys.executable, "-c", "import spoil_torchrl.recipes as r; print(r.__file__)"]
    located = subprocess.run(where, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert located.stdout.strip().startswith(str(target))


@pytest.mark.slow
def test_pip_install_in_a_fresh_venv_runs_train_and_report(tmp_path):
    """What a user without the Makefile does: a fresh venv, the CPU torch, ``pip install .[safety,minari]``
    (plus safety-gymnasium without its pins, as the README says), which gives the default stack (gymnasium 1.x,
    numpy 2, Minari 0.5.4) in one environment, then ``spoil-train`` and ``spoil-report``."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet", "--disable-pip-version-check"]
    subprocess.run([*pip, os.environ.get("TORCH_SPEC", "torch==2.13.0")], check=True, timeout=1800)
    subprocess.run([*pip, f"{ROOT}[safety,minari]"], check=True, timeout=1800)
    subprocess.run([*pip, "--no-deps", "safety-gymnasium==1.0.0"], check=True, timeout=900)
    code = (
        "import json; from importlib.metadata import version as v\n"
        "print(json.dumps({n: v(n) for n in ('gymnasium', 'numpy', 'minari', 'mujoco', 'safety-gymnasium')}))\n"
    )
    versions = json.loads(
        subprocess.run([str(venv / "bin" / "python"), "-c", code], capture_output=True, text=True).stdout
    )
    assert versions["gymnasium"].startswith("1.") and versions["numpy"].startswith("2.")
    assert versions["minari"] == "0.5.4" and versions["safety-gymnasium"] == "1.0.0"
    imports = (
        "import minari, spoil_torchrl.envs as e; e.import_safety_gymnasium(); print(e.applied_patches())"
    )
    proc = subprocess.run([str(venv / "bin" / "python"), "-c", imports], capture_output=True, text=True)
    assert proc.returncode == 0 and "quaternion-reset" in proc.stdout, proc.stderr[-2000:]
    runs = tmp_path / "runs"
    train = [
        str(venv / "bin" / "spoil-train"),
        "preset=smoke",
        "progress=false",
        f"hydra.run.dir={runs}/smoke",
    ]
    proc = subprocess.run(train, capture_output=True, text=True, cwd=tmp_path, timeout=1800)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| normalized_feasible_return |" in proc.stdout
    report = subprocess.run(
        [str(venv / "bin" / "spoil-report"), str(runs)], capture_output=True, text=True, timeout=600
    )
    assert report.returncode == 0 and "| SpoilDICE | 1 |" in report.stdout, report.stderr[-2000:]
