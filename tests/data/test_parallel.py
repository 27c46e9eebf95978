"""Rollouts in worker processes: the same arrays as in the caller (evaluations, a generated dataset), and a
caller that survives its workers (and the other way round)."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

from spoil_torchrl.data.parallel import RolloutPool
from spoil_torchrl.eval import Evaluator, RolloutWriter

needs_simulator = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium missing"
)


class DiesOutsideCaller:
    """A job that kills the worker process it runs in (and returns where it ran in the caller)."""

    def __init__(self, caller: int) -> None:
        self.caller = caller

    def __call__(self) -> dict:
        if os.getpid() != self.caller:
            os._exit(1)
        return {"pid": os.getpid()}


class Sleeps:
    def __call__(self) -> dict:
        time.sleep(2.0)  # long enough for a worker to have taken the jobs before this one
        return {"slept": True}


class SleepsLong:
    def __call__(self) -> dict:
        time.sleep(120.0)
        return {}


class Interrupted:
    def __call__(self) -> dict:
        raise KeyboardInterrupt


class Fails:
    def __call__(self) -> dict:
        raise ValueError(f"no rollout in {os.getpid()}")


def _policies():
    from spoil_torchrl.modules import ObservationNormalizer, make_actor, with_observation_norm
    from spoil_torchrl.zoo import load_policy, zoo_policy

    torch.manual_seed(0)
    standardised = with_observation_norm(
        make_actor(28, 2, hidden_cells=(64, 64)),
        ObservationNormalizer(torch.randn(28), torch.rand(28) + 0.5),
    )
    zoo = [load_policy(zoo_policy("SafetyPointCircle1-v0", name))[0] for name in ("ppo-0050k", "ppo-0250k")]
    return [*zoo, standardised]


@needs_simulator
def test_worker_rollouts_equal_the_callers_bit_for_bit(tmp_path):
    """The pool's arrays (worker and caller shares) equal each evaluation's rollout run here, at another number
    of threads than the worker's one, poses included; the jobs come back in order."""
    policies = _policies()
    with RolloutWriter(tmp_path / "r.mcap", cost_threshold=25.0) as writer:
        evaluator = Evaluator(
            "SafetyPointCircle1-v0",
            cost_threshold=25.0,
            return_range=(0.0, 40.0),
            episodes=3,
            num_envs=2,
            seed=7,
            writer=writer,
        )
        jobs = [evaluator.rollout_job(policy) for policy in policies]
        threads = torch.get_num_threads()
        torch.set_num_threads(2)
        try:
            here = [job() for job in jobs]
        finally:
            torch.set_num_threads(threads)
        with RolloutPool(workers=1) as pool:
            pooled = list(pool.map(jobs))
        for a, b in zip(here, pooled, strict=True):
            assert a.keys() == b.keys() and "recorded" in a
            for key in a:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert len({float(arrays["rewards"].sum()) for arrays in here}) == 3  # three different policies
        # the report of a rollout from elsewhere is the evaluation itself
        assert evaluator.report(pooled[0], step=5) == evaluator(policies[0], step=5)


def test_a_dead_worker_is_reported_once_and_its_jobs_run_here():
    caller = os.getpid()
    with RolloutPool(workers=1) as pool:
        with pytest.warns(RuntimeWarning, match="running the rollouts in this process"):
            results = list(pool.map([DiesOutsideCaller(caller), Sleeps()]))  # the worker takes the first
        assert results == [{"pid": caller}, {"slept": True}]
        assert list(pool.map([DiesOutsideCaller(caller)] * 2)) == [{"pid": caller}] * 2  # all here now


def test_a_jobs_error_is_raised_in_the_caller():
    with RolloutPool(workers=1) as pool:
        with pytest.raises(ValueError, match="no rollout in"):
            list(pool.map([Fails(), Fails(), Fails()]))


def test_ctrl_c_in_the_caller_does_not_wait_for_the_workers():
    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt), RolloutPool(workers=1) as pool:
        list(pool.map([SleepsLong(), Interrupted()]))  # the worker sleeps, the caller is interrupted
    assert time.monotonic() - start < 60


def test_no_workers_runs_everything_here():
    with RolloutPool(workers=0) as pool:
        assert list(pool.map([lambda: {"a": 1}, lambda: {"a": 2}])) == [{"a": 1}, {"a": 2}]


def test_workers_exit_when_the_caller_is_killed():
    script = textwrap.dedent(
        """
        import time
        from spoil_torchrl.data.parallel import RolloutPool
        pool = RolloutPool(workers=2)
        print(*(p.pid for p in pool._executor._processes.values()), flush=True)
        time.sleep(600)
        """
    )
    caller = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    workers = [int(pid) for pid in caller.stdout.readline().split()]
    assert len(workers) == 2
    caller.send_signal(signal.SIGKILL)
    caller.wait(timeout=30)
    # a worker notices once it has started (its imports first), which a loaded machine can delay past 30 s
    deadline = time.monotonic() + 90
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in workers)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False


@needs_simulator
def test_a_dataset_collected_with_a_worker_is_the_one_collected_here(tmp_path):
    import h5py

    from spoil_torchrl.data import read_metadata
    from spoil_torchrl.data.collect import Segment, collect

    segments = [
        Segment("safe", "zoo:safe-high", 2),
        Segment("unsafe", "zoo:unsafe-high", 1),
        Segment("random", "random", 1),
    ]
    files = {
        workers: collect(
            "SafetyPointCircle1-v0",
            segments,
            tmp_path / f"w{workers}.hdf5",
            seed=3,
            num_envs=2,
            reference_episodes=1,
            progress=False,
            workers=workers,
        )
        for workers in (0, 1)
    }
    with h5py.File(files[0]) as here, h5py.File(files[1]) as shared:
        assert sorted(here) == sorted(shared)
        for key in here:
            if isinstance(here[key], h5py.Dataset):
                np.testing.assert_array_equal(here[key][()], shared[key][()], err_msg=key)
    meta = [read_metadata(files[w]) for w in (0, 1)]
    for m in meta:
        m.pop("seconds")
    assert meta[0] == meta[1] and meta[0]["safe_high_return"] is not None


def test_a_script_without_a_main_guard_is_told_and_still_gets_its_results(tmp_path):
    """Spawned workers import the caller's script again; one without an ``if __name__ == "__main__":`` guard
    would start the pool once more in each worker: the worker stops instead, and the caller runs the jobs."""
    script = tmp_path / "unguarded.py"
    script.write_text(
        textwrap.dedent(
            """
            import functools
            import time
            import warnings

            from spoil_torchrl.data.parallel import RolloutPool

            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                with RolloutPool(workers=1) as pool:
                    # the caller takes the last job, long enough for the worker to take the first
                    jobs = [functools.partial(dict, a=1), functools.partial(time.sleep, 2.0)]
                    print(list(pool.map(jobs)), [str(w.message) for w in caught])
            """
        )
    )
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("[{'a': 1}, None]") and "__main__" in proc.stdout  # the warning's hint
    assert "guard its entry point" in proc.stderr  # the worker's reason


def _pool_in_a_daemon(queue) -> None:
    import functools
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with RolloutPool(workers=1) as pool:
            results = list(pool.map([functools.partial(dict, a=1), functools.partial(dict, a=2)]))
    queue.put((results, [str(w.message) for w in caught]))


def test_a_pool_in_a_daemonic_process_runs_everything_there():
    """A daemonic process (a multiprocessing.Pool worker, say) may not start processes: the pool says so and runs
    the jobs itself."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    daemon = context.Process(target=_pool_in_a_daemon, args=(queue,), daemon=True)
    daemon.start()
    results, messages = queue.get(timeout=120)
    daemon.join(timeout=60)
    assert results == [{"a": 1}, {"a": 2}] and daemon.exitcode == 0
    assert len(messages) == 1 and "daemonic processes are not allowed to have children" in messages[0]
