"""Why a DICE run behaves as it does, in sentences: :func:`explain` turns the numbers of
:func:`~spoil_torchrl.eval.dice_diagnostics.dice_diagnostics` into sentences, and :func:`explain_run` does so
for a run directory. On the command line:

    python -m spoil_torchrl.eval.dice_explain RUN_DIR [RUN_DIR ...]

explains each run directory named, and each run under a folder of runs (``docs/results/mixed``). A run that
cannot be explained (no ``results.json``, an unreadable one, a run that failed or stopped before its first
evaluation, a method that is not a DICE method) gets one ``error: <run>: <why>`` line on stderr and the others
go on; in a folder of runs, the finished runs of methods without DICE weights (BC, FBC, ...) get a
``skipped <run>: ...`` line instead, as they are expected there. Exit status: 0 when every run was explained
(or skipped so), 1 when one could not be, or none was found to explain, 2 without an argument (the usage).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from spoil_torchrl.eval.dice_diagnostics import ALL_CUTS, FLAT_SPREAD


def _pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def explain(diag: Mapping, performant_support: Mapping | None = None) -> str:
    """Sentences a researcher can read, from :func:`~spoil_torchrl.eval.dice_diagnostics.dice_diagnostics` (and
    :func:`~spoil_torchrl.eval.dice_diagnostics.support_accuracy` of D_P).

    Examples:
        >>> print(explain({"role": "unlabeled", "spread": {"nu": 0.04, "bellman": 0.06, "advantage": 1.0},
        ...     "variance_share": {"bellman": 0.02, "reward": 0.98},
        ...     "weight_share": {"cost>0": {"weight": 0.3, "transitions": 0.2}}, "effective_sample_size": 0.5}))
        ... # doctest: +NORMALIZE_WHITESPACE
        nu's Bellman term gamma*nu(s') - nu(s) explains 2 % of the variance of the advantage (reward 98 %);
        its spread on unlabeled is 0.06 against 1 for the whole advantage.
        nu is nearly flat (its term moves the weights by less than about 10 %): the weights are those of
        weighted BC on the reward term, with no look-ahead.
        30 % of the weight mass sits on transitions with true cost > 0 (they are 20 % of unlabeled):
        the weights favour costly transitions.
        The effective sample size of the weights is 50 % of the transitions.
    """
    share, spread, weight = diag["variance_share"], diag["spread"], diag["weight_share"]
    others = ", ".join(
        f"{k.replace('_', ' ')} {_pct(v)}" for k, v in share.items() if k not in ("bellman", "rest")
    )
    lines = [
        f"nu's Bellman term gamma*nu(s') - nu(s) explains {_pct(share['bellman'])} of the variance of the "
        f"advantage ({others}); its spread on {diag['role']} is {spread['bellman']:.2g} against "
        f"{spread['advantage']:.2g} for the whole advantage."
    ]
    inside = diag.get("variance_share_in_support")
    if inside:
        lines.append(
            f"Inside the estimated support (where lambda * 1_S is constant) nu's term explains "
            f"{_pct(inside['bellman'])} of it and log r_P {_pct(inside['log_ratio_performant'])}."
        )
    if spread["bellman"] < FLAT_SPREAD:
        lines.append(
            "nu is nearly flat (its term moves the weights by less than about 10 %): the weights are those of "
            "weighted BC on the reward term, with no look-ahead."
        )
    costly = weight["cost>0"]
    if abs(costly["weight"] - costly["transitions"]) < 0.01:
        verdict = "the weights neither favour nor avoid costly transitions"
    elif costly["weight"] > costly["transitions"]:
        verdict = "the weights favour costly transitions"
    else:
        verdict = "the weights move mass away from costly transitions"
    lines.append(
        f"{_pct(costly['weight'])} of the weight mass sits on transitions with true cost > 0 (they are "
        f"{_pct(costly['transitions'])} of {diag['role']}): {verdict}."
    )
    sources = sorted(((k, v) for k, v in weight.items() if k != "cost>0"), key=lambda kv: -kv[1]["weight"])
    if sources:
        top = ", ".join(
            f"{k} {_pct(v['weight'])} ({_pct(v['transitions'])} of the data)" for k, v in sources[:4]
        )
        lines.append(f"Weight by source: {top}.")
    if "support" in diag:
        s = diag["support"]
        lines.append(
            f"The support estimate keeps {_pct(s['kept'])} of {diag['role']}; {_pct(s['costly_among_kept'])} of the "
            f"kept transitions have cost > 0, and it lets in {_pct(s['costly_kept'])} of the costly ones."
        )
        if "by_constraint" in s:
            lines.append(_by_constraint_sentence(s["by_constraint"]))
    if performant_support is not None:
        lines.append(f"It keeps {_pct(performant_support['kept'])} of D_P's transitions.")
    lines.append(
        f"The effective sample size of the weights is {_pct(diag['effective_sample_size'])} of the transitions."
    )
    return "\n".join(lines)


def _by_constraint_sentence(by_constraint: Mapping) -> str:
    """One sentence on each cut (or the one support of a merged safe set) against each constraint's cost.

    Examples:
        >>> print(_by_constraint_sentence({"costly": {"a": 0.2, "b": 0.3},
        ...     "costly_kept": {"a": {"a": 0.1, "b": 0.6}, "b": {"a": 0.5, "b": 0.5}, "all": {"a": 0.05, "b": 0.3}}}))
        ... # doctest: +NORMALIZE_WHITESPACE
        Of the transitions costly on a / b, the a cut lets in 10 % / 60 %, the b cut 50 % / 50 %,
        their intersection 5 % / 30 % (a cut that lets in as many of its own constraint's costly transitions as of
        the others' does not tell its constraint apart).
    """
    names, costly = list(by_constraint["costly"]), by_constraint["costly"]
    rows = by_constraint["costly_kept"]

    def shares(cut: str) -> str:  # "-" for a constraint with no costly transition to keep
        return " / ".join(_pct(rows[cut][j]) if costly[j] > 0 else "-" for j in names)

    cuts = [c for c in rows if c != ALL_CUTS]
    if not cuts:  # one support for all constraints (a merged safe set)
        return f"Of the transitions costly on {' / '.join(names)}, the support lets in {shares(ALL_CUTS)}."
    parts = [f"the {cuts[0]} cut lets in {shares(cuts[0])}", *(f"the {c} cut {shares(c)}" for c in cuts[1:])]
    return (
        f"Of the transitions costly on {' / '.join(names)}, {', '.join(parts)}, their intersection "
        f"{shares(ALL_CUTS)} (a cut that lets in as many of its own constraint's costly transitions as of the "
        "others' does not tell its constraint apart)."
    )


class NotADiceRun(ValueError):
    """A finished run without DICE diagnostics: its method does not weight by DICE (BC, FBC, ...)."""


def _read_results(run_dir: Path) -> dict:
    path = run_dir / "results.json"
    try:
        results = json.loads(path.read_text())
    except OSError as err:
        raise ValueError(f"{run_dir}: results.json cannot be read ({err.strerror})") from None
    except ValueError as err:
        raise ValueError(f"{run_dir}: results.json is unreadable ({err})") from None
    if not isinstance(results, dict):
        raise ValueError(
            f"{run_dir}: results.json holds a JSON {type(results).__name__}, not a run's results"
        )
    return results


def explain_run(run_dir: str | Path) -> str:
    """:func:`explain` for the final diagnostics stored in a run directory's ``results.json``.

    Raises:
        FileNotFoundError: ``run_dir`` has no ``results.json``.
        NotADiceRun: the run finished, and its method is not a DICE method.
        ValueError: ``results.json`` is unreadable or not a run's results, the run stopped before its first
            evaluation (its status and error are named), or its ``dice_diagnostics`` are incomplete.
    """
    run_dir = Path(run_dir)
    if not run_dir.exists():
        raise FileNotFoundError(f"{run_dir}: no such folder")
    if not (run_dir / "results.json").is_file():
        raise FileNotFoundError(
            f"{run_dir}: no results.json (not a run directory of recipes/spoildice_dsrl.py)"
        )
    results = _read_results(run_dir)
    diag = results.get("dice_diagnostics")
    if diag is None:
        status, algo = results.get("status"), results.get("algo")
        if status == "finished":
            raise NotADiceRun(f"{run_dir}: no dice_diagnostics ({algo} is not a DICE method)")
        state = "no status" if status is None else f"status {status}"
        if results.get("error"):
            state += f": {results['error']}"
        raise ValueError(
            f"{run_dir}: no dice_diagnostics ({algo} is not a DICE method, or the run did not reach its "
            f"first evaluation; {state})"
        )
    try:
        return explain(diag, results.get("performant_support"))
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(
            f"{run_dir}: its dice_diagnostics are incomplete or malformed ({type(err).__name__}: {err})"
        ) from None


def _run_dirs(arg: str) -> tuple[list[Path], bool]:
    """The run directories an argument names (itself, or every run under a folder of runs), and whether it
    is a folder of runs."""
    path = Path(arg)
    if path.is_file() and path.name == "results.json":
        return [path.parent], False
    if not path.is_dir() or (path / "results.json").exists():
        return [path], False
    return sorted({found.parent for found in path.rglob("results.json")}), True


def main(argv: Sequence[str] | None = None) -> int:
    """The command line (see the module's docstring); returns the exit status."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m spoil_torchrl.eval.dice_explain",
        description="Explain the DICE weights of finished runs of recipes/spoildice_dsrl.py.",
    )
    parser.add_argument(
        "runs", nargs="+", metavar="RUN_DIR", help="a run directory, or a folder of runs (each is explained)"
    )
    args = parser.parse_args(argv)
    explained, failed = 0, 0
    for arg in args.runs:
        run_dirs, folder = _run_dirs(arg)
        if not run_dirs:
            print(f"error: {arg}: no results.json in it or under it (not a run directory)", file=sys.stderr)
            failed += 1
        for run_dir in run_dirs:
            try:
                text = explain_run(run_dir)
            except NotADiceRun as err:
                if folder:  # a folder's BC, FBC, ... runs: nothing to explain
                    print(f"skipped {err}", file=sys.stderr)
                    continue
                print(f"error: {err}", file=sys.stderr)
                failed += 1
            except (OSError, ValueError) as err:  # FileNotFoundError included
                print(f"error: {err}", file=sys.stderr)
                failed += 1
            else:
                print(f"{run_dir}:\n{text}\n")
                explained += 1
    if not explained and not failed:
        print("error: no DICE run to explain among " + ", ".join(args.runs), file=sys.stderr)
    return 1 if failed or not explained else 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
