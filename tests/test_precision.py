"""Training's matmul precision: ``medium`` where the training device keeps float32 products float32, IEEE
float32 (``highest``) where it would compute them in bfloat16 (a CPU's oneDNN) or TF32 (a GPU), said once."""

from __future__ import annotations

import logging

import pytest
import torch

from spoil_torchrl import precision
from spoil_torchrl.precision import matmul_check, matmul_relative_error, training_precision


@pytest.mark.parametrize(("error", "expected"), [(4e-6, "medium"), (1.6e-2, "highest")])
def test_medium_falls_back_to_ieee_products_where_they_would_be_bfloat16(
    monkeypatch, caplog, error, expected
):
    monkeypatch.setattr(precision, "matmul_relative_error", lambda **_: error)
    before = torch.get_float32_matmul_precision()
    with caplog.at_level(logging.WARNING), training_precision("medium") as level:
        assert level == expected == torch.get_float32_matmul_precision()
    assert torch.get_float32_matmul_precision() == before
    assert ("bfloat16" in caplog.text) == (expected == "highest")


def test_highest_is_never_measured_nor_changed(monkeypatch):
    monkeypatch.setattr(precision, "matmul_relative_error", lambda **_: pytest.fail("measured"))
    with training_precision("highest") as level:
        assert level == "highest"


def test_the_error_is_measured_on_the_training_device(monkeypatch, caplog):
    measured = []

    def tf32(device=None):  # what a GPU's TF32 products give (a 10-bit mantissa)
        measured.append(device)
        return 1.2e-3

    monkeypatch.setattr(precision, "matmul_relative_error", tf32)
    with caplog.at_level(logging.WARNING), training_precision("medium", "cuda:0") as level:
        assert level == "highest" == torch.get_float32_matmul_precision()
        assert matmul_check("cuda:0") == 1.2e-3
    assert measured == ["cuda:0", "cuda:0"]
    assert "cuda:0 computes float32 products in TF32 or bfloat16 there" in caplog.text
    assert "lose precision on cuda:0" in caplog.text
    assert "oneDNN" not in caplog.text


def test_the_error_on_the_cpu_is_the_same_named_or_not():
    for level in ("highest", "medium"):
        with precision.matmul_precision(level):
            assert (
                matmul_relative_error(device="cpu")
                == matmul_relative_error()
                == matmul_relative_error(device=torch.device("cpu"))
            )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_gpu_s_tf32_products_count_as_reduced_precision():
    with precision.matmul_precision("highest"):
        assert matmul_relative_error(device="cuda") <= precision.REDUCED_PRECISION_ERROR
    with precision.matmul_precision("high"):  # TF32 wherever the GPU has it (NVIDIA since Ampere)
        if torch.cuda.get_device_capability()[0] >= 8:
            assert matmul_relative_error(device="cuda") > precision.REDUCED_PRECISION_ERROR
