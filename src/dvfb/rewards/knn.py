"""Particle-based (kNN) entropy rewards (docs/methods.md, "Rewards: kNN particle entropy").

One estimator, parametrised, covers both variants the baselines use:

* **PBE-URLB** (APS, ICM-APT): ``normaliser="mean"`` when the running statistics are on, else
  ``"none"``;
* **APT-CIC** (CIC, CeSD, ComSD, DVFB(CIC)): ``average=True, k=16, clip=5e-4, normaliser="var"``
  (:meth:`KNNConfig.apt_cic`).

For every row ``i`` the k smallest Euclidean distances ``||h_i - h_j||`` over the target set (by
default the batch itself, so the row's own distance 0 is one of them) are kept; optionally divided
by the running mean or the running variance of those distances; reduced by ``max(x - clip, 0)``;
averaged over the k neighbours (``average``) or reduced to the k-th one; the reward is
``log(1 + value)``.

:func:`nearest_distances` is the shared search (also used by Proto's queue reward): it never builds
an ``N x M x d`` difference tensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.nets import RunningMeanStd
from dvfb.nets.members import per_member

NORMALISERS = ("none", "mean", "var")


@dataclass
class KNNConfig:
    """Settings of :func:`particle_entropy`. The defaults are ICM-APT's (PBE-URLB without rms)."""

    k: int = param(12, "Number of nearest neighbours (the row itself, at distance 0, is one of them).")
    average: bool = param(True, "Average over the k nearest distances; false keeps only the k-th.")
    clip: float = param(0.0, "Subtract this from every (normalised) distance and floor at 0; "
                             "a negative value disables the clip (as URLB).")
    normaliser: str = param("none", "Divide the distances by the running mean (PBE-URLB with rms), "
                                    "the running variance (APT-CIC) or nothing.", NORMALISERS)

    @classmethod
    def apt_cic(cls) -> KNNConfig:
        """The CIC-family estimator: k = 16, average, clip 5e-4, divided by the running variance."""
        return cls(k=16, average=True, clip=5e-4, normaliser="var")


def nearest_distances(source: torch.Tensor, target: torch.Tensor, k: int) -> torch.Tensor:
    """The k smallest Euclidean distances from every row of ``source`` to the rows of ``target``,
    ascending, ``(N, k)`` (``k`` is capped at ``M``, the number of targets). A group's
    ``(G, N, d)`` against ``(G, M, d)`` gives ``(G, N, k)``, each member against its own targets.

    The candidates are chosen on squared distances in the matmul form
    ``|s|^2 + |t|^2 - 2 s.t`` (an ``N x M`` matrix, no ``N x M x d`` tensor); only the chosen
    ``N x k`` pairs are then recomputed as norms of differences. Why: the matmul form loses about
    ``eps * |x|^2`` to cancellation, so a point's distance to itself (or to a duplicate) would come
    out near ``sqrt(eps) * |x|`` instead of exactly 0; the recomputation gives exact zeros and
    full-precision values at ``N * k * d`` cost.
    """
    k = min(k, target.shape[-2])
    # Distances are translation invariant; centring shrinks |x|^2 and with it the cancellation.
    centre = target.mean(dim=-2, keepdim=True)
    s, t = source - centre, target - centre
    if target.dim() == 2:
        sq_dist = torch.addmm(t.pow(2).sum(-1).unsqueeze(0), s, t.T, alpha=-2.0)
    else:
        sq_dist = torch.baddbmm(t.pow(2).sum(-1).unsqueeze(-2), s, t.mT, alpha=-2.0)
    sq_dist.add_(s.pow(2).sum(-1, keepdim=True))
    index = sq_dist.topk(k, dim=-1, largest=False, sorted=False).indices  # (N, k)
    exact = (source.unsqueeze(-2) - gather_rows(target, index)).norm(dim=-1)  # (N, k, d) -> (N, k)
    # Re-sort on the exact values so that the last column is the k-th nearest neighbour.
    return exact.sort(dim=-1).values


def gather_rows(target: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``target[index]`` along the row axis for any index shape: ``(M, d)[(N, k)] -> (N, k, d)``,
    or per member ``(G, M, d)[(G, N, k)] -> (G, N, k, d)``."""
    if target.dim() == 2:
        return target[index]
    members = torch.arange(target.shape[0], device=index.device).reshape(-1, *([1] * (index.dim() - 1)))
    return target[members, index]


def particle_entropy(rep: torch.Tensor, k: int, average: bool, clip: float, normaliser: str,
                     stats: RunningMeanStd | None = None, *, target: torch.Tensor | None = None
                     ) -> torch.Tensor:
    """Particle-based entropy reward ``log(1 + value)`` of every row of ``rep``, ``(N, 1)``.

    ``target`` defaults to ``rep`` (the batch against itself, self included). ``normaliser``:
    ``"none"``, ``"mean"`` (divide by the running mean ``M``) or ``"var"`` (divide by the running
    variance ``S``); ``stats`` is updated first with every kept distance (``N * k`` of them with
    ``average``, the ``N`` k-th ones otherwise), then its new value divides them, as URLB and CIC
    do. Call it without gradient.
    """
    if normaliser not in NORMALISERS:
        raise ConfigError(f"normaliser must be one of {NORMALISERS}, got {normaliser!r}")
    if normaliser != "none" and stats is None:
        raise ConfigError(f"normaliser {normaliser!r} needs running statistics (stats=None given)")
    dist = nearest_distances(rep, rep if target is None else target, k)  # (N, k), ascending
    if not average:
        dist = dist[..., -1:]
    if normaliser != "none":
        mean, var = stats.update(dist)  # () or a group's (G,)
        dist = dist / per_member(mean if normaliser == "mean" else var, dist).to(dist.dtype)
    if clip >= 0.0:  # URLB skips the clip for a negative value
        dist = (dist - clip).clamp_min(0.0)
    return torch.log1p(dist.mean(dim=-1, keepdim=True))


class ParticleEntropy(nn.Module):
    """:func:`particle_entropy` with its settings and, when normalising, its own running statistics
    (a submodule, so they move with the owner and are saved in its checkpoints)."""

    def __init__(self, config: KNNConfig | None = None):
        super().__init__()
        self.config = config if config is not None else KNNConfig()
        if self.config.normaliser not in NORMALISERS:
            raise ConfigError(f"normaliser must be one of {NORMALISERS}, got {self.config.normaliser!r}")
        if self.config.k < 1:
            raise ConfigError(f"k must be at least 1, got {self.config.k}")
        self.stats = RunningMeanStd() if self.config.normaliser != "none" else None

    @torch.no_grad()
    def forward(self, rep: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
        c = self.config
        return particle_entropy(rep, c.k, c.average, c.clip, c.normaliser, self.stats, target=target)
