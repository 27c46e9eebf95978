"""Several policy rollouts at once: the caller's process and spawned worker processes share them.

The simulator steps one environment at a time on one core, so a rollout uses one core whatever the caller's
threads. :class:`RolloutPool` hands independent rollouts -- the segments of a generated dataset
(:func:`~spoil_torchrl.data.collect.collect`), the seeds' evaluations of a ``seeds=[...]`` run
(:meth:`~spoil_torchrl.eval.Evaluator.rollout_job`, with a copy of each policy) -- to a worker process per spare
core, while the caller takes its own share. A rollout draws from its own random stream and computes its
policy's products in IEEE float32 on one thread (:func:`~spoil_torchrl.envs.rollout.rollout`), so its arrays
are the same in a worker as in the caller, bit for bit (``tests/data/test_parallel.py``).

Workers are spawned (not forked: the caller's torch threads and open files stay its own), ignore Ctrl-C (the
pool ends them: at once on an error or Ctrl-C in the caller, else after their current job) and exit when the
caller dies. A worker that dies is reported once; its rollouts, and all later ones, then run in the caller's
process. Jobs must be picklable (a :func:`functools.partial` of a module-level function, say); workers import
the package from disk when they start and, as with any spawned process, the caller's script: a script that
uses the pool needs an ``if __name__ == "__main__":`` guard (one without is stopped in the worker, and the
pool runs everything in the caller, with a warning).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor
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


def _warm_up(modules: tuple[str, ...]) -> None:  # the jobs' imports, before the first job needs them
    import importlib

    for module in modules:
        importlib.import_module(module)


class RolloutPool:
    """Runs rollout jobs in this process and in ``workers`` spawned processes; results in the jobs' order.

    Args:
        workers: worker processes (``None``: one per core this process may use, beyond its own; ``0``:
            everything runs here).
        warm_up: modules each worker imports as soon as it starts (the jobs' own, e.g.
            ``("spoil_torchrl.data.collect",)``), so that the first job does not wait for them.

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

    def __init__(self, workers: int | None = None, *, warm_up: tuple[str, ...] = ()) -> None:
        # a worker that is starting runs the caller's script again (multiprocessing's own check of this case)
        if getattr(multiprocessing.current_process(), "_inheriting", False):
            raise RuntimeError(
                "a script that starts rollout workers was run again by one of them: guard its entry point "
                'with `if __name__ == "__main__":`'
            )
        self.workers = max(0, available_cores() - 1 if workers is None else int(workers))
        self._executor: ProcessPoolExecutor | None = None
        self._gave_up = False
        self._lock = threading.Lock()
        if self.workers:
            try:
                self._executor = ProcessPoolExecutor(
                    self.workers,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_start_worker,
                    initargs=(os.getpid(),),
                )
                for _ in range(self.workers):
                    self._executor.submit(_warm_up, tuple(warm_up))
            except Exception as err:  # e.g. in a daemonic process, which may not have children
                self._give_up(err)

    def map(self, jobs: Iterable[Job], run_here: Callable[[Job], dict] | None = None) -> Iterator[dict]:
        """The result of every job, in order.

        The jobs are taken (all of them at the first ``next``) from both ends: each worker takes the next one
        from the front whenever it is free; the caller yields the next result in order as soon as there is one
        (so that its consumer, e.g. writing an evaluation's files, works while the workers roll out), and
        otherwise takes a job from the back and runs it with ``run_here`` (default: ``job()``; e.g. with the
        caller's progress bar). A job's error is raised here. Jobs not yet started when the generator is closed
        are cancelled."""
        jobs, run_here = list(jobs), run_here or _call
        claims = _Claims(len(jobs))
        futures: dict[int, Future | None] = {}  # a worker's job; None: it could not be handed over

        def offer(_: Future | None = None) -> None:  # a free worker takes the next job from the front
            with claims.lock:  # a claimed job has its entry in ``futures`` at once
                i = claims.take_front()
                if i is None:
                    return
                futures[i] = future = self._submit(jobs[i])
            if future is not None:
                future.add_done_callback(offer)

        for _ in range(min(self.workers, len(jobs)) if self._executor is not None else 0):
            offer()
        local, done = {}, 0  # the caller's results; how many have been yielded
        try:
            while done < len(jobs):
                future = futures.get(done)  # the next result, if a worker has the job
                if done in local:
                    yield local.pop(done)
                elif future is not None and future.done():
                    yield self._result(future, jobs[done], run_here)
                elif (i := claims.back()) is not None:  # nothing to yield yet: take a job
                    local[i] = run_here(jobs[i])
                    continue
                else:  # every job is taken, this one by a worker (None: it could not be handed over)
                    future = futures[done]
                    yield (
                        run_here(jobs[done]) if future is None else self._result(future, jobs[done], run_here)
                    )
                done += 1
        finally:
            claims.close()
            for future in futures.values():
                if future is not None:
                    future.cancel()

    def _result(self, future: Future, job: Job, run_here: Callable[[Job], dict]) -> dict:
        try:
            return future.result()
        except (BrokenProcessPool, CancelledError) as err:  # a worker died: the job runs here
            self._give_up(err)
            return run_here(job)

    def _submit(self, job: Job) -> Future | None:
        executor = self._executor
        if executor is None:
            return None
        try:
            return executor.submit(job)
        except Exception as err:  # a broken or shut pool, a worker that cannot start
            self._give_up(err)
            return None

    def _give_up(self, err: BaseException) -> None:
        """Say once that the workers are unavailable; from now on everything runs here. (Called from the
        executor's thread too, so it does not wait for the workers.)"""
        with self._lock:
            executor, self._executor = self._executor, None
            if self._gave_up:
                return
            self._gave_up = True
        warnings.warn(
            f"rollout worker processes unavailable ({type(err).__name__}: {err}); running the rollouts in this "
            "process from now on (if the workers could not start from a script: it needs an "
            '`if __name__ == "__main__":` guard)',
            RuntimeWarning,
            stacklevel=3,
        )
        if executor is not None:
            executor.shutdown(wait=False, cancel_futures=True)

    def close(self, terminate: bool = False) -> None:
        """Stop the workers after their current job (``terminate``: at once, the job's result lost); later jobs
        run in this process."""
        with self._lock:
            executor, self._executor = self._executor, None
        if executor is None:
            return
        if terminate:  # (concurrent.futures has no public way before Python 3.14)
            for process in list(getattr(executor, "_processes", {}).values()):
                process.terminate()
        executor.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> RolloutPool:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(terminate=exc_type is not None)  # an error or Ctrl-C does not wait for the workers' jobs


def _call(job: Job) -> dict:
    return job()


class _Claims:
    """The jobs of one :meth:`RolloutPool.map` not yet taken: ``[front, back)``."""

    def __init__(self, jobs: int) -> None:
        self.lock = threading.Lock()
        self.front, self.end = 0, jobs

    def take_front(self) -> int | None:  # with the lock held
        if self.front >= self.end:
            return None
        self.front += 1
        return self.front - 1

    def back(self) -> int | None:
        with self.lock:
            if self.front >= self.end:
                return None
            self.end -= 1
            return self.end

    def close(self) -> None:
        with self.lock:
            self.end = self.front
