"""The FB family's maps (docs/methods.md §4.2-§4.4): F, B, the skill values ``F.z``, the twin
critic ``Q(s, a, z)`` (also the DDPG core's, with ``out_dim`` for successor features) and the
implicit reward ``B Cov(B)^-1 z`` (§7.9, §9.4) that FB's auxiliary loss and dual-value fine-tuning read."""

from __future__ import annotations

import torch
from torch import nn

from dvfb.nets.geometry import project_to_sphere
from dvfb.nets.layers import TwinHead, full_precision, layernorm_tanh_layer, mlp, orthogonal_init_
from dvfb.nets.members import row_products
from dvfb.nets.policy import TwoStreamEncoder


class ForwardMap(nn.Module):
    """``F_k(s, a, z)``, k = 1..num_heads, on shared ``[s, a]`` and ``[s, z]`` streams (§4.2).

    Returns ``(K, N, d)``. The skill value is ``Q_M,k = F_k . z`` (:func:`skill_values`).
    """

    def __init__(self, obs_dim: int, action_dim: int, z_dim: int, hidden_dim: int,
                 feature_dim: int, num_heads: int = 2):
        super().__init__()
        self.encoder = TwoStreamEncoder(obs_dim + action_dim, obs_dim + z_dim, hidden_dim, feature_dim)
        self.heads = TwinHead(self.encoder.out_dim, hidden_dim, z_dim, num_heads)
        orthogonal_init_(self)

    def forward(self, obs: torch.Tensor, action: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        h = self.encoder(torch.cat([obs, action], dim=-1), torch.cat([obs, z], dim=-1))
        return self.heads(h)


def skill_values(forward_out: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """``Q_M,k = F_k . z`` for every head: ``(K, N, d), (N, d) -> (K, N)`` (a group: leading M)."""
    return (forward_out * z.unsqueeze(-3)).sum(-1)


class BackwardMap(nn.Module):
    """``B(x) = proj(MLP(x))`` with ``||B(x)|| = sqrt(d)`` (§4.3).

    ``input_dim`` is O in ``state`` mode and 2*O in ``transition`` / ``code_exact`` modes.
    """

    def __init__(self, input_dim: int, hidden_dim: int, z_dim: int):
        super().__init__()
        self.net = mlp(input_dim, hidden_dim, hidden_dim, z_dim, first_layer_lnt=True)
        orthogonal_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The projection is a reduction: float32 even under bf16 autocast.
        return project_to_sphere(full_precision(self.net(x)))


def offdiag_mean(matrix: torch.Tensor) -> torch.Tensor:
    """Mean over ``i != j`` of the last two (square) dimensions, without building a mask."""
    n = matrix.shape[-1]
    total = matrix.sum(dim=(-2, -1))
    diag = matrix.diagonal(dim1=-2, dim2=-1).sum(-1)
    return (total - diag) / (n * (n - 1))


def orthonormality_loss(features: torch.Tensor, members: int = 0) -> torch.Tensor:
    """``mean_{i!=j} G_ij^2 - 2 mean_i G_ii`` with ``G = features features^T`` (§7.10): the
    regulariser that pushes ``E[f f^T]`` towards the identity (B of FB, phi of the SF family); one
    loss per member for a group's ``(M, N, d)``."""
    gram = row_products(features, features, members)
    return offdiag_mean(gram.pow(2)) - 2 * gram.diagonal(dim1=-2, dim2=-1).mean(-1)


class TwinCritic(nn.Module):
    """``Q_k(s, a, z)``: a shared ``LNT([s, z, a] -> H)`` trunk and K heads ``H -> H -> 1`` (§4.4).

    Used for the exploration critic Q_P (pre-training), the task critic Q_F (fine-tuning) and the
    DDPG core. Returns ``(K, N, out_dim)``.
    """

    def __init__(self, obs_dim: int, action_dim: int, z_dim: int, hidden_dim: int, num_heads: int = 2,
                 out_dim: int = 1):
        super().__init__()
        self.trunk = layernorm_tanh_layer(obs_dim + z_dim + action_dim, hidden_dim)
        # out_dim > 1: successor features psi_k (APS), whose values are psi_k . w (the caller's).
        self.heads = TwinHead(hidden_dim, hidden_dim, out_dim, num_heads)
        orthogonal_init_(self)

    def forward(self, obs: torch.Tensor, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.heads(self.trunk(torch.cat([obs, z, action], dim=-1)))


def implicit_reward(backward: torch.Tensor, z: torch.Tensor, ridge: float = 0.0) -> torch.Tensor:
    """``r_i = B_i Cov^{-1} z_i`` with ``Cov = B^T B / N`` (§7.9, §9.4), by a linear solve.

    ``z`` is ``(N, d)`` (one z per row) or ``(d,)`` (one z for all rows). Returns ``(N,)``. A group's
    ``backward`` is ``(M, N, d)``, with ``z`` ``(M, N, d)`` or ``(M, d)``, and the result ``(M, N)``.
    """
    n, d = backward.shape[-2:]
    cov = backward.mT @ backward / n
    if ridge:
        cov = cov + ridge * torch.eye(d, device=backward.device, dtype=backward.dtype)
    per_row = z.dim() == backward.dim()
    rhs = z.mT if per_row else z.unsqueeze(-1)
    # solve_ex: no host sync on failure. An exactly singular Cov(B) gives non-finite rewards, which
    # stop the run with an error naming the step and --fb.cov-ridge when the metrics are read (D19).
    solution, _info = torch.linalg.solve_ex(cov, rhs)
    if per_row:
        return (backward * solution.mT).sum(-1)
    if backward.dim() == 2:
        return backward @ solution.squeeze(-1)
    # A group's one z per member: each member's own matrix-vector product, which rounds as its
    # separate run's does (a batched product does not).
    return torch.stack([member @ x.squeeze(-1) for member, x in zip(backward, solution)])
