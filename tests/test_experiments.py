"""A paper experiment's sweep through the real command: every cell its own run directory, a second start
passes over the finished cells and resumes a killed one, ``spoil-report --keep`` keeps the finished cells' small
files apart and ``spoil-report --figure`` draws the figure from them."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest

from tests.cli import run_command
from tests.short_runs import RECIPE, ROOT, kill_command_when

pytestmark = pytest.mark.runs


def _command(dataset: Path, sweep_dir: Path) -> list[str]:
    # 2 levels x 2 methods x 1 seed of Fig. 4c on a tiny collected file; 300 steps, so a cell can be killed
    return [
        sys.executable,
        RECIPE,
        "experiment=fig4c",
        "grid=local",
        "dataset=point_circle1_controlled",  # the grid's tasks, narrowed on the command line
        "dataset.performance=0.0,1.0",
        "algo=bc,fbc",
        "seed=0",
        "preset=smoke",
        "train.steps=300",
        "train.batch_size=64",
        "train.eval_episodes=2",
        "logger=none",
        f"dataset.source=file:{dataset}",
        "dataset.n_safe=2",
        "dataset.n_performant=2",
        "dataset.n_unlabeled=null",
        f"hydra.sweep.dir={sweep_dir}",
    ]


def _cells(sweep_dir: Path) -> dict[str, dict]:
    out = {}
    for path in sweep_dir.rglob("results.json"):
        try:
            out[str(path.parent.relative_to(sweep_dir))] = json.loads(path.read_text())
        except ValueError:  # caught mid-write by the watcher
            continue
    return out


CELLS = {
    f"point-circle1-controlled/performance{level}/{algo}/seed0"
    for level in ("0.0", "1.0")
    for algo in ("bc", "fbc")
}


def test_an_experiment_sweep_names_skips_resumes_and_draws_its_cells(tmp_path, tiny_pc1_dataset):
    sweep_dir = tmp_path / "fig4c"
    command = _command(tiny_pc1_dataset, sweep_dir)

    # first start, killed while its third cell is training (after that cell's first checkpoint)
    def third_cell_checkpointed() -> bool:
        cells = _cells(sweep_dir)
        training = [
            d
            for d, r in cells.items()
            if r["status"] == "training" and (sweep_dir / d / "checkpoints").is_dir()
        ]
        done = [d for d, r in cells.items() if r["status"] == "finished"]
        return len(done) == 2 and any(
            (sweep_dir / d / "checkpoints" / "training_state.pt").is_file() for d in training
        )

    kill_command_when(command, third_cell_checkpointed, timeout=300)
    before = _cells(sweep_dir)
    killed = [d for d, r in before.items() if r["status"] != "finished"]
    assert len(killed) == 1 and len(before) == 3
    finished_files = {
        d: sorted((p.relative_to(sweep_dir / d), p.stat().st_mtime_ns) for p in (sweep_dir / d).rglob("*"))
        for d, r in before.items()
        if r["status"] == "finished"
    }

    # the finished cells' small files kept apart while the sweep is unfinished; the killed cell is not among them
    kept_dir = tmp_path / "kept"
    keep = run_command(["recipes/report.py", "--keep", kept_dir, sweep_dir])
    assert keep.returncode == 0, keep.stderr[-3000:]
    assert "2 runs kept" in keep.stdout and f"{killed[0]}: killed" in keep.stderr
    assert sorted(p.relative_to(kept_dir) for p in kept_dir.rglob("*") if p.is_file()) == sorted(
        Path(d) / name for d in finished_files for name in ("config.yaml", "results.json")
    )

    # the same command again: the finished cells are passed over untouched, the killed one resumed, the last run
    again = run_command(command[1:])  # in this process: the sweep's jobs one after the other
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("finished already; nothing to do") == 2
    after = _cells(sweep_dir)
    assert set(after) == CELLS and all(r["status"] == "finished" for r in after.values())
    assert after[killed[0]].get("resumed_at"), "the killed cell was started over, not resumed"
    for d, files in finished_files.items():
        now = sorted((p.relative_to(sweep_dir / d), p.stat().st_mtime_ns) for p in (sweep_dir / d).rglob("*"))
        assert now == files, d
    for d, r in after.items():
        assert r["experiment"] == {
            "name": "fig4c",
            "level": "dataset.performance",
            "value": float(d.split("/")[1][11:]),
        }
    # a third start has nothing left to do
    third = run_command(command[1:])
    assert third.returncode == 0 and third.stdout.count("finished already; nothing to do") == 4

    # the rest kept too; the first two are there already, unchanged
    keep = run_command(["recipes/report.py", "--keep", kept_dir, sweep_dir])
    assert keep.returncode == 0 and "2 runs kept" in keep.stdout and "2 already there" in keep.stdout
    for d in CELLS:
        for name in ("config.yaml", "results.json"):
            assert (kept_dir / d / name).read_bytes() == (sweep_dir / d / name).read_bytes()

    # on another machine (the run folders gone), the kept files copied into a new sweep folder are enough for the
    # same command to pass over every cell
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(kept_dir, elsewhere)
    fourth = run_command(_command(tiny_pc1_dataset, elsewhere)[1:])
    assert fourth.returncode == 0 and fourth.stdout.count("finished already; nothing to do") == 4
    assert sorted(p.relative_to(elsewhere) for p in elsewhere.rglob("*") if p.is_file()) == sorted(
        [Path("multirun.yaml")] + [Path(d) / name for d in CELLS for name in ("config.yaml", "results.json")]
    )

    # the figure and its tables from the kept files alone
    report = run_command(
        [
            "recipes/report.py",
            "--figure",
            kept_dir,
            "--out",
            tmp_path / "fig4c.md",
            "--plot",
            tmp_path / "fig4c.png",
        ]
    )
    assert report.returncode == 0, report.stderr[-3000:]
    text = (tmp_path / "fig4c.md").read_text()
    assert "fig4c: against dataset.performance" in text and "| normalised cost | 0.0 | 1.0 |" in text
    assert text.count("| BC |") >= 2 and text.count("| FBC |") >= 2
    assert (tmp_path / "fig4c.png").stat().st_size > 10_000


def test_a_finished_cell_with_other_settings_is_refused(tmp_path, tiny_pc1_dataset):
    """A changed sweep whose cells keep their names must not pass over runs that are not its own."""
    sweep_dir = tmp_path / "fig4c"
    command = [c for c in _command(tiny_pc1_dataset, sweep_dir) if not c.startswith(("train.steps", "algo="))]
    command[command.index("dataset.performance=0.0,1.0")] = "dataset.performance=1.0"
    first = run_command([*command[1:], "algo=bc"])
    assert first.returncode == 0, first.stderr[-3000:]
    changed = run_command([*command[1:], "algo=bc", "train.lr=0.01"])
    assert (
        changed.returncode == 2
        and "has finished, with other settings (algo.actor_lr, train.lr)" in changed.stderr
    )


@pytest.mark.parametrize(
    "name", ["fig4a", "fig4b", "figB", "fig4c", "fig4d", "figH", "figI", "tableK", "tableL"]
)
def test_every_experiment_expands_into_its_grid(name):
    """The sweep each experiment config describes (Hydra's own expansion, nothing run)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3", job_name="t"):
        cfg = compose(
            "spoildice_dsrl", overrides=[f"experiment={name}", "grid=local"], return_hydra_config=True
        )
    params = cfg.hydra.sweeper.params
    assert cfg.hydra.mode.name == "MULTIRUN" and cfg.resume == "auto"
    assert cfg.hydra.sweep.dir == f"runs/experiments/{name}"
    if name != "figI":  # Fig. I: SpoilDICE's kappa, five seeds
        assert params.algo == "spoildice,bc,fbc,jfbc,demodice_s,dwbc_s" and params.seed == "0,1,2"
    if name == "tableK":
        assert params.dataset == "point_circle1_replay" and cfg.dataset.scheme == "replay"
    elif name not in ("figI", "figH"):  # Fig. H and I: controlled PointCircle1 only
        assert params.dataset == "point_circle1_controlled"
    else:
        assert "dataset" not in params and cfg.dataset.name == "point-circle1-controlled"
    level = cfg.experiment.level
    if level is not None:
        assert params[level].count(",") >= 4  # five levels at least
