"""The safe-support indicator of Eq. (13): a kappa-quantile cut on the safe discriminator's ratio, and the checks
of an indicator a loss reads (0/1 values; with several constraints, a non-empty intersection)."""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey

from spoil_torchrl.objectives.annotate import annotate
from spoil_torchrl.objectives.discriminator import LogRatio


def quantile_threshold(log_ratios: torch.Tensor, kappa: float) -> torch.Tensor:
    """The kappa-quantile of ``log_ratios`` taken as an actual sample (the "lower" order statistic).

    Using an order statistic rather than an interpolated value means that the cut keeps at least
    ``(1 - kappa) n`` of the samples it was computed on, and that the cut on ``log r`` equals the cut on
    ``r`` (log is monotone), as Eq. (13) states it on ``r_hat_S``.

    Examples:
        >>> quantile_threshold(torch.arange(100.0), kappa=0.01).item()
        0.0
        >>> quantile_threshold(torch.arange(100.0), kappa=0.1).item()
        9.0
    """
    values = log_ratios.reshape(-1)
    if values.numel() == 0:
        raise ValueError("cannot compute a quantile of an empty set of safe samples")
    if not torch.isfinite(values).all():
        raise ValueError("the safe discriminator returned non-finite log-ratios; check its training")
    k = math.floor(kappa * (values.numel() - 1)) + 1
    return values.kthvalue(k).values


def support_indicator(log_ratio: torch.Tensor, threshold: torch.Tensor) -> torch.Tensor:
    """Eq. (13): ``1_S(s, a) = [r_hat_S(s, a) >= Quantile_kappa(r_hat_S, D_S)]`` as a float 0/1 tensor.

    Examples:
        >>> support_indicator(torch.tensor([-1.0, 0.0, 2.0]), torch.tensor(0.0)).tolist()
        [0.0, 1.0, 1.0]
    """
    return (log_ratio >= threshold).to(log_ratio.dtype)


class SupportEstimator(TensorDictModuleBase):
    """Estimated safe support :math:`\\hat 1_{d_S}` (Eq. 13) from a trained safe discriminator :math:`\\hat C_S`.

    :meth:`fit` computes the kappa-quantile of :math:`\\log \\hat r_S` over the safe demonstrations; calling the
    module then writes the 0/1 indicator (shape ``[*B, 1]``) at ``out_key``. :meth:`annotate` does so once for
    a whole stored dataset. The discriminator's logit is :math:`\\log \\hat r_S` (Eq. 18); pass
    ``log_ratio_fn`` when it is not (e.g. :func:`~spoil_torchrl.objectives.pu_log_ratio` for a PU-trained one).

    Args:
        discriminator (TensorDictModule): the safe discriminator; its first out_key is read.

    Keyword Args:
        kappa (float): quantile cutoff in (0, 1). Default 0.01 (paper section 4.3).
        out_key (str): where the indicator is written. Default ``"safe_support"``.
        log_ratio_fn (callable, optional): maps the discriminator output to :math:`\\log \\hat r_S`.

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> disc = TensorDictModule(lambda obs: obs[..., :1], in_keys=["observation"], out_keys=["logit"])
        >>> safe = TensorDict({"observation": torch.arange(100.0).unsqueeze(-1)}, [100])
        >>> support = SupportEstimator(disc, kappa=0.05).fit(safe)
        >>> support.threshold.item()
        4.0
        >>> query = TensorDict({"observation": torch.tensor([[3.0], [4.0], [50.0]])}, [3])
        >>> support(query)["safe_support"].squeeze(-1).tolist()
        [0.0, 1.0, 1.0]
    """

    def __init__(
        self,
        discriminator: TensorDictModule,
        *,
        kappa: float = 0.01,
        out_key: str = "safe_support",
        log_ratio_fn=None,
    ) -> None:
        super().__init__()
        if not isinstance(kappa, numbers.Real) or not 0.0 < float(kappa) < 1.0:
            raise ValueError(f"kappa must lie strictly between 0 and 1, got {kappa!r}")
        self.log_ratio_module = LogRatio(discriminator, out_key="log_ratio_safe", log_ratio_fn=log_ratio_fn)
        self.kappa = float(kappa)
        self.in_keys = list(discriminator.in_keys)
        self.out_keys = [out_key]
        self.register_buffer("threshold", torch.tensor(float("nan")))

    @property
    def fitted(self) -> bool:
        return bool(torch.isfinite(self.threshold))

    @torch.no_grad()
    def log_ratio(self, tensordict: TensorDictBase) -> torch.Tensor:
        """:math:`\\log \\hat r_S` for every row of ``tensordict`` (shape ``[*B, 1]``)."""
        return self.log_ratio_module.log_ratio(tensordict)

    @torch.no_grad()
    def fit(self, safe: TensorDictBase | Iterable[TensorDictBase], *, chunk_size: int = 65536):
        """Set the threshold to the kappa-quantile of :math:`\\log \\hat r_S` over all safe samples.

        Args:
            safe: the safe demonstrations, as one tensordict or an iterable of chunks.
        """
        chunks = [safe] if isinstance(safe, TensorDictBase) else list(safe)
        values = []
        for chunk in chunks:
            flat = chunk.reshape(-1)
            for start in range(0, flat.shape[0], chunk_size):
                values.append(self.log_ratio(flat[start : start + chunk_size]).reshape(-1))
        if not values:
            raise ValueError("cannot fit the support estimator on an empty safe dataset")
        self.threshold.copy_(quantile_threshold(torch.cat(values), self.kappa))
        return self

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self.fitted:
            raise RuntimeError("SupportEstimator.fit(safe_data) must be called before the indicator is used")
        with torch.no_grad():
            indicator = support_indicator(self.log_ratio(tensordict), self.threshold)
        tensordict.set(self.out_keys[0], indicator)
        return tensordict

    def annotate(self, data, *, chunk_size: int = 65536, progress: bool = False) -> TensorDictBase:
        """Write the indicator into a stored dataset (tensordict, storage or replay buffer) once."""
        return annotate(data, self, chunk_size=chunk_size, progress=progress)


def check_support_indicator(support: torch.Tensor, key: NestedKey) -> None:
    """Raise a clear ``ValueError`` unless ``support`` (read from ``key``) is a 0/1 indicator (Eq. 13).

    The check is an assertion on the tensor's device (:func:`torch._assert_async`): on a CPU it raises at once,
    on a GPU it fails the device's stream later, so a training step never waits to read the answer back.

    Examples:
        >>> check_support_indicator(torch.tensor([0.0, 1.0]), "safe_support")
    """
    if torch.compiler.is_compiling():
        return
    message = (
        f"{key} must be a 0/1 indicator (Eq. 13); got other values. "
        "Write it with SupportEstimator, or point set_keys(support=...) at the right entry."
    )
    indicator = ((support == 0) | (support == 1)).all()
    try:  # only the assertion's own failure is the message's
        torch._assert_async(indicator, message)
    except RuntimeError:  # a CPU's answer, at once
        raise ValueError(message) from None


def check_supports_intersect(support: torch.Tensor, key: NestedKey) -> None:
    """Raise a clear ``ValueError`` when ``support`` (``[n, K]`` indicators, one column per constraint, read from
    ``key``) has no row inside every support: nothing can then be imitated within all K constraints, and the
    dual of ``docs/several_constraints.md`` is unbounded below. Check it on all of D_U once it is annotated (a
    batch may miss the intersection by chance).

    Examples:
        >>> check_supports_intersect(torch.tensor([[1.0, 0.0], [1.0, 1.0]]), "safe_support")
        >>> check_supports_intersect(torch.tensor([[1.0, 0.0], [0.0, 1.0]]), "s")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: s: no transition is inside all 2 supports (share inside each: 50.0 %, 50.0 %); no policy ...
    """
    support = support.reshape(-1, support.shape[-1])
    if bool((support.prod(-1) > 0).any()):
        return
    each = ", ".join(f"{100 * float(column.float().mean()):.1f} %" for column in support.T)
    raise ValueError(
        f"{key}: no transition is inside all {support.shape[-1]} supports (share inside each: {each}); "
        "no policy can respect every constraint on this data"
    )
