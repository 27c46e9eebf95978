"""Collect finished runs of ``recipes/spoildice_dsrl.py`` into a Table-1-style markdown table and a trade-off plot.

    python recipes/report.py runs/final --out docs/results.md --plot docs/tradeoff.png --curves docs/curves.png
    python recipes/report.py --figure docs/results/fig4c --out docs/experiments/fig4c.md --plot docs/experiments/fig4c.png
    python recipes/report.py --keep docs/results/fig4c runs/experiments/fig4c

``--keep DEST`` copies each finished run's ``results.json`` and ``config.yaml`` under the folders into ``DEST``
(:func:`spoil_torchrl.reporting.keep.keep_finished`), at its path relative to its folder: what the tables
and figures read, to commit or share while a sweep goes on. Runs not finished are listed; one already kept the
same is left; one kept with other contents is refused (exit status 1), never overwritten.

``--figure`` reads the cells of a paper experiment (``experiment=...``) instead: per level and method the mean ±
s.e. over seeds, averaged over the tasks present and per task, the aggregate statistics
(:func:`spoil_torchrl.eval.experiment_tables.experiment_statistics`), the DICE diagnostics of the weighted
methods per level (:func:`~spoil_torchrl.eval.experiment_tables.diagnostics_markdown`) and the figure
(:func:`spoil_torchrl.eval.figures.plot_levels`).

Every ``results.json`` under the given folders with ``status == "finished"`` counts. Per dataset and algorithm,
each seed contributes its aggregate (the mean of its last evaluations, as the paper does); the table gives the
mean ± standard error over seeds of the normalised feasible return and the normalised cost, and marks safe
results (mean normalised cost <= 1) in bold, as the paper's Table 1 / Table L. Algorithms are listed in the
paper's order. Runs that did not finish (failed, interrupted, killed, still running) are listed as skipped, with
the reason, as is a ``results.json`` that is not a finished run's results (not a JSON object, without a
``status``, finished without an ``aggregate``: an expert's run, a file written by hand). A seed found twice
(unless ``--latest``: the newest run counts), or runs of one dataset made with different training budgets
(the ``train`` section of the ``config.yaml`` beside each ``results.json``), stop the report with an error
naming the runs. Each table names the software stack its runs were made on
(``results.json``'s ``stack``), and the report warns when one dataset's runs come from several stacks, a
run's data were made on another stack than the run (their simulators differ), or a run was resumed on
another machine than the one that started it (``resumed_elsewhere``).
The plot puts normalised cost on x and normalised feasible return on y, one marker per algorithm with
standard-error bars, the safe region (cost <= 1) shaded; the curves plot each metric against the training
step (mean over seeds, standard error shaded); both from ``spoil_torchrl.eval.figures`` (one colour and
marker per algorithm on every panel, one legend outside the panels).
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import torch

from spoil_torchrl.eval import format_mean_stderr, mean_stderr
from spoil_torchrl.eval.figures import ALGORITHM_NAMES, algorithm_order, plot_learning_curves, plot_tradeoff
from spoil_torchrl.reporting.constraints import constraint_markdown
from spoil_torchrl.reporting.experiments import finished_results, incomplete, train_section
from spoil_torchrl.stack import stack_label, stack_name

METRICS = ("normalized_feasible_return", "normalized_cost", "normalized_return")


def load_runs(
    folders: list[Path], *, latest: bool = False, skipped: list[tuple[Path, str]] | None = None
) -> dict[tuple[str, str], list[dict]]:
    """``(dataset, algo) -> [results of each finished seed]``, sorted by seed.

    Runs that are not finished (failed, interrupted, killed, still training: :func:`run_status`), and
    ``results.json`` files that are not a finished run's results (not a JSON object, no ``status``, no
    ``aggregate`` or a metric of it: :func:`~spoil_torchrl.reporting.experiments.incomplete`), are left out and
    appended to ``skipped`` as ``(path, reason)``. A seed found twice is an error, unless ``latest``: then the
    run whose ``results.json`` was written last counts and the others are skipped.
    """
    runs: dict[tuple[str, str], list[dict]] = defaultdict(list)
    found: dict[tuple[str, str, int], list[tuple[float, Path, dict]]] = defaultdict(list)
    skipped = [] if skipped is None else skipped
    for path, results in finished_results(folders, skipped):
        problem = incomplete(results)  # e.g. an expert's run, or a file written by hand
        lacking = [metric for metric in METRICS if problem is None and metric not in results["aggregate"]]
        if problem is not None or lacking:
            skipped.append((path, problem or f"finished, but its aggregate has no {', '.join(lacking)}"))
            continue
        key = (results["dataset"], results["algo"], results["seed"])
        found[key].append((path.stat().st_mtime, path, results))
    _refuse_mixed_data(found)
    budgets: dict[str, dict[str | None, Path]] = defaultdict(dict)
    for key, copies in sorted(found.items(), key=lambda item: str(item[0])):
        copies.sort(key=lambda c: c[0])
        if len(copies) > 1 and not latest:
            raise ValueError(
                f"seed {key[2]} of {key[1]} on {key[0]} twice: {copies[0][1]} and {copies[1][1]} "
                "(pass --latest to use the newest run of each seed, or the folder of one sweep)"
            )
        skipped.extend((path, f"an older run of seed {key[2]}") for _, path, _ in copies[:-1])
        _, path, results = copies[-1]
        budgets[results["dataset"]].setdefault(train_section(path), path)
        runs[(results["dataset"], results["algo"])].append(results)
    for dataset, settings in budgets.items():
        if len(settings) > 1:
            raise ValueError(
                f"runs on {dataset} were made with different train settings, e.g. "
                + " and ".join(map(str, settings.values()))
                + " (report the folder of one sweep or budget)"
            )
    for group in runs.values():
        group.sort(key=lambda r: r["seed"])
    return dict(runs)


def _refuse_mixed_data(found: dict) -> None:
    """Runs filed under one dataset name must have been trained on the same data (``results.json``'s
    ``data.fingerprint``; runs made before it was recorded are not checked)."""
    seen: dict[str, tuple[str, Path]] = {}
    for (dataset, _, _), copies in sorted(found.items(), key=lambda item: str(item[0])):
        for _, path, results in copies:
            fingerprint = (results.get("data") or {}).get("fingerprint")
            if fingerprint is None:
                continue
            first = seen.setdefault(dataset, (fingerprint, path))
            if first[0] != fingerprint:
                raise ValueError(
                    f"runs filed as dataset {dataset} were trained on different data: {first[1].parent} "
                    f"(data {first[0]}) and {path.parent} (data {fingerprint}); give each its own "
                    "dataset.name, or report them separately"
                )


def run_stack(results: dict) -> str:
    """The software stack a run was made on, as the report names it (``results.json``'s ``stack``)."""
    stack = results.get("stack")
    if stack is None:
        return "not recorded (made before runs recorded their stack: the legacy stack)"
    return f"{stack_name(stack)} ({stack_label(stack)})"


def stack_warnings(runs: dict[tuple[str, str], list[dict]]) -> list[str]:
    """A line for each dataset whose runs come from more than one software stack, and for runs trained on data
    made on another stack than their own: their numbers are not comparable (other physics). A line, too, for
    each run whose parts ran on more than one machine (``results.json``'s ``resumed_elsewhere``): it continued
    exactly from what it stored, but its arithmetic was done on different CPUs."""
    out = []
    by_dataset: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for (dataset, _), group in runs.items():
        for results in group:
            by_dataset[dataset][run_stack(results)] += 1
            if results.get("resumed_elsewhere"):
                where = "; ".join(
                    f"{part['stage']}{' from step ' + str(part['from_step']) if 'from_step' in part else ''} "
                    f"on {part.get('host')} ({part.get('cpu')})"
                    for part in results.get("ran_on", [])
                )
                out.append(
                    f"{results['algo']} seed {results['seed']} on {dataset} was resumed elsewhere: {where}"
                )
            data_stack = (results.get("data") or {}).get("stack")
            if data_stack is not None and results.get("stack") is not None:
                if stack_label(data_stack) != stack_label(results["stack"]):
                    out.append(
                        f"{results['algo']} seed {results['seed']} on {dataset} was trained on data made on "
                        f"{stack_label(data_stack)} and evaluated on {stack_label(results['stack'])}"
                    )
    for dataset, stacks in sorted(by_dataset.items()):
        if len(stacks) > 1:
            out.append(
                f"the runs on {dataset} come from {len(stacks)} software stacks, whose simulators differ: "
                + "; ".join(f"{count} on {name}" for name, count in sorted(stacks.items()))
            )
    return out


def summarize(runs: dict[tuple[str, str], list[dict]]) -> dict[tuple[str, str], dict]:
    """Per group: seeds and mean / standard error of each metric's per-seed aggregate."""
    out = {}
    for key, group in runs.items():
        row = {
            "seeds": [r["seed"] for r in group],
            "stacks": sorted({run_stack(r) for r in group}),
            "minutes": sum(r["total_seconds"] for r in group) / 60,
            "per_seed": [
                (r["aggregate"]["normalized_feasible_return"], r["aggregate"]["normalized_cost"])
                for r in group
            ],
        }
        for metric in METRICS:
            row[metric] = mean_stderr(torch.tensor([r["aggregate"][metric] for r in group]))
        diagnostics = [r["dice_diagnostics"] for r in group if r.get("dice_diagnostics")]
        if len(diagnostics) == len(group):  # DICE methods: nu's share and the weight on cost > 0, final
            row["bellman_share"] = sum(d["variance_share"]["bellman"] for d in diagnostics) / len(group)
            row["weight_on_cost"] = sum(d["weight_share"]["cost>0"]["weight"] for d in diagnostics) / len(
                group
            )
        out[key] = row
    return out


def _cell(mean: float, se: float, bold: bool = False) -> str:
    text = format_mean_stderr(mean, se)
    return f"**{text}**" if bold else text


def markdown(summary: dict[tuple[str, str], dict]) -> str:
    """One table per dataset: normalised feasible return and cost (mean ± s.e. over seeds); safe in bold."""
    lines = []
    for dataset in sorted({d for d, _ in summary}):
        lines += [
            f"**{dataset}**",
            "",
            "| algorithm | seeds | normalised feasible return | normalised cost | normalised return | "
            "per seed (feasible return / cost) | nu's share / weight on cost > 0 |",
            "|---|---|---|---|---|---|---|",
        ]
        for algo in sorted((a for d, a in summary if d == dataset), key=algorithm_order):
            row = summary[(dataset, algo)]
            safe = row["normalized_cost"][0] <= 1.0
            per_seed = ", ".join(f"{f:.2f} / {c:.2f}" for f, c in row["per_seed"])
            lines.append(
                f"| {ALGORITHM_NAMES.get(algo, algo)} | {len(row['seeds'])} | "
                f"{_cell(*row['normalized_feasible_return'], bold=safe)} | "
                f"{_cell(*row['normalized_cost'], bold=safe)} | {_cell(*row['normalized_return'])} | {per_seed} | "
                + (
                    f"{100 * row['bellman_share']:.0f} % / {100 * row['weight_on_cost']:.0f} % |"
                    if "bellman_share" in row
                    else "- |"
                )
            )
        stacks = sorted({name for (d, a), row in summary.items() if d == dataset for name in row["stacks"]})
        lines += ["", f"Stack: {' and '.join(stacks)}.", ""]
    lines.append(
        "Bold: safe on average (normalised cost <= 1). Each seed contributes the mean of its last "
        "evaluations (results.json `aggregate`); ± is the standard error over seeds. Last column (DICE methods, "
        "mean over seeds at the final evaluation): the share of the advantage's variance carried by nu's "
        "Bellman term, and the share of the policy-extraction weight on transitions with true cost > 0."
    )
    return "\n".join(lines)


def learning_curves(runs: dict[tuple[str, str], list[dict]]) -> dict[tuple[str, str], dict]:
    """Per group: the evaluation steps shared by all its seeds and, per metric, the mean and standard error
    over seeds at each of them."""
    out = {}
    for key, group in runs.items():
        steps = sorted(set.intersection(*({e["step"] for e in r["evaluations"]} for r in group)))
        curves = {"steps": steps}
        for metric in METRICS[:2]:
            by_step = [
                mean_stderr(
                    torch.tensor([next(e[metric] for e in r["evaluations"] if e["step"] == s) for r in group])
                )
                for s in steps
            ]
            curves[metric] = by_step
        out[key] = curves
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("folders", nargs="+", type=Path, help="folders searched for results.json")
    parser.add_argument("--out", type=Path, help="write the markdown table here (also printed)")
    parser.add_argument("--plot", type=Path, help="save the trade-off scatter PNG here")
    parser.add_argument(
        "--curves", type=Path, help="save the learning curves (mean ± s.e. over seeds) PNG here"
    )
    parser.add_argument(
        "--latest", action="store_true", help="a seed run more than once counts with its newest run"
    )
    parser.add_argument(
        "--figure",
        action="store_true",
        help="the folders hold the cells of a paper experiment (experiment=...): its per-level tables, "
        "aggregate statistics (--out) and figure (--plot)",
    )
    parser.add_argument(
        "--experiment", help="with --figure: the experiment to report, when several are found"
    )
    parser.add_argument(
        "--mixed-files",
        action="store_true",
        help="with --figure: the cells of one dataset may come from different files of it (a generated "
        "dataset made again on another CPU); the tables say how many runs each file has",
    )
    parser.add_argument(
        "--keep",
        type=Path,
        metavar="DEST",
        help="copy each finished run's results.json and config.yaml into DEST (at its path relative to its "
        "folder), instead of reporting",
    )
    args = parser.parse_args()
    if args.keep is not None:
        return keep_report(parser, args)
    for flag, path in (("--out", args.out), ("--plot", args.plot), ("--curves", args.curves)):
        if path is not None and path.is_dir():
            parser.error(f"{flag} {path} is a directory; give the file to write")
        if flag != "--out" and path is not None and path.suffix.lower() not in (".png", ".pdf", ".svg"):
            # matplotlib would add an extension and write a file that was not named
            parser.error(f"{flag} {path}: give a file name ending in .png, .pdf or .svg")
    if args.figure:
        return figure_report(parser, args)
    if args.experiment or args.mixed_files:
        parser.error(f"{'--experiment' if args.experiment else '--mixed-files'} needs --figure")
    skipped: list[tuple[Path, str]] = []
    try:
        runs = load_runs(args.folders, latest=args.latest, skipped=skipped)
    except (FileNotFoundError, ValueError) as error:
        parser.error(str(error))
    for path, reason in skipped:
        print(f"skipped {path.parent}: {reason}", file=sys.stderr)
    for line in stack_warnings(runs):
        print(f"warning: {line}", file=sys.stderr)
    if not runs:
        raise SystemExit(f"no finished results.json under {', '.join(map(str, args.folders))}")
    summary = summarize(runs)
    figures = [(args.plot, lambda path: plot_tradeoff(summary, path))]
    seeds = lambda dataset, algo: len(runs[(dataset, algo)])  # noqa: E731
    figures.append((args.curves, lambda path: plot_learning_curves(learning_curves(runs), path, seeds=seeds)))
    per_constraint = constraint_markdown(runs)  # runs evaluated on several constraints: each one's cost
    write_outputs(markdown(summary) + ("\n\n" + per_constraint if per_constraint else ""), args.out, figures)


def write_outputs(text: str, out: Path | None, figures: list[tuple[Path | None, object]]) -> None:
    """Print ``text`` and write it to ``out``; draw each ``(path, draw)`` figure whose path was given. An
    unwritable place ends the report in one line."""
    print(text)
    try:
        if out:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text + "\n")
        for path, draw in figures:
            if path is not None:
                draw(path)
    except OSError as err:
        raise SystemExit(f"error: cannot write {err.filename}: {err.strerror}") from None


def keep_report(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--keep DEST``: the finished runs' small files copied into ``DEST``, and what was not."""
    from spoil_torchrl.reporting.keep import keep_finished

    others = ("out", "plot", "curves", "latest", "figure", "experiment", "mixed_files")
    given = [f"--{flag.replace('_', '-')}" for flag in others if getattr(args, flag) not in (None, False)]
    if given:
        parser.error(f"--keep copies runs and reports nothing: drop {', '.join(given)}")
    try:
        kept = keep_finished(args.folders, args.keep)
    except (FileNotFoundError, ValueError) as error:
        raise SystemExit(f"error: {error}") from None
    except OSError as err:
        raise SystemExit(f"error: cannot copy {err.filename}: {err.strerror}") from None
    for path, reason in kept.skipped:
        print(f"skipped {path.parent}: {reason}", file=sys.stderr)
    for relative in kept.copied:
        print(f"kept {relative}")
    print(f"{len(kept.copied)} runs kept in {args.keep}, {len(kept.already)} already there")
    if kept.refused:
        raise SystemExit(
            f"error: {args.keep} keeps other files for {len(kept.refused)} run(s) found now (started over, edited, "
            "or two runs at one place): " + ", ".join(kept.refused) + "; left as they were"
        )


def figure_report(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--figure``: a paper experiment's tables and statistics (printed, and into ``--out``) and figure."""
    from spoil_torchrl.eval.experiment_tables import (
        diagnostics_markdown,
        experiment_markdown,
        experiment_statistics,
        figure_panels,
    )
    from spoil_torchrl.eval.figures import plot_levels
    from spoil_torchrl.reporting.experiments import load_experiment

    if args.curves or args.latest:
        parser.error("--curves and --latest are not available with --figure")
    skipped: list[tuple[Path, str]] = []
    try:
        experiment = load_experiment(
            args.folders, name=args.experiment, skipped=skipped, mixed_files=args.mixed_files
        )
    except (FileNotFoundError, ValueError) as error:
        experiment = error
    for path, reason in skipped:
        print(f"skipped {path.parent}: {reason}", file=sys.stderr)
    if isinstance(experiment, Exception):
        raise SystemExit(f"error: {experiment}")
    for cell in experiment.resumed_elsewhere:  # exact continuations, of arithmetic done on different CPUs
        print(f"warning: {cell} was resumed on another machine (its results.json's ran_on)", file=sys.stderr)
    if args.plot and experiment.level is None:
        raise SystemExit(f"error: {experiment.name} has one configuration: a table, not a figure")
    try:
        statistics = experiment_statistics(experiment)
    except (ImportError, ValueError) as err:  # rliable is an extra; a NaN score cannot be bootstrapped
        statistics = f"(aggregate statistics left out: {err})"
    draw = lambda path: plot_levels(  # noqa: E731
        figure_panels(experiment), experiment.levels, path, level_name=experiment.level
    )
    parts = [experiment_markdown(experiment), statistics, diagnostics_markdown(experiment)]
    write_outputs("\n\n".join(part for part in parts if part), args.out, [(args.plot, draw)])


if __name__ == "__main__":
    main()
