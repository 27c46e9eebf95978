"""Aggregate statistics (rliable) against hand-computed values and an independent NumPy bootstrap."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from spoil_torchrl.eval.aggregate import interquartile_mean, interval_estimates, probability_of_improvement

pytest.importorskip("rliable")

# 3 runs x 2 tasks with distinct values, for the bootstrap tests
A = np.array([[0.1, 0.6], [0.4, 0.2], [0.9, 0.5]])


def test_iqm_by_hand():
    # 8 values: int(0.25 * 8) = 2 cut at each end -> mean(2, 3, 4, 5) = 3.5 (the outlier 100 is cut)
    assert interquartile_mean([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 100.0]) == pytest.approx(3.5)
    # (4 runs, 2 tasks), pooled: sorted -7, 0, 1, 2, 3, 4, 5, 10 -> mean(1, 2, 3, 4) = 2.5
    runs_by_tasks = np.array([[10.0, 0.0], [1.0, 2.0], [3.0, 4.0], [5.0, -7.0]])
    assert interquartile_mean(runs_by_tasks) == pytest.approx(2.5)
    # 0..8 and 99: int(2.5) = 2 cut at each end (0, 1 and 8, 99) -> (2 + ... + 7) / 6 = 27 / 6 = 4.5
    # (the plain mean would be (36 + 99) / 10 = 13.5)
    assert interquartile_mean(np.r_[np.arange(9.0), 99.0]) == pytest.approx(4.5)


def test_probability_of_improvement_by_hand():
    scores = {"X": np.array([1.0, 2.0, 3.0]), "Y": np.array([0.0, 2.0, 2.0]), "Z": np.array([0.0, 2.0])}
    est = probability_of_improvement(scores, [("X", "Y"), ("Y", "X"), ("X", "Z")], reps=20)
    # X vs Y, 9 pairs: 1 beats 0; 2 beats 0, ties 2 and 2; 3 beats 0, 2, 2 -> (5 wins + 2 ties / 2) / 9 = 2/3
    assert est["X", "Y"][0] == pytest.approx(2 / 3)
    # Y vs X: each 2 of Y beats X's 1 (2 wins), ties X's 2 (2 ties) -> (2 + 2 / 2) / 9 = 1/3
    assert est["Y", "X"][0] == pytest.approx(1 / 3)
    # X vs Z (3 x 2 runs): 1 > 0; 2 > 0, 2 = 2; 3 > 0, 3 > 2 -> (4 wins + 1 tie / 2) / 6 = 0.75
    assert est["X", "Z"][0] == pytest.approx(0.75)
    no_ties = {"X": np.array([1.0, 3.0, 5.0]), "Y": np.array([0.0, 2.0])}
    # 1 beats 0; 3 beats 0, 2; 5 beats 0, 2 -> 5 / 6
    assert probability_of_improvement(no_ties, [("X", "Y")], reps=20)["X", "Y"][0] == pytest.approx(5 / 6)


def test_probability_of_improvement_averages_tasks():
    x = np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 1.0]])
    y = np.array([[0.0, 1.0], [2.0, 1.0], [2.0, 1.0]])
    # task 0 as above: 2/3; task 1: X = 0, 0, 1 vs Y = 1, 1, 1 -> no wins, 3 ties -> 1.5 / 9 = 1/6
    # average: (2/3 + 1/6) / 2 = 5/12
    est = probability_of_improvement({"X": x, "Y": y}, [("X", "Y")], reps=50)
    point, lower, upper = est["X", "Y"]
    assert point == pytest.approx(5 / 12)
    assert 0.0 <= lower <= point <= upper <= 1.0
    assert probability_of_improvement({"X": x, "Y": y}, [("X", "Y")], reps=50) == est  # same seed


def test_interval_deterministic_and_global_rng_untouched():
    # rliable resamples with NumPy's legacy global RNG; the caller's stream of it must come out unchanged
    np.random.seed(123)  # noqa: NPY002
    expected_draw = np.random.random()  # noqa: NPY002
    np.random.seed(123)  # noqa: NPY002
    first = interval_estimates({"A": A}, reps=200, seed=7)
    assert np.random.random() == expected_draw  # noqa: NPY002
    assert interval_estimates({"A": A}, reps=200, seed=7) == first


def test_interval_contains_point_and_ignores_other_methods():
    b = np.array([[0.3, 0.3], [0.8, 0.1], [0.2, 0.7], [0.5, 0.5], [0.6, 0.4]])  # 5 runs: more than A's 3
    both = interval_estimates({"A": A, "B": b}, reps=200)
    # mean of A: task means (0.1 + 0.4 + 0.9) / 3 = 0.4667, (0.6 + 0.2 + 0.5) / 3 = 0.4333 -> 0.45
    assert both["A"]["mean"][0] == pytest.approx(0.45)
    # IQM of A: sorted 0.1, 0.2, 0.4, 0.5, 0.6, 0.9, int(1.5) = 1 cut at each end -> (0.2+0.4+0.5+0.6)/4 = 0.425
    assert both["A"]["iqm"][0] == pytest.approx(0.425)
    for stats in both.values():
        for point, lower, upper in stats.values():
            assert lower <= point <= upper and lower < upper
    assert interval_estimates({"A": A}, reps=200)["A"] == both["A"]  # seeded per method, not per call


def test_constant_scores_collapse():
    est = interval_estimates({"C": np.full((4, 3), 0.25)}, statistics=("iqm", "mean", "median"), reps=50)
    assert est["C"] == {stat: (0.25, 0.25, 0.25) for stat in ("iqm", "mean", "median")}
    poi = probability_of_improvement({"X": np.ones((3, 2)), "Y": np.zeros((2, 2))}, [("X", "Y")], reps=20)
    assert poi["X", "Y"] == (1.0, 1.0, 1.0)


def test_seed_changes_interval():
    first = interval_estimates({"A": A}, statistics=("mean",), reps=200, seed=0)["A"]["mean"]
    other = interval_estimates({"A": A}, statistics=("mean",), reps=200, seed=1)["A"]["mean"]
    assert first[0] == other[0]  # the point estimate does not depend on the seed
    assert first[1:] != other[1:]


def test_wider_confidence_wider_interval():
    # the same seed gives the same resamples, so the 99 % percentiles enclose the 50 % ones
    narrow = interval_estimates({"A": A}, reps=300, confidence=0.5)["A"]
    wide = interval_estimates({"A": A}, reps=300, confidence=0.99)["A"]
    for stat in ("iqm", "mean"):
        assert wide[stat][1] <= narrow[stat][1] and narrow[stat][2] <= wide[stat][2]
        assert wide[stat][2] - wide[stat][1] > narrow[stat][2] - narrow[stat][1]


def test_mean_interval_matches_numpy_bootstrap():
    runs, tasks, reps = 8, 3, 4000
    scores = np.random.default_rng(1).normal(size=(runs, tasks)) + np.arange(tasks)
    point, lower, upper = interval_estimates({"A": scores}, statistics=("mean",), reps=reps)["A"]["mean"]
    # independent stratified bootstrap: for every task, resample its runs with replacement; mean of task means
    big = 40_000
    idx = np.random.default_rng(2).integers(0, runs, size=(big, runs, tasks))
    replicates = np.take_along_axis(np.broadcast_to(scores, idx.shape), idx, axis=1).mean(axis=(1, 2))
    ref_lower, ref_upper = np.percentile(replicates, [2.5, 97.5])
    assert point == pytest.approx(scores.mean())
    # Tolerance: the replicates are ~normal with sd sigma_b = sqrt(sum_t var_t / runs) / tasks; a 2.5 % quantile
    # from R draws has standard error sqrt(.025 * .975 / R) / phi(1.96) * sigma_b = 2.67 sigma_b / sqrt(R):
    # 0.042 sigma_b for R = 4000 (0.013 for 40 000), so 0.044 sigma_b for the difference; 0.2 sigma_b is ~4.5 SE,
    # yet smaller than the 0.31 sigma_b shift of a 90 % interval's bound (1.96 vs 1.645 sigma_b).
    sigma_b = np.sqrt(scores.var(axis=0).sum() / runs) / tasks
    assert lower == pytest.approx(ref_lower, abs=0.2 * sigma_b)
    assert upper == pytest.approx(ref_upper, abs=0.2 * sigma_b)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: interquartile_mean(np.zeros((0, 2))), "empty"),
        (lambda: interval_estimates({"A": A, "bad": [[0.1, np.nan]]}, reps=5), "'bad' contain NaN"),
        (lambda: interval_estimates({"A": A, "B": np.ones((2, 3))}), "'A' has 2, 'B' has 3"),
        (lambda: interval_estimates({"A": A}, statistics=("iqm", "max")), r"unknown \['max'\]"),
        (lambda: interval_estimates({"A": A}, confidence=95), r"confidence must be in \(0, 1\)"),
        (lambda: interval_estimates({}), "no methods"),
        (lambda: interval_estimates({"A": np.ones((2, 2, 2))}), r"shape \(runs, tasks\)"),
        (lambda: probability_of_improvement({"A": A}, [("A", "B")]), r"without scores: \['B'\]"),
        (lambda: probability_of_improvement({"A": A, "B": [np.nan]}, [("A", "B")]), "'B' contain NaN"),
        (lambda: probability_of_improvement({"A": A, "B": np.ones(3)}, [("A", "B")]), "'B' has 1"),
    ],
)
def test_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_missing_rliable(monkeypatch):
    monkeypatch.setitem(sys.modules, "rliable", None)  # makes `import rliable` raise ImportError
    with pytest.raises(ImportError, match=r'pip install -e "\.\[report\]"'):
        interquartile_mean([1.0, 2.0])
