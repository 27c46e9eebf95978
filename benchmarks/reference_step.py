"""The SpoilDICE + weighted-BC update written in plain PyTorch, the base of ``make bench``'s ratios: no
tensordict, no LossModule, the same networks (copied from the library's step), loss and nu gradient penalty
(Table J's coefficient 10 on the unlabeled points, the initial-unlabeled and the s-s' interpolations)."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torch import nn


class ReferenceStep:
    """The same update in plain PyTorch: no tensordict, no LossModule; shares the library step's weights."""

    def __init__(self, library, lr: float = 3e-5) -> None:
        """``library``: a ``bench_losses.LibraryStep``, whose networks and multiplier are copied."""
        self.nu = library.dice.get_stateful_net("nu_network", copy=True).module
        actor = library.bc.get_stateful_net("actor_network", copy=True)
        self.policy_net = actor.module[0].module  # MLP + NormalParams
        self.dist_kwargs = {"low": -1.0, "high": 1.0}
        probe = torch.zeros(1, library.obs_dim, device=library.dice.lagrange.device)
        self.dist_class = type(actor.get_dist(TensorDict({"observation": probe}, [1])))
        self.lagrange = nn.Parameter(library.dice.lagrange.detach().clone())
        self.optims = [
            torch.optim.Adam(self.nu.parameters(), lr=lr),
            torch.optim.Adam([self.lagrange], lr=lr),
            torch.optim.Adam(self.policy_net.parameters(), lr=lr),
        ]

    def losses(self, batch: TensorDict, gamma: float = 0.99, gp: float = 10.0):
        obs, nxt = batch["unlabeled", "observation"], batch["unlabeled", "next", "observation"]
        s0 = batch["init", "observation"]
        n0, n = s0.shape[0], obs.shape[0]
        v0, v, v_next = self.nu(torch.cat([s0, obs, nxt])).squeeze(-1).split([n0, n, n])
        not_term = 1.0 - batch["unlabeled", "next", "terminated"].float().squeeze(-1)
        support = batch["unlabeled", "safe_support"].squeeze(-1)
        base = batch["unlabeled", "log_ratio_performant"].squeeze(-1) + gamma * v_next * not_term - v
        adv_nu = base + self.lagrange.detach() * support
        adv_lam = adv_nu.detach() + (self.lagrange - self.lagrange.detach()) * support
        lme = lambda x: torch.logsumexp(x, 0) - torch.log(torch.tensor(float(x.numel()), device=x.device))  # noqa: E731
        loss_nu = (1 - gamma) * v0.mean() + lme(adv_nu) - self.lagrange.detach()
        loss_lam = (1 - gamma) * v0.detach().mean() + lme(adv_lam) - self.lagrange
        # nu gradient penalty on unlabeled, init-unlabeled and s-s' interpolations
        a1, a2 = torch.rand(n0, 1, device=obs.device), torch.rand(n, 1, device=obs.device)
        pts = torch.cat([obs, a1 * s0 + (1 - a1) * obs[:n0], a2 * obs + (1 - a2) * nxt]).requires_grad_(True)
        (g,) = torch.autograd.grad(self.nu(pts).sum(), pts, create_graph=True)
        loss_nu = loss_nu + gp * g.norm(dim=-1).pow(2).mean()
        w = torch.exp(adv_nu.detach() - adv_nu.detach().max())
        w = w / w.mean()
        loc, scale = self.policy_net(obs)
        dist = self.dist_class(loc, scale, **self.dist_kwargs)
        loss_actor = -(w * dist.log_prob(batch["unlabeled", "action"])).mean()
        return loss_nu, loss_lam, loss_actor

    def __call__(self, batch: TensorDict) -> None:
        for optim in self.optims:
            optim.zero_grad(set_to_none=True)
        sum(self.losses(batch)).backward()
        for optim in self.optims:
            optim.step()
