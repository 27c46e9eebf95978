"""Evaluation rollouts in worker processes: the same arrays as in the caller, and a caller that survives its
workers (and the other way round)."""

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

from spoil_torchrl.eval import Evaluator, RolloutWriter
from spoil_torchrl.eval.parallel import RolloutPool, local_share

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


class Fails:
    def __call__(self) -> dict:
        raise ValueError(f"no rollout in {os.getpid()}")


def _policies():
    from spoil_torchrl.experts import load_policy, zoo_policy
    from spoil_torchrl.modules import ObservationNormalizer, make_actor, with_observation_norm

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
        with pytest.warns(RuntimeWarning, match="evaluating in this process"):
            results = list(pool.map([DiesOutsideCaller(caller), DiesOutsideCaller(caller)]))
        assert results == [{"pid": caller}] * 2
        assert pool.workers == 1 and list(pool.map([DiesOutsideCaller(caller)] * 2)) == [{"pid": caller}] * 2


def test_a_jobs_error_is_raised_in_the_caller():
    with RolloutPool(workers=1) as pool:
        results = pool.map([Fails(), lambda: {"a": 1}])  # the first job runs in the worker
        with pytest.raises(ValueError, match="no rollout in") as err:
            next(results)
        assert str(os.getpid()) not in str(err.value)


def test_no_workers_runs_everything_here():
    assert local_share(4, 0) == 4
    with RolloutPool(workers=0) as pool:
        assert list(pool.map([lambda: {"a": 1}, lambda: {"a": 2}])) == [{"a": 1}, {"a": 2}]


def test_workers_exit_when_the_caller_is_killed():
    script = textwrap.dedent(
        """
        import time
        from spoil_torchrl.eval.parallel import RolloutPool
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
    deadline = time.monotonic() + 30
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in workers)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False
