"""Aggregate statistics of few-seed results, the estimators of Agarwal et al. (2021), through ``rliable``.

Scores are arrays of shape ``(runs, tasks)`` -- e.g. the normalised feasible return of each seed on each task --
or 1-D (one task). Methods may have different numbers of runs but must share their tasks.

* :func:`interquartile_mean` -- the IQM: the mean of the middle 50 % of all ``runs * tasks`` values
  (``scipy.stats.trim_mean`` cutting ``int(0.25 * n)`` values at each end), robust to outlier runs and more
  efficient than the median;
* :func:`interval_estimates` -- point estimates of aggregate statistics (IQM, mean, median, optimality gap)
  with percentile confidence intervals from a *stratified bootstrap*: each replicate resamples the runs with
  replacement within every task, so that every task keeps its weight;
* :func:`probability_of_improvement` -- P(X > Y): the probability that a run of X beats a run of Y on a task
  (ties count 1/2; the Mann-Whitney U statistic over ``m * n``), averaged over tasks, with its stratified
  bootstrap interval (X's runs and Y's runs resampled independently within each task).

Reference: R. Agarwal, M. Schwarzer, P. S. Castro, A. Courville, M. G. Bellemare, "Deep Reinforcement Learning
at the Edge of the Statistical Precipice", NeurIPS 2021, https://arxiv.org/abs/2108.13264.

``rliable`` is an optional dependency (``pip install -e ".[report]"``), imported on first use. Its bootstrap
draws from NumPy's *global* RNG (it ignores its ``random_state`` argument), so the functions here seed that RNG
for each method / pair and restore its previous state afterwards: results depend only on ``seed`` and that
method's (pair's) data, not on the other entries or the order. This is not thread-safe.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager

import numpy as np

_INSTALL_HINT = 'pip install -e ".[report]" (or pip install rliable "pandas<3")'


def _rliable():
    try:
        from rliable import library, metrics
    except ImportError as exc:
        raise ImportError(f"spoil_torchrl.eval.aggregate needs rliable: {_INSTALL_HINT}") from exc
    except TypeError as exc:  # arch < 8 (which rliable 1.2 requires) fails to import with pandas >= 3
        raise ImportError(f"rliable failed to import ({exc}); with pandas >= 3, {_INSTALL_HINT}") from exc
    return library, metrics


def _scores(name: str, scores) -> np.ndarray:
    """``scores`` as a float64 ``(runs, tasks)`` array, refused if empty or NaN."""
    array = np.asarray(scores, dtype=np.float64)
    if array.ndim == 1:
        array = array[:, None]
    if array.ndim != 2:
        raise ValueError(f"scores of {name!r}: expected shape (runs, tasks) or (runs,), got {array.shape}")
    if array.size == 0:
        raise ValueError(f"scores of {name!r} are empty (shape {array.shape})")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"scores of {name!r} contain NaN or inf")
    return array


def _same_tasks(arrays: Mapping[str, np.ndarray]) -> None:
    tasks = {name: array.shape[1] for name, array in arrays.items()}
    if len(set(tasks.values())) > 1:
        counts = ", ".join(f"{name!r} has {n}" for name, n in tasks.items())
        raise ValueError(f"all methods must have the same number of tasks: {counts}")


def _check_bootstrap(reps: int, confidence: float) -> None:
    if reps < 1:
        raise ValueError(f"reps must be >= 1, got {reps}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")


@contextmanager
def _global_seed(seed: int) -> Iterator[None]:
    """Seed NumPy's global RNG (which rliable's bootstrap draws from) and restore its state afterwards."""
    state = np.random.get_state()  # noqa: NPY002 -- rliable draws from the legacy global RNG
    np.random.seed(seed)  # noqa: NPY002
    try:
        yield
    finally:
        np.random.set_state(state)  # noqa: NPY002


def interquartile_mean(scores) -> float:
    """The interquartile mean of all values of ``scores`` (``(runs, tasks)`` or 1-D).

    >>> interquartile_mean([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 100.0])  # mean of 2, 3, 4, 5
    3.5
    >>> interquartile_mean([[10.0, 0.0], [1.0, 2.0], [3.0, 4.0], [5.0, -7.0]])  # mean of 1, 2, 3, 4
    2.5
    """
    _, metrics = _rliable()
    return float(metrics.aggregate_iqm(_scores("scores", scores)))


def _statistics(metrics, names: Sequence[str]) -> dict[str, Callable[[np.ndarray], float]]:
    if isinstance(names, str):
        names = (names,)
    known = {
        "iqm": metrics.aggregate_iqm,
        "mean": metrics.aggregate_mean,
        "median": metrics.aggregate_median,
        "optimality_gap": metrics.aggregate_optimality_gap,
    }
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise ValueError(f"statistics: unknown {unknown} (or none given); known: {sorted(known)}")
    return {name: known[name] for name in names}


def interval_estimates(
    scores: Mapping[str, np.ndarray],
    *,
    statistics: Sequence[str] = ("iqm", "mean"),
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> dict[str, dict[str, tuple[float, float, float]]]:
    """``{method: {statistic: (point, lower, upper)}}``: stratified-bootstrap percentile intervals.

    ``statistics`` are among ``"iqm"``, ``"mean"`` (of the per-task means), ``"median"`` (of the per-task
    means) and ``"optimality_gap"`` (below 1); all share the same ``reps`` resamples of each method.

    >>> scores = {"A": np.array([[0.2, 0.4], [0.3, 0.5], [0.4, 0.9]]), "B": np.full((2, 2), 0.5)}
    >>> est = interval_estimates(scores, reps=200)
    >>> point, lower, upper = est["A"]["mean"]
    >>> round(point, 6), lower <= point <= upper
    (0.45, True)
    >>> est["B"]["iqm"]  # constant scores: the interval collapses to the point
    (0.5, 0.5, 0.5)
    """
    library, metrics = _rliable()
    funcs = _statistics(metrics, statistics)
    _check_bootstrap(reps, confidence)
    if not scores:
        raise ValueError("scores: no methods given")
    arrays = {name: _scores(name, value) for name, value in scores.items()}
    _same_tasks(arrays)

    def aggregate(array: np.ndarray) -> np.ndarray:
        return np.array([func(array) for func in funcs.values()])

    out: dict[str, dict[str, tuple[float, float, float]]] = {}
    for name, array in arrays.items():
        with _global_seed(seed):
            points, intervals = library.get_interval_estimates(
                {name: array}, aggregate, reps=reps, confidence_interval_size=confidence
            )
        point, (lower, upper) = points[name], intervals[name]  # intervals: row 0 lower, row 1 upper
        out[name] = {
            stat: (float(point[i]), float(lower[i]), float(upper[i])) for i, stat in enumerate(funcs)
        }
    return out


def probability_of_improvement(
    scores: Mapping[str, np.ndarray],
    pairs: Sequence[tuple[str, str]],
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> dict[tuple[str, str], tuple[float, float, float]]:
    """``{(X, Y): (point, lower, upper)}``: P(X > Y) averaged over tasks, with its bootstrap interval.

    Per task, the fraction of (run of X, run of Y) pairs where X's score is higher, ties counting 1/2.

    >>> scores = {"X": np.array([1.0, 2.0, 3.0]), "Y": np.array([0.0, 2.0, 2.0])}
    >>> est = probability_of_improvement(scores, [("X", "Y"), ("Y", "X")], reps=100)
    >>> round(est["X", "Y"][0], 6), round(est["Y", "X"][0], 6)  # (5 wins + 2 ties / 2) / 9 = 2/3
    (0.666667, 0.333333)
    """
    library, metrics = _rliable()
    _check_bootstrap(reps, confidence)
    if not pairs:
        raise ValueError("pairs: no (X, Y) pairs given")
    missing = sorted({name for pair in pairs for name in pair} - set(scores))
    if missing:
        raise ValueError(f"pairs name methods without scores: {missing}; have {sorted(scores)}")
    arrays = {name: _scores(name, scores[name]) for pair in pairs for name in pair}
    _same_tasks(arrays)

    def improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.array([metrics.probability_of_improvement(x, y)])

    out: dict[tuple[str, str], tuple[float, float, float]] = {}
    for x_name, y_name in pairs:
        key = f"{x_name} > {y_name}"
        with _global_seed(seed):
            # a list value makes rliable resample X's runs and Y's runs independently within each task
            points, intervals = library.get_interval_estimates(
                {key: [arrays[x_name], arrays[y_name]]},
                improvement,
                reps=reps,
                confidence_interval_size=confidence,
            )
        out[x_name, y_name] = (
            float(points[key][0]),
            float(intervals[key][0, 0]),
            float(intervals[key][1, 0]),
        )
    return out
