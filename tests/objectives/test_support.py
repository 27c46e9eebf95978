"""SupportEstimator (Eq. 13) and annotation of stored data."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, TensorDictReplayBuffer

from spoil_torchrl.modules import make_discriminator
from spoil_torchrl.objectives import LogRatio, SupportEstimator, annotate, quantile_threshold
from tests.conftest import ACT_DIM, OBS_DIM, transitions


def _first_feature_disc():
    return TensorDictModule(lambda obs: obs[..., :1], in_keys=["observation"], out_keys=["logit"])


@pytest.mark.parametrize("kappa", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_kappa_outside_open_unit_interval_is_rejected(kappa):
    with pytest.raises(ValueError, match="kappa must lie strictly between 0 and 1"):
        SupportEstimator(_first_feature_disc(), kappa=kappa)


@pytest.mark.parametrize("kappa", [0.001, 0.01, 0.05, 0.2])
@pytest.mark.parametrize("n", [1, 7, 1000])
def test_fit_keeps_at_least_one_minus_kappa_of_safe_samples(kappa, n):
    safe = TensorDict({"observation": torch.randn(n, 3)}, [n])
    support = SupportEstimator(_first_feature_disc(), kappa=kappa).fit(safe)
    kept = support(safe.clone())["safe_support"]
    assert kept.shape == (n, 1)
    assert kept.mean().item() >= 1 - kappa
    # and it is a real cut: the kappa-fraction below the threshold is dropped
    assert kept.sum().item() <= n - int(kappa * (n - 1))


def test_threshold_is_an_order_statistic_in_log_space():
    values = torch.tensor([3.0, -1.0, 0.5, 2.0])
    assert quantile_threshold(values, 0.5).item() == 0.5
    with pytest.raises(ValueError, match="empty"):
        quantile_threshold(torch.tensor([]), 0.1)
    with pytest.raises(ValueError, match="non-finite"):
        quantile_threshold(torch.tensor([0.0, float("nan")]), 0.1)


def test_unfitted_estimator_refuses_to_answer():
    with pytest.raises(RuntimeError, match="fit"):
        SupportEstimator(_first_feature_disc())(TensorDict({"observation": torch.zeros(2, 3)}, [2]))


def test_fit_accepts_chunks_and_matches_one_shot():
    safe = TensorDict({"observation": torch.randn(100, 3)}, [100])
    one = SupportEstimator(_first_feature_disc(), kappa=0.1).fit(safe)
    chunked = SupportEstimator(_first_feature_disc(), kappa=0.1).fit([safe[:30], safe[30:]], chunk_size=7)
    assert one.threshold == chunked.threshold
    assert "threshold" in one.state_dict()


@pytest.mark.parametrize("storage_cls", [LazyTensorStorage, LazyMemmapStorage])
def test_annotate_a_replay_buffer_storage_once(storage_cls, tmp_path):
    kwargs = {"scratch_dir": tmp_path} if storage_cls is LazyMemmapStorage else {}
    buffer = TensorDictReplayBuffer(storage=storage_cls(200, **kwargs), batch_size=16)
    data = transitions(150)
    buffer.extend(data)
    disc = make_discriminator(OBS_DIM, ACT_DIM, hidden_cells=(8,))
    support = SupportEstimator(disc, kappa=0.05).fit(data[:50])
    annotate(buffer, LogRatio(disc), chunk_size=32)
    support.annotate(buffer, chunk_size=32)
    sample = buffer.sample()
    assert sample["safe_support"].shape == (16, 1)
    stored = buffer.storage[:150]
    expected = support(data.clone())["safe_support"]
    torch.testing.assert_close(stored["safe_support"], expected)
    with torch.no_grad():
        torch.testing.assert_close(stored["log_ratio_performant"], disc(data.clone())["logit"])


def test_annotate_rejects_bad_inputs():
    disc = _first_feature_disc()
    with pytest.raises(TypeError, match="annotate expects"):
        annotate([1, 2, 3], LogRatio(disc))
    with pytest.raises(KeyError, match="observation"):
        annotate(TensorDict({"obs": torch.zeros(3, 2)}, [3]), LogRatio(disc))
    with pytest.raises(ValueError, match="chunk_size"):
        annotate(TensorDict({"observation": torch.zeros(3, 2)}, [3]), LogRatio(disc), chunk_size=0)
    empty = TensorDictReplayBuffer(storage=LazyTensorStorage(10))
    with pytest.raises(ValueError, match="empty storage"):
        annotate(empty, LogRatio(disc))
