"""How float32 matrix products are computed during a run: PyTorch's ``float32_matmul_precision``, scoped.

``train.matmul_precision`` names one of PyTorch's three levels (:func:`torch.set_float32_matmul_precision`):

* ``"highest"``: IEEE float32 products everywhere (the committed eager results' mode);
* ``"high"``: TF32 tensor cores on NVIDIA GPUs (and oneDNN's TF32 path on CPUs that have one);
* ``"medium"``: on a CPU, float32 products handed to oneDNN, which may use bfloat16 arithmetic (below); on
  NVIDIA GPUs, TF32.

Tensors, parameters, optimiser states and every non-matmul operation stay float32 at all three levels: only the
inside of a matrix product may change. What ``"medium"`` does on a CPU depends on the CPU. It hands float32
products to oneDNN and allows it bfloat16 arithmetic; on this project's machines (AMD EPYC, AVX-512 without AMX)
oneDNN still picks its float32 kernel (``ONEDNN_VERBOSE=1`` names ``brg_matmul:avx512_core``), which runs the
step's layer products 2.2x as fast as the MKL kernel ``"highest"`` uses, at float32 accuracy (largest relative
error against float64: 4e-6, against 2e-6 for MKL; CONTRIBUTING.md, "Matmul precision"). On a CPU with AMX, oneDNN may
take bfloat16 kernels instead (relative errors of ~1e-2). :func:`matmul_relative_error` measures which of the
two a machine does; the main recipe trains at :func:`training_precision`, which falls back to ``"highest"`` where
products would lose precision on the training device (a CPU's bfloat16 kernels, a GPU's TF32), and records the
level in force and its error on that device in ``results.json``.
The recipe applies the level to training (pre-training and the main stage) only, and every policy rollout
(:func:`~spoil_torchrl.envs.rollout.rollout`: generated datasets, evaluations) computes IEEE products whatever the
level, so neither a cached dataset nor an evaluation depends on it.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any

import torch

log = logging.getLogger(__name__)

#: The levels of :func:`torch.set_float32_matmul_precision`, most exact first.
MATMUL_PRECISIONS = ("highest", "high", "medium")

#: Above this relative error a float32 product has lost precision: IEEE float32 kernels stay below 1e-5 on
#: :func:`matmul_relative_error`'s product, a bfloat16 rounding of the inputs alone gives ~1e-2.
REDUCED_PRECISION_ERROR = 1e-4


def intra_op_threads(threads: int) -> contextlib.AbstractContextManager[None]:
    """Run the block with ``torch.set_num_threads(threads)``, restoring the previous number after.

    A product's rounding may depend on how many threads compute it (on this project's CPUs a ``[10, 256] x
    [256, 256]`` float32 product differs in the last bits between one and two threads), so code whose numbers must
    not depend on the caller's ``threads`` runs at a fixed number.

    Examples:
        >>> before = torch.get_num_threads()
        >>> with intra_op_threads(1):
        ...     torch.get_num_threads()
        1
        >>> torch.get_num_threads() == before
        True
    """
    return _scoped(torch.get_num_threads, torch.set_num_threads, threads)


def matmul_precision(precision: str) -> contextlib.AbstractContextManager[None]:
    """Run the block with ``torch.set_float32_matmul_precision(precision)``, restoring the previous level after.

    Examples:
        >>> with matmul_precision("medium"):
        ...     torch.get_float32_matmul_precision()
        'medium'
        >>> torch.get_float32_matmul_precision()
        'highest'
    """
    if precision not in MATMUL_PRECISIONS:
        raise ValueError(f"matmul precision must be one of {MATMUL_PRECISIONS}, got {precision!r}")
    return _scoped(torch.get_float32_matmul_precision, torch.set_float32_matmul_precision, precision)


@contextlib.contextmanager
def _scoped(get: Callable[[], Any], set_: Callable[[Any], None], value: Any) -> Iterator[None]:
    """A global setting set to ``value`` for the block, its previous value restored after."""
    previous = get()
    set_(value)
    try:
        yield
    finally:
        set_(previous)


def matmul_relative_error(
    rows: int = 512, cells: int = 256, device: torch.device | str | None = None
) -> float:
    """Largest relative error, against float64, of a float32 ``[rows, cells] x [cells, cells]`` product (the size of
    a hidden layer of the default networks on a batch) at the current matmul precision, computed on ``device``
    (``None``: the CPU) from the same operands on every device.

    Below :data:`REDUCED_PRECISION_ERROR` the products are float32 whatever kernel computes them. On an NVIDIA
    GPU, ``"high"`` and ``"medium"`` allow TF32 (a 10-bit mantissa: errors of ~1e-3).

    Examples:
        >>> matmul_relative_error() < REDUCED_PRECISION_ERROR  # "highest": IEEE float32
        True
        >>> matmul_relative_error(device="cpu") == matmul_relative_error()
        True
    """
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(rows, cells, generator=generator)
    b = torch.randn(cells, cells, generator=generator)
    exact = a.double() @ b.double()
    product = a @ b if _on_cpu(device) else (a.to(device) @ b.to(device)).cpu()
    return float((product.double() - exact).abs().max() / exact.abs().mean())


@contextlib.contextmanager
def training_precision(precision: str, device: torch.device | str | None = None) -> Iterator[str]:
    """Run training's block at ``precision`` (``train.matmul_precision``) if ``device`` (training's; ``None``: the
    CPU) keeps float32 products float32 there, else at ``"highest"``: yields the level in force.

    ``"medium"`` is the default presets' level because on CPUs without AMX oneDNN computes it in float32, 2.2x as
    fast as MKL. A CPU with AMX computes it in bfloat16 (relative error ~1e-2, :func:`matmul_relative_error`):
    the run would then train with other arithmetic than the same settings give elsewhere, so training falls back
    to IEEE float32 (``"highest"``), says so once, and the run records the level in force
    (``results.json``'s ``matmul_precision``). The same holds on an NVIDIA GPU, where ``"medium"`` is TF32.

    Examples:
        >>> with training_precision("highest") as level:
        ...     level
        'highest'
    """
    with matmul_precision(precision):
        error = 0.0 if precision == "highest" else matmul_relative_error(device=device)
        if error <= REDUCED_PRECISION_ERROR:
            yield precision
            return
    who = "this CPU's oneDNN" if _on_cpu(device) else str(device)
    log.warning(
        f"train.matmul_precision={precision}: {who} computes float32 products in {_reduced_kernels(device)} "
        f"there (relative error {error:.1e}); training uses IEEE float32 (highest) instead"
    )
    with matmul_precision("highest"):
        yield "highest"


def matmul_check(device: torch.device | str | None = None) -> float:
    """The relative error of float32 products at the run's matmul precision on ``device`` (training's; ``None``:
    the CPU); a warning when they lose precision (``train.matmul_precision=medium`` on a CPU whose oneDNN takes
    bfloat16 kernels, e.g. one with AMX, or on a GPU's TF32)."""
    error = matmul_relative_error(device=device)
    if error > REDUCED_PRECISION_ERROR:
        log.warning(
            f"train.matmul_precision={torch.get_float32_matmul_precision()}: float32 products lose precision on "
            f"{device or 'this machine'} (relative error {error:.1e}: {_reduced_kernels(device)} kernels); "
            "train.matmul_precision=highest keeps them IEEE float32"
        )
    return error


def _reduced_kernels(device: torch.device | str | None) -> str:
    """The arithmetic a reduced-precision float32 product uses on ``device``: a CPU's oneDNN takes bfloat16, an
    NVIDIA GPU TF32 (or bfloat16)."""
    return "bfloat16" if _on_cpu(device) else "TF32 or bfloat16"


def _on_cpu(device: torch.device | str | None) -> bool:
    return device is None or torch.device(device).type == "cpu"
