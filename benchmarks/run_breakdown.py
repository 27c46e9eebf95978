"""Where a run's wall time went: data, pre-training, main stage and evaluation, from its ``results.json``.

    make bench                                            # the newest `make run` (runs/spoildice_dsrl/...)
    python benchmarks/run_breakdown.py runs/a/results.json runs/b/results.json

Reads what the main recipe records: ``data_seconds`` (loading and preparing the data), ``pretrain_seconds``
(from the start to the end of pre-training, data included), ``train_seconds`` (the main stage, evaluations
included) with each evaluation's ``eval_seconds``, and ``total_seconds``. Runs made before these fields existed
show what they have.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DEFAULT_RUNS = Path("runs/spoildice_dsrl/point-circle1-mixed/spoildice")


def breakdown(results: dict) -> dict[str, float | None]:
    """Seconds per stage (``None`` where the run did not record it)."""
    data = results.get("data_seconds")
    pretrain = results.get("pretrain_seconds")
    evaluations = [e.get("eval_seconds") for e in results.get("evaluations", [])]
    evaluation = sum(evaluations) if evaluations and None not in evaluations else None
    train = results.get("train_seconds")
    return {
        "data": data,
        "pre-training": None if pretrain is None or data is None else pretrain - data,
        "main stage": None if train is None or evaluation is None else train - evaluation,
        "evaluation": evaluation,
        "total": results.get("total_seconds"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "results", nargs="*", type=Path, help="results.json files (default: the newest make run)"
    )
    args = parser.parse_args()
    paths = args.results or sorted(DEFAULT_RUNS.glob("*/results.json"), key=lambda p: p.stat().st_mtime)[-1:]
    if not paths:
        print(f"run breakdown: no results.json under {DEFAULT_RUNS} (run `make run` first)")
        return
    for path in paths:
        results = json.loads(path.read_text())
        parts = breakdown(results)
        steps = len(results.get("evaluations", [])) and results["evaluations"][-1]["step"]
        cells = ", ".join(f"{k} {'-' if v is None else f'{v:.0f} s'}" for k, v in parts.items())
        print(f"{path} ({results.get('algo')}, {steps} steps, {results.get('status')}): {cells}")


if __name__ == "__main__":
    main()
