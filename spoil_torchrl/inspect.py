"""Look into an evaluation rollout file: ``python -m spoil_torchrl.inspect <file.mcap> [--plot out.png]``.

Prints the run metadata, whether the file was finished (or which complete episodes were salvaged from a run
that died), and one table row per episode: evaluation step, episode, length, return, cost, feasible return
and strict feasible return (the numbers stored in the episode summaries, see
:mod:`spoil_torchrl.eval.metrics`). ``--plot`` saves a PNG of return, feasible return and cost against the
training step of each evaluation.
For step-level plots open the file in Foxglove (topics ``/eval/step`` and ``/eval/episode``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from spoil_torchrl.eval.mcap_reader import Rollouts, read_rollouts
from spoil_torchrl.eval.mcap_schemas import EPISODE_TOPIC, MCAP_MAGIC, STEP_TOPIC, RolloutFileError

COLUMNS = (
    ("eval step", "evaluation_step"),
    ("episode", "episode"),
    ("length", "length"),
    ("return", "return"),
    ("cost", "cost"),
    ("feasible return", "feasible_return"),
    ("strict feasible", "strict_feasible_return"),
)


def _cell(value) -> str:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def episode_table(rollouts: Rollouts) -> str:
    """The episode table as text, one row per complete episode and a final row of means.

    Examples:
        >>> import tempfile
        >>> from spoil_torchrl.eval import RolloutWriter
        >>> path = Path(tempfile.mkdtemp()) / "rollouts.mcap"
        >>> with RolloutWriter(path, cost_threshold=1.0) as writer:
        ...     for costs in ([0.0, 1.0, 1.0], [0.0, 0.0]):
        ...         for c in costs:
        ...             writer.add_step([0.0], [0.0], reward=1.0, cost=c)
        ...         _ = writer.end_episode()
        >>> print(episode_table(read_rollouts(path)))
        eval step  episode  length  return  cost  feasible return  strict feasible
        ---------  -------  ------  ------  ----  ---------------  ---------------
                0        0       3       3     2                2                1
                0        1       2       2     0                2                2
             mean                      2.5     1                2              1.5
    """
    episodes = rollouts.episodes
    rows = [[_cell(episodes[key][i].item()) for _, key in COLUMNS] for i in range(episodes.batch_size[0])]
    if rows:
        means = [episodes[key].double().mean().item() for _, key in COLUMNS[3:]]
        rows.append(["mean", "", ""] + [_cell(m) for m in means])
    header = [name for name, _ in COLUMNS]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)).rstrip()]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(lines)


def plot_rollouts(rollouts: Rollouts, path: str | Path) -> Path:
    """Save a PNG of the run's evaluations against the training step: return and feasible return (top), episode
    cost with the threshold (bottom); each episode a faint dot, each evaluation's mean a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes = rollouts.episodes
    steps = episodes["evaluation_step"].tolist()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8.5, 5), sharex=True)
    series = (
        (top, "return", "tab:blue", "o"),
        (top, "feasible_return", "tab:green", "s"),
        (bottom, "cost", "tab:red", "o"),
    )
    for ax, key, color, marker in series:
        values = episodes[key].tolist()
        by_step: dict[int, list[float]] = {}
        for step, value in zip(steps, values, strict=True):
            by_step.setdefault(step, []).append(value)
        xs = sorted(by_step)
        label = key.replace("_", " ")
        ax.plot(steps, values, marker, color=color, alpha=0.25, markersize=3, linestyle="none")
        ax.plot(
            xs, [sum(by_step[x]) / len(by_step[x]) for x in xs], "-", color=color, label=f"{label} (mean)"
        )
    top.set_ylabel("return")
    outside = dict(loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)  # never over the points
    top.legend(**outside)
    thresholds = {t for t in episodes["cost_threshold"].tolist() if not math.isnan(t)}
    for t in sorted(thresholds):
        bottom.axhline(t, color="k", linestyle=":", label=f"threshold {t:g}")
    bottom.set_ylabel("episode cost")
    bottom.set_xlabel("training step of the evaluation (dots: episodes)")
    bottom.legend(**outside)
    title = ", ".join(
        f"{k} {rollouts.metadata[k]}" for k in ("task", "algo", "seed") if k in rollouts.metadata
    )
    fig.suptitle(title or "evaluation rollouts")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _ends_like_a_finished_file(path: Path) -> bool:
    """Whether the file ends with the MCAP magic bytes, as a file whose writer finished it does."""
    with open(path, "rb") as f:
        f.seek(0, 2)
        if f.tell() < 2 * len(MCAP_MAGIC):
            return False
        f.seek(-len(MCAP_MAGIC), 2)
        return f.read() == MCAP_MAGIC


def _has_rollout_channels(path: Path) -> bool:
    """Whether the (finished) MCAP file declares a channel on one of the rollout topics."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    channels = [] if summary is None else summary.channels.values()
    return any(channel.topic in (STEP_TOPIC, EPISODE_TOPIC) for channel in channels)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m spoil_torchrl.inspect",
        description="Print the episodes of an evaluation rollout file.",
    )
    parser.add_argument("file", type=Path, help="rollout file (.mcap) written by RolloutWriter")
    parser.add_argument("--plot", type=Path, metavar="OUT.png", help="also save a return / cost plot")
    args = parser.parse_args(argv)
    try:
        rollouts = read_rollouts(args.file)
    except (FileNotFoundError, RolloutFileError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if rollouts.finished and not _has_rollout_channels(args.file):
        print(
            f"error: {args.file}: an MCAP file without rollout topics ({STEP_TOPIC}, {EPISODE_TOPIC}): not "
            "written by the evaluator (recipes/spoildice_dsrl.py writes rollouts.mcap in its run directory)",
            file=sys.stderr,
        )
        return 1
    if not rollouts.finished and _ends_like_a_finished_file(args.file):
        print(
            f"error: {args.file}: the file was finished by its writer but is damaged ({rollouts.stop_reason}); "
            f"{rollouts.episodes.batch_size[0]} complete episode(s) before the damage are readable with "
            "read_rollouts",
            file=sys.stderr,
        )
        return 1
    print(f"file: {args.file}")
    for key, value in sorted(rollouts.metadata.items()):
        print(f"  {key}: {value}")
    n = rollouts.episodes.batch_size[0]
    if rollouts.finished:
        print(f"{n} episode(s)" + (f", {rollouts.skipped} incomplete skipped" if rollouts.skipped else ""))
    else:
        print(
            f"the writer did not finish this file: {n} complete episode(s) salvaged, "
            f"{rollouts.skipped} incomplete skipped; reading stopped at: {rollouts.stop_reason}"
        )
    print(episode_table(rollouts))
    if args.plot is not None:
        print(f"plot: {plot_rollouts(rollouts, args.plot)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
