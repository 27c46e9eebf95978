"""Training's matmul precision: ``medium`` where this machine keeps float32 products float32, IEEE float32
(``highest``) where its oneDNN would compute them in bfloat16, said once."""

from __future__ import annotations

import logging

import pytest
import torch

from spoil_torchrl import precision
from spoil_torchrl.precision import training_precision


@pytest.mark.parametrize(("error", "expected"), [(4e-6, "medium"), (1.6e-2, "highest")])
def test_medium_falls_back_to_ieee_products_where_they_would_be_bfloat16(
    monkeypatch, caplog, error, expected
):
    monkeypatch.setattr(precision, "matmul_relative_error", lambda: error)
    before = torch.get_float32_matmul_precision()
    with caplog.at_level(logging.WARNING), training_precision("medium") as level:
        assert level == expected == torch.get_float32_matmul_precision()
    assert torch.get_float32_matmul_precision() == before
    assert ("bfloat16" in caplog.text) == (expected == "highest")


def test_highest_is_never_measured_nor_changed(monkeypatch):
    monkeypatch.setattr(precision, "matmul_relative_error", lambda: pytest.fail("measured"))
    with training_precision("highest") as level:
        assert level == "highest"
