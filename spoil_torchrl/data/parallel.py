"""Several policy rollouts at once: the caller's process and spawned worker processes share them.

The simulator steps one environment at a time on one core, so a rollout uses one core whatever the caller's
threads. :class:`RolloutPool` hands independent rollouts -- the segments of a generated dataset
(:func:`~spoil_torchrl.data.collect.collect`), the seeds' evaluations of a ``seeds=[...]`` run
(:meth:`~spoil_torchrl.eval.Evaluator.rollout_job`, with a copy of each policy) -- to a worker process per spare
core, while the caller takes its own share. A rollout draws from its own random stream and computes its
policy's products in IEEE float32 on one thread (:func:`~spoil_torchrl.data.collect.rollout`), so its arrays
are the same in a worker as in the caller, bit for bit (``tests/data/test_parallel.py``).

Workers are spawned (not forked: the caller's torch threads and open files stay its own), ignore Ctrl-C (the
caller stops them) and exit when the caller dies. A worker that dies is reported once; its rollouts, and all
later ones, then run in the caller's process. Jobs must be picklable (a :func:`functools.partial` of a
module-level function, say); workers import the package from disk when they start and, as with any spawned
process, the caller's script: a script that uses the pool needs an ``if __name__ == "__main__":`` guard (one
without is stopped in the worker, and the pool runs everything in the caller, with a warning).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

#: A rollout job: a picklable call without arguments that returns the rollout's arrays.
Job = Callable[[], dict]


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. a cluster job's share of a node)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


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
        # a worker that is starting runs the caller's script again (multiprocessing's own check of this case)
        if getattr(multiprocessing.current_process(), "_inheriting", False):
            raise RuntimeError(
                "a script that starts rollout workers was run again by one of them: guard its entry point "
                'with `if __name__ == "__main__":`'
            )
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

    def map(self, jobs: Iterable[Job], run_here: Callable[[Job], dict] | None = None) -> Iterator[dict]:
        """The result of every job, in order. All jobs are offered to the workers, which take them from the
        front; meanwhile the caller takes them from the back, as long as no worker has taken the next one, and
        runs them with ``run_here`` (default: ``job()``; e.g. with the caller's progress bar). It yields once it
        has none left to take, so that it consumes the workers' results as they finish. A job's own error is
        raised as if it had run here."""
        jobs, run_here = list(jobs), run_here or (lambda job: job())
        futures = self._submit(jobs)
        local = {}
        for i in reversed(range(len(jobs))):
            if futures and not futures[i].cancel():  # a worker has it already
                break
            local[i] = run_here(jobs[i])
        for i, job in enumerate(jobs):
            if i in local:
                yield local.pop(i)
                continue
            try:
                yield futures[i].result()
            except BrokenProcessPool as err:
                self._give_up(err)
                yield run_here(job)

    def _submit(self, jobs: list[Job]) -> list[Future]:
        if self._executor is None:
            return []
        try:
            return [self._executor.submit(job) for job in jobs]
        except (BrokenProcessPool, RuntimeError) as err:
            self._give_up(err)
            return []

    def _give_up(self, err: BaseException) -> None:
        if self._executor is None:  # said already
            return
        warnings.warn(
            f"rollout worker processes unavailable ({type(err).__name__}: {err}); running them in this "
            'process from now on (a script that starts them needs an `if __name__ == "__main__":` guard)',
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
