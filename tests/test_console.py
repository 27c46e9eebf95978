"""A fresh process of the library prints nothing that does not concern its user."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import pytest


def test_importing_the_simulators_prints_nothing():
    if importlib.util.find_spec("safety_gymnasium") is None:
        pytest.skip("safety-gymnasium not installed")
    code = (
        "import spoil_torchrl, gymnasium\n"
        "from spoil_torchrl.envs import import_safety_gymnasium, make_env\n"
        "import_safety_gymnasium()\n"
        "make_env('SafetyPointCircle1-v0', seed=0).reset()\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stderr == "" and proc.stdout == ""


def test_only_the_unrelated_notices_are_dropped(monkeypatch):
    farama = pytest.importorskip("farama_notifications")
    from spoil_torchrl.console import quiet_unrelated_notices

    table = {
        "gymnasium_robotics": {"1.2.4": "AdroitHandDoorDense-v1 reward changed", "1.5.0": "something else"},
        "gymnasium": {"1.0.0": "please upgrade"},
    }
    monkeypatch.setattr(farama, "notifications", table)
    quiet_unrelated_notices()
    assert table == {
        "gymnasium_robotics": {"1.5.0": "something else"},
        "gymnasium": {"1.0.0": "please upgrade"},
    }
