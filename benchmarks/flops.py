"""What the speed benchmarks measure besides their steps: FLOPs counted per operator with PyTorch's formulas
(:func:`count_flops`), a device's product rate on a step's own layer shapes (:func:`matmul_rate`) and on a large
square product (:func:`machine_peak`), and waiting for a device's queued work (:func:`synchronize`).

    >>> count_flops(lambda: torch.ones(4, 3) @ torch.ones(3, 2))  # 2 * 4 * 3 * 2
    48
"""

from __future__ import annotations

import itertools
import time

import torch


def synchronize(device) -> None:
    """Wait for ``device``'s queued work (a CUDA device runs asynchronously); nothing on a CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def count_flops(fn) -> int:
    """FLOPs of ``fn()``, counted per operator with PyTorch's FLOP formulas
    (``torch.utils.flop_counter.flop_registry``; its ``FlopCounterMode`` cannot be used: its module tracker
    breaks on the penalty's ``autograd.grad``)."""
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils.flop_counter import flop_registry

    class Count(TorchDispatchMode):
        total = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            kwargs = kwargs or {}
            out = func(*args, **kwargs)
            formula = flop_registry.get(func._overloadpacket)
            if formula is not None:
                Count.total += formula(*args, **kwargs, out_val=out)
            return out

    with Count():
        fn()
    return Count.total


def matmul_rate(batch_size: int, cells: list[int], obs_dim: int, seconds: float = 1.0, device="cpu") -> float:
    """FLOP/s of ``device`` on the step's own matmul shapes (its MLP layers at 3x the batch, as nu runs)."""
    dims = [obs_dim, *cells]
    mats = [
        (torch.randn(3 * batch_size, i, device=device), torch.randn(i, o, device=device))
        for i, o in itertools.pairwise(dims)
    ]
    flops_per_round = sum(2 * a.shape[0] * a.shape[1] * b.shape[1] for a, b in mats)
    for a, b in mats:  # warm-up
        a @ b
    synchronize(device)
    rounds, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for a, b in mats:
            a @ b
        rounds += 1
        synchronize(device)
    return rounds * flops_per_round / (time.perf_counter() - start)


def machine_peak(size: int = 2048, seconds: float = 1.0, device="cpu") -> float:
    """FLOP/s of ``device`` on a large square float32 product (``size`` x ``size``): the most any step's
    products could reach there, whatever their shapes."""
    a, b = torch.randn(size, size, device=device), torch.randn(size, size, device=device)
    a @ b  # warm-up
    synchronize(device)
    rounds, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        a @ b
        rounds += 1
        synchronize(device)
    return rounds * 2 * size**3 / (time.perf_counter() - start)
