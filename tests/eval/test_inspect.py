"""``python -m spoil_torchrl.inspect``: the episode table, the plot, and clear errors."""

from __future__ import annotations

from spoil_torchrl.inspect import main
from tests.cli import run_command
from tests.eval.test_mcap_io import EPISODES, write_file

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_cli_prints_the_table_and_saves_a_plot(tmp_path):
    path = tmp_path / "rollouts.mcap"
    write_file(path)
    plot = tmp_path / "plots" / "rollouts.png"
    # spoil-inspect in a process of its own
    proc = run_command(["-m", "spoil_torchrl.inspect", path, "--plot", plot], cwd=tmp_path, real=True)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "task: OfflinePointCircle1Gymnasium-v0" in out and "4 episode(s)" in out
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("eval step"))
    assert lines[header].split("  ")[:3] == ["eval step", "episode", "length"]
    assert "feasible return" in lines[header]
    rows = [line.split() for line in lines[header + 2 : header + 2 + len(EPISODES)]]
    # eval step, episode, length, return, cost, feasible return, strict feasible (see test_round_trip)
    assert rows[1] == ["0", "1", "7", "28", "3", "15", "1"]
    assert rows[3] == ["1000", "3", "6", "21", "3", "15", "1"]
    assert lines[header + 2 + len(EPISODES)].split()[0] == "mean"
    assert plot.read_bytes()[:8] == PNG_MAGIC and plot.stat().st_size > 5000


def test_missing_and_non_mcap_files(tmp_path, capsys):
    assert main([str(tmp_path / "nope.mcap")]) == 1
    assert "no such rollout file" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not a rollout file")
    assert main([str(tmp_path / "notes.txt")]) == 1
    assert "not an MCAP file" in capsys.readouterr().err


def test_salvaged_file_is_reported(tmp_path, capsys):
    path = tmp_path / "rollouts.mcap"
    writer = write_file(path, finish=False)  # the writer has not finished: as after a crash
    assert main([str(path)]) == 0
    writer.finish()
    out = capsys.readouterr().out
    assert "did not finish this file: 4 complete episode(s) salvaged" in out
