"""The successor-feature family's feature learners phi(s) (docs/methods.md, "Successor features").

Each learner owns the feature network ``phi`` -- ``LNT(s -> Hb) -> ReLU(Hb) -> d`` projected to
the sphere of radius sqrt(d), the same network as FB's B -- and the auxiliary networks of its
objective, and computes that objective from a batch. The SF agent trains them with their own
optimiser; no gradient of the successor-feature TD loss reaches them.

The four learners of the paper's Table 1, by registered name:

* ``lap`` -- Laplacian eigenfunctions: ``mean (phi(s) - phi(s'))^2 + L_orth(phi(s))``;
* ``lra_p`` -- low-rank approximation of the transition probabilities with ``mu(s, a)``:
  ``-2 mean_i P_ii + mean_{i!=j} P_ij^2 + L_orth(phi(s'))``, ``P = mu(s, a) phi(s')^T``;
* ``lra_sr`` -- low-rank approximation of the successor representation, TD form, with ``mu(s)``
  and EMA targets: ``-2 mean_i SR_ii + mean_{i!=j} (SR_ij - gamma SRbar_ij)^2 + L_orth(phi(s))``;
* ``cl`` -- contrastive (SimCLR-like, temperature 1) between ``phi(s)`` and ``mu(s')``, the
  positive excluded from the normaliser.

A learner is chosen by ``--sf.features NAME``; :data:`FEATURE_LEARNERS` maps names to classes, and
a new learner is a class with ``name`` and :meth:`FeatureLearner.loss` added with
:func:`register_feature_learner`.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import nn

from dvfb.nets.layers import make_target, mlp, orthogonal_init_
from dvfb.nets.maps import BackwardMap, offdiag_mean, orthonormality_loss
from dvfb.nets.members import member_mean, row_products


class FeatureLearner(nn.Module):
    """``phi`` and its objective. ``loss(obs, action, next_obs, next_features)`` returns the scalar
    loss and detached metrics (a group's: ``(M,)``, one per member); ``next_features = phi(s')``
    is passed in with its graph, because the agent computes it once for the TD target, the
    training skills and (here) the loss."""

    name: ClassVar[str] = ""
    members: int = 0  # a group's member count (dvfb.nets.members): losses and metrics are then (M,)

    def __init__(self, obs_dim: int, action_dim: int, z_dim: int, hidden_dim: int, tau: float, discount: float):
        super().__init__()
        self.phi = BackwardMap(obs_dim, hidden_dim, z_dim)
        self.tau, self.discount = tau, discount

    def loss(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor,
             next_features: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        raise NotImplementedError


FEATURE_LEARNERS: dict[str, type[FeatureLearner]] = {}


def register_feature_learner(cls: type[FeatureLearner]) -> type[FeatureLearner]:
    FEATURE_LEARNERS[cls.name] = cls
    return cls


def _auxiliary_mlp(in_dim: int, hidden_dim: int, z_dim: int) -> nn.Sequential:
    """``LNT(in -> Hb) -> ReLU(Hb) -> d`` without the sphere projection (the mu of LRA-P / LRA-SR)."""
    return orthogonal_init_(mlp(in_dim, hidden_dim, hidden_dim, z_dim, first_layer_lnt=True))


@register_feature_learner
class LaplacianFeatures(FeatureLearner):
    """SF-Lap: the graph-Laplacian drawing objective with the orthonormality constraint."""

    name = "lap"

    def loss(self, obs, action, next_obs, next_features):
        features = self.phi(obs)
        smoothness = member_mean((features - next_features).pow(2), self.members)
        ortho = orthonormality_loss(features, self.members)
        return smoothness + ortho, {"feature_smoothness": smoothness.detach(), "feature_ortho": ortho.detach()}


@register_feature_learner
class TransitionLowRankFeatures(FeatureLearner):
    """SF-LRA-P: ``P(s'|s, a) ~ mu(s, a) . phi(s')`` fitted by the low-rank (measure) loss."""

    name = "lra_p"

    def __init__(self, obs_dim, action_dim, z_dim, hidden_dim, tau, discount):
        super().__init__(obs_dim, action_dim, z_dim, hidden_dim, tau, discount)
        self.mu = _auxiliary_mlp(obs_dim + action_dim, hidden_dim, z_dim)

    def loss(self, obs, action, next_obs, next_features):
        p = row_products(self.mu(torch.cat([obs, action], dim=-1)), next_features, self.members)  # (N, N)
        diag = p.diagonal(dim1=-2, dim2=-1).mean(-1)
        offdiag = offdiag_mean(p.pow(2))
        ortho = orthonormality_loss(next_features, self.members)
        return -2 * diag + offdiag + ortho, {"feature_diag": diag.detach(), "feature_offdiag": offdiag.detach(),
                                             "feature_ortho": ortho.detach()}


@register_feature_learner
class SuccessorLowRankFeatures(FeatureLearner):
    """SF-LRA-SR: ``SR(s, s') ~ phi(s) . mu(s')`` fitted by a TD version of the low-rank loss.

    The targets ``phibar``, ``mubar`` follow their networks by EMA *inside* every loss evaluation,
    before the targets are read (as the sources do), not with the agent's other targets.
    """

    name = "lra_sr"

    def __init__(self, obs_dim, action_dim, z_dim, hidden_dim, tau, discount):
        super().__init__(obs_dim, action_dim, z_dim, hidden_dim, tau, discount)
        self.mu = _auxiliary_mlp(obs_dim, hidden_dim, z_dim)
        self.phi_target = make_target(self.phi)
        self.mu_target = make_target(self.mu)

    def loss(self, obs, action, next_obs, next_features):
        with torch.no_grad():
            torch._foreach_lerp_([*self.phi_target.parameters(), *self.mu_target.parameters()],
                                 [*self.phi.parameters(), *self.mu.parameters()], self.tau)
            next_mu_target = self.mu_target(next_obs)
            target_sr = self.phi_target(next_obs) @ next_mu_target.mT
        features = self.phi(obs)
        sr = row_products(features, self.mu(next_obs), self.members)  # (N, N)
        diag = sr.diagonal(dim1=-2, dim2=-1).mean(-1)
        td = offdiag_mean((sr - self.discount * target_sr).pow(2))
        ortho = orthonormality_loss(features, self.members)
        return -2 * diag + td + ortho, {"feature_diag": diag.detach(), "feature_td": td.detach(),
                                        "feature_ortho": ortho.detach()}


@register_feature_learner
class ContrastiveFeatures(FeatureLearner):
    """SF-CL: InfoNCE between ``phi(s)`` and ``mu(s')`` (cosine similarity, temperature 1), the
    positive pair excluded from the log-sum-exp; ``mu`` is built like ``phi``."""

    name = "cl"

    def __init__(self, obs_dim, action_dim, z_dim, hidden_dim, tau, discount):
        super().__init__(obs_dim, action_dim, z_dim, hidden_dim, tau, discount)
        self.mu = BackwardMap(obs_dim, hidden_dim, z_dim)

    def loss(self, obs, action, next_obs, next_features):
        query = nn.functional.normalize(self.phi(obs), dim=-1)
        key = nn.functional.normalize(self.mu(next_obs), dim=-1)
        logits = row_products(query, key, self.members)  # (N, N)
        positive = logits.diagonal(dim1=-2, dim2=-1)
        eye = torch.eye(logits.shape[-1], dtype=torch.bool, device=logits.device)
        negatives = logits.masked_fill(eye, float("-inf")).logsumexp(-1)
        loss = member_mean(negatives - positive, self.members)
        return loss, {"feature_positive": member_mean(positive.detach(), self.members)}
