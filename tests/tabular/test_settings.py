"""The tabular recipes refuse a setting they cannot take at start, in one line naming it, with exit status 2:
their checks (spoil_torchrl.tabular.settings), and the recipes run in this process (tests/cli.py), which also
check the settings they share with the main recipe (threads, progress, the logger) as it does."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from spoil_torchrl.errors import SettingsError
from spoil_torchrl.tabular.settings import check_gridworld_settings, check_tabular_settings
from tests.cli import run_command

ROOT = Path(__file__).resolve().parents[2]


def _config(name: str) -> dict:
    cfg = OmegaConf.to_container(OmegaConf.load(ROOT / "configs" / f"{name}.yaml"))
    cfg.pop("defaults", None)
    cfg.pop("hydra", None)
    if "threads" in cfg:
        cfg["threads"] = 1  # whatever this machine's cores
    return cfg


def _with(cfg: dict, dotted: str, value) -> dict:
    cfg = copy.deepcopy(cfg)
    *path, key = dotted.split(".")
    node = cfg
    for part in path:
        node = node[part]
    if value is _DELETE:
        del node[key]
    else:
        node[key] = value
    return cfg


_DELETE = object()

TABULAR_CASES = [
    ("training.batch_size", 0, "training.batch_size = 0: expected an integer >= 1"),
    ("training.n_samples", -5, "training.n_samples = -5"),
    ("training.n_init", 2.5, "training.n_init = 2.5"),
    ("training.discriminator_steps", 0, "training.discriminator_steps = 0"),
    ("training.dice_steps", 0, "training.dice_steps = 0"),
    ("training.kappa", 2, "training.kappa = 2: expected a quantile in (0, 1)"),
    ("training.kappa", 0.0, "training.kappa = 0.0"),
    ("training.nu_lr", -1e-3, "training.nu_lr = -0.001: expected a finite number > 0"),
    ("training.discriminator_lr", float("nan"), "training.discriminator_lr = nan"),
    ("training.discriminator_cells", [64, 0], "training.discriminator_cells = [64, 0]"),
    ("training.nu_gradient_penalty", -1.0, "training.nu_gradient_penalty = -1.0"),
    ("training.discriminator_gradient_penalty", {"safe": 1.0}, "training.discriminator_gradient_penalty"),
    ("training.init_lagrange", "big", "training.init_lagrange = 'big'"),
    ("training.seed", 3, "training.seed is not a setting"),
    ("problem.n_states", 0, "problem.n_states = 0: expected an integer >= 1"),
    ("problem.n_actions", 1, "problem.n_actions = 1: expected an integer >= 2"),
    ("problem.gamma", 1.0, "problem.gamma = 1.0: expected a number in (0, 1)"),
    ("problem.slip", 1.5, "problem.slip = 1.5: expected a probability in [0, 1]"),
    ("problem.temperature", 0, "problem.temperature = 0: expected a finite number > 0"),
    ("problem.slip", _DELETE, "problem.slip is missing"),
    ("seeds", [], "seeds = []: expected a non-empty list of distinct integers >= 0"),
    ("seeds", None, "seeds = None"),
    ("seeds", [0, 0], "seeds = [0, 0]"),
    ("seeds", [-1], "seeds = [-1]"),
    ("seeds", 3, "seeds = 3"),
    ("threads", 0, "threads = 0: expected an integer >= 1"),
    ("problem.n_state", 7, "problem.n_state is not a setting; the settings of problem: n_states"),
    ("logger.experiment_name", 2024, "logger.experiment_name = 2024"),
]


@pytest.mark.parametrize("key, value, match", TABULAR_CASES)
def test_a_bad_tabular_check_setting_is_named(key, value, match):
    cfg = _config("tabular_spoildice")
    check_tabular_settings(cfg)  # the committed settings pass
    with pytest.raises(SettingsError, match=re.escape(match)):
        check_tabular_settings(_with(cfg, key, value))


GRIDWORLD_CASES = [
    ("seeds", 0, "seeds = 0: expected an integer n >= 1 (seeds 0 .. n-1) or a non-empty list"),
    ("seeds", [], "seeds = []"),
    ("seeds", [1, 1], "seeds = [1, 1]"),
    ("seeds", True, "seeds = True"),
    ("levels", [1.5], "levels = [1.5]: expected a non-empty list of distinct shares in [0, 1]"),
    ("levels", [], "levels = []"),
    ("levels", [0.5, 0.5], "levels = [0.5, 0.5]"),
    ("fixed_level", -0.1, "fixed_level = -0.1: expected a share in [0, 1]"),
    ("figures", "yes", "figures = 'yes': expected true or false"),
    ("grid.size", 0, "grid.size = 0: expected an integer >= 2"),
    ("grid.size", 5, "grid.n_zones = None: the across layout's 4 zones do not fit the 5 x 5 grid"),
    ("grid.layout", "diagonal", "grid.layout = 'diagonal': expected across | along"),
    ("grid.n_zones", -1, "grid.n_zones = -1"),
    ("grid.n_zones", 9, "grid.n_zones = 9: expected an integer from 0 to 7"),
    ("grid.start", [5, 11], "grid.start = [5, 11]: expected a cell [row, col] inside the 11 x 11 grid"),
    ("grid.goal", [5, 0], "grid.start = grid.goal = [5, 0]"),
    ("grid.goal", "corner", "grid.goal = 'corner'"),
    ("grid.slip", 0.8, "grid.slip = 0.8: expected a probability in [0, 0.75)"),
    ("grid.gamma", 0, "grid.gamma = 0"),
    ("grid.cost_limit", -1.0, "grid.cost_limit = -1.0: expected a finite number >= 0"),
    ("grid.cost_model", "entering", "grid.cost_model = 'entering': expected crossing | transition"),
    ("grid.walls", 3, "grid.walls is not a setting"),
    ("methods.thresholds", [], "methods.thresholds = []"),
    ("methods.thresholds", [0.0, -1e-9], "methods.thresholds = [0.0, -1e-09]"),
    ("methods.demodice_alphas", [float("inf")], "methods.demodice_alphas = [inf]"),
    ("methods.spoildice_lagrange", -1.0, "methods.spoildice_lagrange = -1.0"),
    ("methods.alphas", [1.0], "methods.alphas is not a setting"),
]


@pytest.mark.parametrize("key, value, match", GRIDWORLD_CASES)
def test_a_bad_gridworld_setting_is_named(key, value, match):
    cfg = _config("tabular_gridworld")
    check_gridworld_settings(cfg)  # the committed settings pass
    with pytest.raises(SettingsError, match=re.escape(match)):
        check_gridworld_settings(_with(cfg, key, value))


def test_the_settings_that_stay_valid_are_taken():
    check_tabular_settings(_with(_config("tabular_spoildice"), "logger.backend", "none"))
    check_tabular_settings(_with(_config("tabular_spoildice"), "logger.backend", None))
    grid = _config("tabular_gridworld")
    for key, value in [
        ("seeds", 1),
        ("seeds", [7, 3]),
        ("grid.layout", "along"),
        ("grid.n_zones", 0),
        ("grid.start", [0, 0]),
        ("methods.spoildice_lagrange", None),
        ("methods.demodice_alphas", [0.0]),
    ]:
        check_gridworld_settings(_with(grid, key, value))


# -- through the recipes: one line on stderr, exit status 2, before anything is built -----------------------


@pytest.mark.parametrize(
    "recipe, override, match",
    [
        ("tabular_spoildice", "training.batch_size=0", "training.batch_size = 0"),
        ("tabular_spoildice", "seeds=[]", "seeds = []"),
        ("tabular_spoildice", "threads=0", "threads = 0: expected an integer >= 1"),
        (
            "tabular_spoildice",
            "logger.backend=nope",
            "logger.backend='nope' is not a logger; choose one of csv",
        ),
        ("tabular_spoildice", "training.kappa=2", "training.kappa = 2"),
        ("tabular_spoildice", "+training.seed=3", "training.seed is not a setting"),
        ("tabular_gridworld", "seeds=0", "seeds = 0"),
        ("tabular_gridworld", "levels=[1.5]", "levels = [1.5]"),
        ("tabular_gridworld", "grid.cost_model=entering", "grid.cost_model = 'entering'"),
    ],
)
def test_the_tabular_recipes_refuse_a_bad_setting_in_one_line(tmp_path, recipe, override, match):
    run_dir = tmp_path / "run"
    proc = run_command(
        [f"recipes/{recipe}.py", override, "progress=false", f"hydra.run.dir={run_dir}"], cwd=ROOT
    )
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert len(errors) == 1 and errors[0].startswith(f"error: {match}"), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert not (run_dir / "results.json").exists()
    assert "Tabular check" not in proc.stdout  # refused before the run began
