"""The compatibility patches of safety-gymnasium 1.0.0: each one's break, shown in a fresh process that leaves
the patch out, and its fix, shown here. A patch the installed stack does not need is skipped with its gate."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed (EXTRAS=dev)"
)

#: SafetyAntVelocity-v1's first observation after ``reset(seed=0)`` on the legacy stack (gymnasium 0.29.1,
#: mujoco 2.3.7, numpy 1.26.4), read there with ``make_safety_gymnasium("SafetyAntVelocity-v1")``.
ANT_RESET_LEGACY = [
    0.658194704787239, 0.9932097434413132, 0.06888988156661442, 0.09076726505272541, 0.023449804814266836,
    0.045899312196799685, 0.008724998293084568, 0.08701448475755366, 0.06317071082430645, -0.09945229996597038,
    0.07148085531751389, -0.09328288493890713, 0.045931089285988824, -0.07322673547034517, -0.054425898285730995,
    -0.031630015636915455, 0.04116305363741329, 0.10425133694426776, -0.012853466294403426, 0.1366463470549686,
    -0.06651946734866136, 0.035151007009301974, 0.09034701816518087, 0.009401229776087457, -0.07434992493538084,
    -0.09217253762584195, -0.045772582566733916,
]  # fmt: skip

ANT_RESET = (
    "import json\n"
    "from spoil_torchrl.envs import make_safety_gymnasium\n"
    "obs, _ = make_safety_gymnasium('SafetyAntVelocity-v1').reset(seed=0)\n"
    "print(json.dumps(obs.tolist()))\n"
)


def needs(name: str):
    """Skip unless the installed stack needs the patch ``name``."""
    from spoil_torchrl.envs.compat import PATCHES

    patch = next(p for p in PATCHES if p.name == name)
    return pytest.mark.skipif(not patch.needed(), reason=f"{name} not needed here ({patch.gate} is false)")


def without(name: str, code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh process with the patch ``name`` left out (in a temporary folder: MuJoCo's own
    warning handler writes ``MUJOCO_LOG.TXT`` into the working directory)."""
    env = dict(os.environ, SPOIL_TORCHRL_SKIP_PATCHES=name, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    with tempfile.TemporaryDirectory() as cwd:
        return subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env, cwd=cwd
        )


def test_every_patch_has_a_gate_a_fix_and_a_documented_upstream_line():
    from spoil_torchrl.envs.compat import PATCHES

    assert len({p.name for p in PATCHES}) == len(PATCHES)
    for patch in PATCHES:
        assert patch.gate and ">=" in patch.gate
        assert (
            ".py:" in patch.apply.__doc__ or ".xml" in patch.apply.__doc__ or ".py``" in patch.apply.__doc__
        )


def test_an_unknown_patch_name_is_refused(monkeypatch):
    from spoil_torchrl.envs.compat import needed_patches

    monkeypatch.setenv("SPOIL_TORCHRL_SKIP_PATCHES", "no-such-patch")
    with pytest.raises(ValueError, match="unknown patch"):
        needed_patches()


def test_the_patches_this_stack_needs_are_applied():
    from spoil_torchrl.envs import applied_patches, import_safety_gymnasium
    from spoil_torchrl.envs.compat import needed_patches

    import_safety_gymnasium()
    assert applied_patches() == [p.name for p in needed_patches()]


@needs("hashable-colours")
def test_hashable_colours():
    from spoil_torchrl.envs import import_safety_gymnasium
    from spoil_torchrl.envs.patches import COLOR_MODULE, HashableArray

    proc = without("hashable-colours", "from spoil_torchrl.envs import import_safety_gymnasium as i; i()")
    assert proc.returncode != 0 and "mutable default" in proc.stderr
    sg = import_safety_gymnasium()
    colors = sys.modules[COLOR_MODULE].COLOR
    assert all(isinstance(v, HashableArray) and hash(v) for v in colors.values())
    np.testing.assert_array_equal(np.asarray(colors["hazard"]), [0, 0, 1, 0.25])
    assert hasattr(sg, "make")


@needs("wrapper-modules")
def test_wrapper_modules():
    proc = without("wrapper-modules", "from spoil_torchrl.envs import import_safety_gymnasium as i; i()")
    assert proc.returncode != 0 and "No module named 'gymnasium.wrappers." in proc.stderr
    from spoil_torchrl.envs import import_safety_gymnasium

    sg = import_safety_gymnasium()
    assert sg.wrappers.SafeTimeLimit.__mro__[1].__module__.startswith("gymnasium.wrappers")


@needs("envspec-fields")
def test_envspec_fields():
    code = "from spoil_torchrl.envs import import_safety_gymnasium as i; i().make('SafetyPointCircle1-v0')"
    proc = without("envspec-fields", code)
    assert proc.returncode != 0 and ("apply_api_compatibility" in proc.stderr or "autoreset" in proc.stderr)
    from spoil_torchrl.envs import import_safety_gymnasium

    env = import_safety_gymnasium().make("SafetyPointCircle1-v0")
    assert env.spec.id == "SafetyPointCircle1-v0" and env.spec.max_episode_steps == 500
    with pytest.raises(NotImplementedError, match="gymnasium 1.0 removed"):
        import_safety_gymnasium().make("SafetyPointCircle1-v0", apply_api_compatibility=True)


@needs("array-copy")
def test_array_copy():
    code = (
        "from spoil_torchrl.envs import import_safety_gymnasium as i\n"
        "env = i().make('SafetyPointCircle1-v0'); env.reset(seed=0); env.step([0.1, 0.2])\n"
    )
    proc = without("array-copy", code)
    assert proc.returncode != 0 and "copy" in proc.stderr
    from spoil_torchrl.envs import import_safety_gymnasium

    steps = []
    for action in ([0.1, 0.2], np.array([0.1, 0.2])):
        env = import_safety_gymnasium().make("SafetyPointCircle1-v0")
        env.reset(seed=0)
        steps.append(env.step(action)[:3])
    np.testing.assert_array_equal(steps[0][0], steps[1][0])
    assert steps[0][1:] == steps[1][1:]


@needs("box-overflow")
def test_box_overflow():
    code = (
        "import warnings; warnings.simplefilter('error')\n"
        "from spoil_torchrl.envs import import_safety_gymnasium as i; i().make('SafetyPointCircle1-v0')\n"
    )
    proc = without("box-overflow", code)
    assert proc.returncode != 0 and "overflow encountered in cast" in proc.stderr
    from spoil_torchrl.envs import import_safety_gymnasium

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = import_safety_gymnasium().make("SafetyPointCircle1-v0")
    assert env.action_space.dtype == np.float64
    np.testing.assert_array_equal(env.action_space.low, [-1.0, -1.0])


@needs("settotalmass-notice")
def test_settotalmass_notice():
    code = "from spoil_torchrl.envs import make_safety_gymnasium as m; m('SafetyHalfCheetahVelocity-v1')"
    assert "settotalmass" in without("settotalmass-notice", code).stderr
    proc = without("", code)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_the_settotalmass_filter_passes_other_warnings_on():
    pytest.importorskip("mujoco")
    import mujoco

    from spoil_torchrl.envs.patches import SETTOTALMASS_NOTICE, _filter_mujoco_warnings

    seen = []
    mujoco.set_mju_user_warning(seen.append)
    try:
        previous, callback = _filter_mujoco_warnings(SETTOTALMASS_NOTICE)
        callback(SETTOTALMASS_NOTICE + " and will be removed")
        callback("Nan, Inf or huge value in QACC at DOF 0")
    finally:
        mujoco.set_mju_user_warning(None)
    assert previous is not None and seen == ["Nan, Inf or huge value in QACC at DOF 0"]


def test_ant_reset_observation_equals_the_legacy_stacks():
    """Both stacks: the first Ant observation is the legacy stack's (the quaternion normalised, as MuJoCo 2.3
    did in ``mj_forward``)."""
    from spoil_torchrl.envs import make_safety_gymnasium

    obs, _ = make_safety_gymnasium("SafetyAntVelocity-v1").reset(seed=0)
    np.testing.assert_allclose(obs, ANT_RESET_LEGACY, rtol=0, atol=1e-12)


@needs("quaternion-reset")
def test_quaternion_reset():
    proc = without("quaternion-reset", ANT_RESET)
    assert proc.returncode == 0, proc.stderr[-2000:]
    unpatched = np.array(json.loads(proc.stdout.strip().splitlines()[-1]))
    assert (
        np.abs(unpatched - ANT_RESET_LEGACY).max() > 1e-3
    )  # the quaternion of norm != 1 (and what it moves)


@needs("track-camera")
def test_track_camera():
    code = (
        "from spoil_torchrl.envs import make_safety_gymnasium as m\n"
        "env = m('SafetyHalfCheetahVelocity-v1', render_mode='rgb_array', width=32, height=32)\n"
        "print(env.unwrapped.mujoco_renderer.camera_id)\n"
    )
    proc = without("track-camera", code)
    assert proc.returncode == 0 and proc.stdout.strip().splitlines()[-1] == "-1", proc.stderr[-2000:]
    import mujoco

    from spoil_torchrl.envs import make_safety_gymnasium

    for env_id in ("SafetyHalfCheetahVelocity-v1", "SafetyAntVelocity-v1"):
        sim = make_safety_gymnasium(env_id, render_mode="rgb_array", width=32, height=32).unwrapped
        track = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_CAMERA, "track")
        assert track >= 0 and sim.mujoco_renderer.camera_id == track
