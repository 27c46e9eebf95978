"""Several evaluations' rollouts at once: the caller's process and spawned worker processes share them.

The simulator steps one environment at a time on one core, so an evaluation uses one core whatever the
training's threads. When a ``seeds=[...]`` run evaluates its seeds' policies, :class:`RolloutPool` gives each
spare core a share of the rollouts (:meth:`~spoil_torchrl.eval.Evaluator.rollout_job`, a picklable call with
a copy of the policy) and runs the rest in the caller's process. A rollout draws from its own random stream
and computes in IEEE float32 (:func:`spoil_torchrl.data.collect.rollout`), so its arrays are the same in a
worker as in the caller, bit for bit (``tests/eval/test_parallel.py``).

Workers are spawned (not forked: the caller's torch threads and open files stay its own), ignore Ctrl-C (the
caller stops them) and exit when the caller dies. A worker that dies is reported once; its rollouts, and all
later ones, then run in the caller's process.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

#: A rollout job: a picklable call without arguments that returns the rollout's arrays.
Job = Callable[[], dict]


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. a cluster job's share of a node)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def local_share(jobs: int, workers: int) -> int:
    """How many of ``jobs`` the caller runs itself beside ``workers`` workers: an even share, at least one
    (the caller would otherwise only wait), and it takes the smaller share because it also writes the results.

    Examples:
        >>> [local_share(5, 1), local_share(5, 4), local_share(2, 1), local_share(1, 1), local_share(3, 0)]
        [2, 1, 1, 1, 3]
    """
    if workers < 1:
        return jobs
    return min(jobs, max(1, jobs // (workers + 1)))


def _exit_with(parent: int) -> None:  # a worker outlives no killed caller
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(0)


def _start_worker(parent: int) -> None:
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller handles Ctrl-C and shuts the pool down
    torch.set_num_threads(1)  # one simulator, one core
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()


def _warm_up() -> None:  # the imports, before the first evaluation needs them
    import spoil_torchrl.data.collect  # noqa: F401
    import spoil_torchrl.envs  # noqa: F401


class RolloutPool:
    """Runs rollout jobs in this process and in ``workers`` spawned processes; results in the jobs' order.

    Args:
        workers: worker processes (``None``: one per core this process may use, beyond its own; ``0``:
            everything runs here).

    Examples:
        >>> from spoil_torchrl.eval import Evaluator
        >>> from spoil_torchrl.modules import make_actor
        >>> evaluator = Evaluator("SafetyPointCircle1-v0", cost_threshold=10.0, return_range=(0.0, 50.0),
        ...                       episodes=1, num_envs=1)
        >>> policies = [make_actor(28, 2, hidden_cells=(8,)) for _ in range(2)]
        >>> with RolloutPool(workers=0) as pool:
        ...     rollouts = list(pool.map(evaluator.rollout_job(p) for p in policies))
        >>> [len(arrays["rewards"]) for arrays in rollouts]
        [500, 500]
    """

    def __init__(self, workers: int | None = None) -> None:
        self.workers = max(0, available_cores() - 1 if workers is None else int(workers))
        self._executor: ProcessPoolExecutor | None = None
        if self.workers:
            try:
                self._executor = ProcessPoolExecutor(
                    self.workers,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_start_worker,
                    initargs=(os.getpid(),),
                )
                for _ in range(self.workers):
                    self._executor.submit(_warm_up)
            except (OSError, RuntimeError) as err:
                self._give_up(err)

    def map(self, jobs: Iterable[Job]) -> Iterator[dict]:
        """The result of every job, in order. The first jobs go to the workers, the caller runs the
        last :func:`local_share` itself before it yields, so that it can consume the workers' results while
        they finish. A job's own error is raised as if it had run here."""
        jobs = list(jobs)
        remote = len(jobs) - local_share(len(jobs), self.workers if self._executor else 0)
        futures = []
        for job in jobs[:remote]:
            try:
                futures.append(self._executor.submit(job))
            except (BrokenProcessPool, RuntimeError) as err:
                self._give_up(err)
                break
        local = [job() for job in jobs[len(futures) :]]
        for job, future in zip(jobs, futures, strict=False):
            try:
                yield future.result()
            except BrokenProcessPool as err:
                self._give_up(err)
                yield job()
        yield from local

    def _give_up(self, err: BaseException) -> None:
        if self._executor is None:  # said already
            return
        warnings.warn(
            f"evaluation worker processes unavailable ({type(err).__name__}: {err}); evaluating in this "
            "process from now on",
            RuntimeWarning,
            stacklevel=3,
        )
        self.close()

    def close(self) -> None:
        """Stop the workers (after their current job); later jobs run in this process."""
        executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> RolloutPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
