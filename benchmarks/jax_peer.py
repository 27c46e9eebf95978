"""The SpoilDICE + weighted-BC update written in JAX and jit-compiled whole: the peer ``bench_losses.py`` measures
the library's step against (``make bench`` prints it when JAX is installed: ``pip install -e ".[bench]"``).

The same math as ``reference_step.ReferenceStep`` and the library's step, in the form a JAX user would write it:

* nu, a ReLU MLP ([256, 256] by default) on the initial, current and next states (one pass), and its input
  gradient at the penalty's points (JAX's zeros are symbolic: the penalty's gradient skips the products on
  zeros that PyTorch's autograd does, see ``spoil_torchrl.objectives.input_gradient``; the library's compiled
  form, nu's values at :math:`s` taken from the penalty's pass, costs JAX 0.2 GFLOP more, and this form is the
  cheaper of the two for JAX);
* the dual of Eq. (19) with :math:`\\lambda` detached for nu and nu detached for :math:`\\lambda` (one
  objective here: the stop-gradients make its gradient that of the two losses);
* nu's gradient penalty :math:`c\\,E\\lVert \\nabla_s \\nu \\rVert^2` on the current states, points between the
  initial and current states and points between :math:`s` and :math:`s'` (one uniform draw per row, inside the
  jitted step);
* the policy, a ReLU MLP giving a tanh-squashed Gaussian (mean clipped, log-std clipped to [-5, 2], actions
  clipped to :math:`\\pm(1 - 10^{-6})`), trained by weighted BC on the self-normalised closed-form weights;
* Adam (optax) on every parameter, learning rate 3e-5.

One call of :meth:`JaxStep.__call__` is one update: forward, backward, the penalty's second derivative and the
optimiser, in one XLA executable. :meth:`JaxStep.flops` is XLA's own count of that executable's arithmetic
(its ``cost_analysis``): 1.79 GFLOP at the bench's sizes. A penalty on two sets of points only (the
interpolations, not the current states) would be 1.48 GFLOP: that is a different objective from the library's.

XLA reads its thread settings when JAX is first imported: :func:`import_jax` sets one intra-op thread when
``threads == 1`` (the flags below), so a one-thread comparison is one thread on both sides.
"""

from __future__ import annotations

import math
import os
import time


def import_jax(threads: int, platform: str = "cpu"):
    """Import JAX (``None`` when it is not installed, or has no backend for ``platform``: ``"cpu"`` or
    ``"cuda"``) with XLA on ``platform``, on ``threads`` threads (only 1 is forced, on the CPU: XLA's CPU client
    otherwise sizes its pool from the process's cores)."""
    if threads == 1:
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = (
            f"{flags} --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".strip()
        )
    try:
        import jax
        import jax.numpy as jnp  # noqa: F401
        import optax  # noqa: F401
    except ImportError:
        return None
    jax.config.update("jax_platforms", platform)
    try:
        jax.devices(platform)
    except RuntimeError:  # e.g. a CPU-only JAX asked for "cuda"
        return None
    return jax


def _mlp_init(key, sizes: list[int]):
    """PyTorch's default ``nn.Linear`` initialisation (uniform in +/- 1/sqrt(fan_in)) of an MLP of ``sizes``."""
    import jax

    params = []
    for fan_in, fan_out in zip(sizes[:-1], sizes[1:], strict=True):
        key, kw, kb = jax.random.split(key, 3)
        bound = 1.0 / math.sqrt(fan_in)
        params.append(
            (
                jax.random.uniform(kw, (fan_in, fan_out), minval=-bound, maxval=bound),
                jax.random.uniform(kb, (fan_out,), minval=-bound, maxval=bound),
            )
        )
    return params


def _mlp(params, x):
    import jax.numpy as jnp

    for i, (w, b) in enumerate(params):
        x = x @ w + b
        if i < len(params) - 1:
            x = jnp.maximum(x, 0.0)
    return x


class JaxStep:
    """One jitted SpoilDICE + weighted-BC update (see the module docstring) on numpy batches.

    Args:
        obs_dim, act_dim: state and action sizes.
        cells: hidden layer sizes of nu and the policy.
        gamma, gradient_penalty, lr: the step's constants (the bench's).
        seed: initial parameters and the penalty's random stream.
        optimizer: ``False`` leaves Adam out: the jitted step computes the gradients (returned, so XLA keeps
            them) and leaves the parameters as they are, to time the gradient graph alone.
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        cells: tuple[int, ...],
        *,
        gamma: float = 0.99,
        gradient_penalty: float = 10.0,
        lr: float = 3e-5,
        seed: int = 0,
        optimizer: bool = True,
    ) -> None:
        import jax
        import jax.numpy as jnp
        import optax

        key = jax.random.PRNGKey(seed)
        k_nu, k_pi, self.key = jax.random.split(key, 3)
        params = {
            "nu": _mlp_init(k_nu, [obs_dim, *cells, 1]),
            "pi": _mlp_init(k_pi, [obs_dim, *cells, 2 * act_dim]),
            "lagrange": jnp.zeros(()),
        }
        adam = optax.adam(lr)
        self.state = (params, adam.init(params))
        clip, bound = 1.0 - 1e-6, math.atanh(1.0 - 1e-6)

        def nu(p, states):
            return _mlp(p["nu"], states)[:, 0]

        def losses(p, batch, key):
            s0, obs, nxt = batch["init"], batch["observation"], batch["next_observation"]
            n0, n = s0.shape[0], obs.shape[0]
            m = min(n0, n)
            k1, k2 = jax.random.split(key)
            a1 = jax.random.uniform(k1, (m, 1))
            a2 = jax.random.uniform(k2, (n, 1))
            points = jnp.concatenate([obs, a1 * s0[:m] + (1 - a1) * obs[:m], a2 * obs + (1 - a2) * nxt])
            g = jax.grad(lambda x: nu(p, x).sum())(points)
            v = nu(p, jnp.concatenate([s0, obs, nxt]))
            v0, v_cur, v_next = v[:n0], v[n0 : n0 + n], v[n0 + n :]
            lam = p["lagrange"]
            base = batch["log_ratio"] + gamma * v_next * (1.0 - batch["terminated"]) - v_cur
            adv = base + jax.lax.stop_gradient(lam) * batch["support"]
            adv_lam = jax.lax.stop_gradient(adv) + (lam - jax.lax.stop_gradient(lam)) * batch["support"]

            def lme(x):
                return jax.scipy.special.logsumexp(x) - math.log(x.shape[0])

            loss_nu = (1 - gamma) * v0.mean() + lme(adv) - jax.lax.stop_gradient(lam)
            loss_lam = (1 - gamma) * jax.lax.stop_gradient(v0).mean() + lme(adv_lam) - lam
            loss_nu = loss_nu + gradient_penalty * (g**2).sum(-1).mean()
            w = jnp.exp(jax.lax.stop_gradient(adv) - jax.lax.stop_gradient(adv).max())
            w = w / w.mean()
            out = _mlp(p["pi"], obs)
            loc, log_std = jnp.split(out, 2, axis=-1)
            loc, log_std = jnp.clip(loc, -bound, bound), jnp.clip(log_std, -5.0, 2.0)
            u = jnp.clip(batch["action"], -clip, clip)
            pre = jnp.arctanh(u)
            normal = -0.5 * ((pre - loc) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
            log_prob = (normal - jnp.log1p(-(u**2))).sum(-1)
            loss_actor = -(w * log_prob).mean()
            return loss_nu + loss_lam + loss_actor

        def step(state, batch, key):
            params, opt_state = state
            key, sub = jax.random.split(key)
            value, grads = jax.value_and_grad(losses)(params, batch, sub)
            if not optimizer:
                return (params, opt_state), key, (value, grads)
            updates, opt_state = adam.update(grads, opt_state, params)
            return (optax.apply_updates(params, updates), opt_state), key, (value, None)

        self._step = jax.jit(step, donate_argnums=(0,))
        self._jax = jax

    def batch(self, torch_batch) -> dict:
        """The arrays of one of ``bench_losses.make_batch``'s batches, on JAX's device."""
        import jax.numpy as jnp

        u = torch_batch["unlabeled"]
        arrays = {
            "init": torch_batch["init", "observation"],
            "observation": u["observation"],
            "next_observation": u["next", "observation"],
            "action": u["action"],
            "terminated": u["next", "terminated"].float().reshape(-1),
            "log_ratio": u["log_ratio_performant"].reshape(-1),
            "support": u["safe_support"].reshape(-1),
        }
        return {k: jnp.asarray(v.cpu().numpy()) for k, v in arrays.items()}

    def __call__(self, batch: dict) -> None:
        self.state, self.key, (value, _) = self._step(self.state, batch, self.key)
        return value

    def compiled(self, batch: dict):
        """The jitted update as XLA compiled it for ``batch``'s shapes (its optimised module: ``.as_text()``)."""
        return self._step.lower(self.state, batch, self.key).compile()

    def flops(self, batch: dict) -> float:
        """XLA's count of the jitted update's floating-point operations (``cost_analysis``)."""
        analysis = self.compiled(batch).cost_analysis()
        if isinstance(analysis, list):  # older JAX: one dict per device
            analysis = analysis[0]
        return float(analysis["flops"])


def jax_rate(step: JaxStep, batches: list[dict], steps: int) -> float:
    """Updates per second of ``steps`` calls (waiting for the last result: XLA dispatches asynchronously)."""
    start = time.perf_counter()
    value = None
    for i in range(steps):
        value = step(batches[i % len(batches)])
    value.block_until_ready()
    return steps / (time.perf_counter() - start)
