"""BeCL's behaviour-contrastive module (docs/methods.md, "BeCL").

A state network ``f(s) = project_head(embed(s))`` maps the n-step successor ``s_{t+n}`` of every
row to a ``d``-wide feature (``d`` = the number of skills); the module learns it with a contrastive
loss that has one positive per anchor, picked among the rows of the same skill
(:func:`becl_contrastive_loss`), and scores each row by ``exp(-loss_i)``, about the softmax
probability of its positive.

* ``embed``: ``O -> H -> H -> d``; ``project_head``: ``d -> H -> d`` (ReLU, orthogonal init).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import call_network, mlp, orthogonal_init_
from dvfb.nets.members import member_mean
from dvfb.nets.skills import skill_index
from dvfb.rewards.base import IntrinsicReward, Runner


@dataclass
class BeCLConfig:
    """BeCL's skill, contrastive network and update schedule (official BeCL defaults)."""

    skill_dim: int = param(16, "Number of discrete (one-hot) skills; also the width of f(s).", at_least=1)
    skill_every: int = param(50, "Resampling period of the rollout skill, in environment steps.", at_least=1)
    hidden_dim: int = param(1024, "Hidden width of the embedding and the projection head.", at_least=1)
    contrastive_update_rate: int = param(3, "Contrastive steps per agent update, each on a fresh batch; the "
                                            "last batch also feeds the reward and the DDPG step.", at_least=1)
    temperature: float = param(0.5, "Temperature T of the contrastive loss.", above=0)
    lr: float = param(1e-4, "Adam learning rate of the contrastive network.", above=0)


def becl_contrastive_loss(features: torch.Tensor, labels: torch.Tensor, temperature: float) -> torch.Tensor:
    """Per-row loss ``(N, 1)`` of BeCL's one-positive contrastive objective (a group's ``(M, N, d)``
    features and ``(M, N)`` labels: ``(M, N, 1)``, each member within its own rows).

    With ``u = normalize(features)`` and ``S_ij = u_i . u_j / T`` over ``j != i``: each row's
    maximum is subtracted and ``E = exp(S - max)``; the positive of anchor ``i`` is the *first*
    other row with the same label (none: index 0 of the row without its diagonal, i.e. row 1 for
    anchor 0 and row 0 otherwise); ``neg_i = sum_{j != i} E_ij`` (the positive and every same-skill
    row included); ``loss_i = -log(pos_i / (neg_i + 1e-6) + 1e-6)``.

    Vectorised without reshaping away the diagonal: its entries are set to ``-inf``, so they drop
    out of the row maximum and contribute ``exp(-inf) = 0`` to the sums (no boolean indexing, hence
    no host sync). Indices stay those of the full row, which is why the fallback is translated.
    """
    n = features.shape[-2]
    u = F_nn.normalize(features, dim=-1)
    eye = torch.eye(n, dtype=torch.bool, device=features.device)
    sim = (u @ u.mT / temperature).masked_fill(eye, float("-inf"))
    sim = sim - sim.amax(dim=-1, keepdim=True)
    exp_sim = sim.exp()
    idx = torch.arange(n, device=features.device)
    same = (labels.unsqueeze(-2) == labels.unsqueeze(-1)) & ~eye
    # First same-skill index per row (n where there is none), then the reduced row's index 0.
    first = torch.where(same, idx.unsqueeze(0), n).amin(dim=-1)
    fallback = (idx == 0).long()
    positive_idx = torch.where(first < n, first, fallback)
    positive = exp_sim.gather(-1, positive_idx.unsqueeze(-1))
    negative = exp_sim.sum(dim=-1, keepdim=True)
    return -torch.log(positive / (negative + 1e-6) + 1e-6)


class BeCLNetwork(nn.Module):
    """``f(s) = project_head(embed(s))``."""

    def __init__(self, obs_dim: int, skill_dim: int, hidden_dim: int):
        super().__init__()
        self.embed = mlp(obs_dim, hidden_dim, hidden_dim, skill_dim)
        self.project_head = mlp(skill_dim, hidden_dim, skill_dim)
        orthogonal_init_(self)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.project_head(self.embed(obs))


class BeCLReward(IntrinsicReward):
    """One contrastive step per :meth:`update` on ``f(batch.next_obs)`` with the skills of
    ``batch.z``; :meth:`score` is ``exp(-loss_i)`` with the current network. The agent runs
    several updates on fresh batches before it scores the last one (docs/methods.md, "BeCL")."""

    def __init__(self, obs_dim: int, skill_dim: int, config: BeCLConfig):
        super().__init__()
        self.config = config
        self.net = BeCLNetwork(obs_dim, skill_dim, config.hidden_dim)

    def losses(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """Per-row contrastive loss ``(N, 1)`` of the batch's successors ``s_{t+n}``."""
        return becl_contrastive_loss(run(self.net, batch.next_obs), skill_index(batch.z), self.config.temperature)

    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        loss = member_mean(self.losses(batch, run), self.members)
        self.step(loss)
        return {"contrastive_loss": loss.detach()}

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        return torch.exp(-self.losses(batch, run))
