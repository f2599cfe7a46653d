"""CeSD's representation, state prototypes and partitioned reward (docs/methods.md, "CeSD").

CeSD keeps CIC's contrastive module (:class:`~dvfb.rewards.contrastive.CICReward`: state encoder
g, transition predictor, skill projector and the NCE update, here with the 16-way one-hot skill as
the query) and adds P = skill_dim state prototypes, one per skill and per critic head:

* **prototypes** C, a bias-free ``Linear(P -> P)`` applied to ``normalize(g(.))``; its rows are
  re-normalised to unit length (in place, without gradient) before every use;
* **clustering** (:meth:`CeSDReward.assign`): every state ``s_{t+n}`` of the batch *draws* its
  cluster from ``softmax(C normalize(g(s_{t+n})) / T_p)``;
* **partitioned reward** (:func:`partitioned_apt_reward`): for every cluster with more than k
  members, the APT particle entropy of g(s_{t+n}) among the cluster's own states, plus the
  constraint bonus ``lambda_c / (1 + number of the cluster's states whose skill is not the
  cluster's index)``; states of smaller clusters get 0;
* **prototype loss** (:meth:`CeSDReward.prototype_loss`, swapped assignment as in Proto-RL):
  ``-mean_i sum_j q_ij log p_ij`` with ``log p = log_softmax(C normalize(g(s_t)) / T_p)`` and
  ``q = Sinkhorn(C normalize(g(s_{t+n})) / T_p)``; g is evaluated without gradient, only C learns.

:func:`dvfb.rewards.proto.sinkhorn_knopp` is CeSD's Sinkhorn: global-max shift, exponentiate,
normalise the total, then alternately scale prototype rows to mass 1/P and sample columns to mass
1/N, and a final column normalisation. The official code also replaces infinities by the largest
finite value (a host read); here that step cannot fire, since C's rows and the embeddings have
unit norm: the scores lie in ``[-1/T_p, 1/T_p]``, so every ``exp`` is at least ``e^{-2/T_p}``
(``e^{-20}`` at T_p = 0.1), far above float32's underflow.

The agent (:class:`dvfb.agents.cesd.CeSDAgent`) calls the pieces in CeSD's order: :meth:`update`
(NCE step), :meth:`score_and_assign` (clusters and reward), then, after its critic and actor
steps, :meth:`update_prototypes`. One Adam holds the encoders and C; each step only moves the
parameters its loss reaches.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.data import Batch
from dvfb.nets import RunningMeanStd, call_network, orthogonal_init_
from dvfb.nets.members import member_mean, member_sum, per_member
from dvfb.nets.skills import skill_index
from dvfb.rewards.base import Runner
from dvfb.rewards.contrastive import CICConfig, CICReward
from dvfb.rewards.knn import gather_rows
from dvfb.rewards.proto import sample_one_per_row, sinkhorn_knopp


def masked_nearest_distances(rep: torch.Tensor, allowed: torch.Tensor, k: int) -> torch.Tensor:
    """For every row of ``rep`` (``(N, d)``), the Euclidean distances to its ``k`` nearest rows
    among those ``allowed`` (``(N, N)`` bool, row i's candidates), ``(N, k)``.

    Candidates are chosen on squared distances in matmul form with the forbidden pairs at +inf
    (one ``N x N`` matrix, no ``N x N x d`` tensor), and the chosen pairs are recomputed as norms of
    differences, for exact zeros and full precision (as :func:`dvfb.rewards.knn.nearest_distances`).
    A row with fewer than ``k`` allowed candidates also gets forbidden ones (finite distances);
    the caller discards such rows.
    """
    centred = rep - rep.mean(dim=-2, keepdim=True)  # translation invariant; less cancellation
    sq_norm = centred.pow(2).sum(-1)
    if rep.dim() == 2:
        sq_dist = torch.addmm(sq_norm.unsqueeze(0), centred, centred.T, alpha=-2.0).add_(sq_norm.unsqueeze(1))
    else:  # a group (M, N, d): one product per member
        sq_dist = torch.baddbmm(sq_norm.unsqueeze(-2), centred, centred.mT, alpha=-2.0).add_(sq_norm.unsqueeze(-1))
    sq_dist = sq_dist.masked_fill(~allowed, float("inf"))
    index = sq_dist.topk(k, dim=-1, largest=False, sorted=False).indices  # (N, k)
    return (rep.unsqueeze(-2) - gather_rows(rep, index)).norm(dim=-1)


def partitioned_apt_reward(rep: torch.Tensor, cluster: torch.Tensor, skill: torch.Tensor, num_clusters: int,
                           k: int, clip: float, constraint_factor: float, stats: RunningMeanStd | None = None
                           ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """CeSD's reward ``(N, 1)`` of the states with representations ``rep`` (``(N, d)``), cluster
    indices ``cluster`` (``(N,)``) and skill indices ``skill`` (``(N,)``).

    For every cluster i with more than ``k`` members, each of its states gets
    ``log(1 + mean_k max(d / S_i - clip, 0)) + constraint_factor / (1 + B_i)``: the mean of its k
    nearest distances (itself included, at 0) *within the cluster*, divided by the running
    variance S_i, and ``B_i`` the number of the cluster's states whose skill is not i. States of
    clusters with at most ``k`` members get 0.

    ``stats`` (the APT tracker, docs/methods.md "kNN particle entropy") is folded in cluster by cluster in index order, each with its
    ``size * k`` distances, and cluster i is divided by the variance right after its own fold, as
    the official per-cluster loop does; here all folds come from one closed form (Chan's
    combination: the tracker is a running mean and a pseudo sum of squares ``S * n``, and folding
    batches one after the other equals combining all groups at once). ``stats=None``: no
    normalisation. No host sync: every cluster is computed on the whole batch with the other
    clusters' states masked out, and small clusters are zeroed with ``torch.where``.

    Also returns detached metrics: the number of scored clusters and the fraction of states whose
    cluster is not their skill.
    """
    members = rep.shape[0] if rep.dim() == 3 else 0  # a group: (M, N, d), (M, N), (M, N), stats (M,)
    n = rep.shape[-2]
    k_eff = min(k, n)
    labels = torch.arange(num_clusters, device=rep.device)
    member = cluster.unsqueeze(-1) == labels  # (N, P)
    size = member.sum(dim=-2)  # (P,)
    scored = size > k  # (P,): clusters that are rewarded
    off_skill = skill != cluster  # (N,)
    off_count = (member & off_skill.unsqueeze(-1)).sum(dim=-2)  # B_i, (P,)

    dist = masked_nearest_distances(rep, cluster.unsqueeze(-1) == cluster.unsqueeze(-2), k_eff)  # (N, k)

    if stats is not None:
        # Per-cluster count, mean and unbiased variance of the cluster's N_i * k distances (two passes).
        d64, member64 = dist.double(), member.double()
        count = torch.where(scored, size.double() * k_eff, 0.0)
        mean = torch.where(scored, _cluster_sums(member64, d64.sum(dim=-1)) / count.clamp_min(1.0), 0.0)
        sq_dev = (d64 - mean.gather(-1, cluster).unsqueeze(-1)).pow(2).sum(dim=-1)
        var = torch.where(scored, _cluster_sums(member64, sq_dev) / (count - 1.0).clamp_min(1.0), 0.0)
        # The tracker after the fold of clusters 0..i, for every i: prior (M0, S0, n0) plus the groups.
        m0, s0, n0 = (per_member(x, count) for x in (stats.mean, stats.var, stats.count))
        total = n0 + count.cumsum(-1)
        running_mean = (n0 * m0 + (count * mean).cumsum(-1)) / total
        upto = torch.ones(num_clusters, num_clusters, dtype=torch.bool, device=rep.device).tril()  # [i, j]: j <= i
        between = torch.where(upto, count.unsqueeze(-2) * (mean.unsqueeze(-2) - running_mean.unsqueeze(-1)).pow(2),
                              0.0).sum(-1)
        running_var = (s0 * n0 + (count * var).cumsum(-1) + n0 * (m0 - running_mean).pow(2) + between) / total
        stats.mean.copy_(running_mean[..., -1])
        stats.var.copy_(running_var[..., -1])
        stats.count.copy_(total[..., -1])
        dist = dist / running_var.to(dist.dtype).gather(-1, cluster).unsqueeze(-1)
    entropy = torch.log1p((dist - clip).clamp_min(0.0).mean(dim=-1))
    bonus = constraint_factor / (1.0 + off_count.to(rep.dtype))
    reward = torch.where(scored.gather(-1, cluster), entropy + bonus.gather(-1, cluster), torch.zeros_like(entropy))
    metrics = {"scored_clusters": member_sum(scored, members).to(rep.dtype),
               "off_cluster_fraction": member_mean(off_skill.to(rep.dtype), members)}
    return reward.unsqueeze(-1), metrics


def _cluster_sums(member: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``sum_i member_ip values_i`` per cluster p: ``(N, P), (N,) -> (P,)``, or per member
    ``(M, N, P), (M, N) -> (M, P)``."""
    if member.dim() == 2:
        return member.T @ values
    return (member.mT @ values.unsqueeze(-1)).squeeze(-1)


class CeSDReward(CICReward):
    """CIC's module plus CeSD's prototypes, clustering and partitioned reward (see the module
    docstring). ``config`` is a :class:`~dvfb.rewards.contrastive.CICConfig` (CeSD's config is
    one): encoder width, NCE temperature, APT k / clip / running variance, learning rate."""

    def __init__(self, obs_dim: int, skill_dim: int, config: CICConfig, proto_temperature: float = 0.1,
                 sinkhorn_iters: int = 6, constraint_factor: float = 1.0):
        super().__init__(obs_dim, skill_dim, config)
        self.num_clusters = skill_dim
        self.proto_temperature, self.sinkhorn_iters = proto_temperature, sinkhorn_iters
        self.constraint_factor = constraint_factor
        self.protos = nn.Linear(skill_dim, skill_dim, bias=False)
        orthogonal_init_(self.protos)

    # Prototypes --------------------------------------------------------------------------------
    @torch.no_grad()
    def normalize_protos(self) -> None:
        """Rescale every prototype row to unit L2 norm, in place (the optimiser moves them off)."""
        self.protos.weight.copy_(F_nn.normalize(self.protos.weight, dim=-1))

    def cluster_scores(self, rep: torch.Tensor, run: Runner = call_network) -> torch.Tensor:
        """``C normalize(rep) / T_p``, ``(N, P)``; call :meth:`normalize_protos` first."""
        return run(self.protos, F_nn.normalize(rep, dim=-1)) / self.proto_temperature

    @torch.no_grad()
    def assign(self, rep: torch.Tensor, run: Runner = call_network) -> torch.Tensor:
        """One cluster per state, ``(N,)``, drawn from ``softmax(C normalize(rep) / T_p)`` with
        torch's random stream (no host sync)."""
        self.normalize_protos()
        return sample_one_per_row(F_nn.softmax(self.cluster_scores(rep, run), dim=-1), self.generator)

    def prototype_loss(self, batch: Batch, run: Runner = call_network,
                       next_rep: torch.Tensor | None = None) -> torch.Tensor:
        """Swapped assignment: online scores of ``s_t`` against Sinkhorn targets of ``s_{t+n}``.
        g is evaluated without gradient (only C learns); ``next_rep`` may pass ``g(s_{t+n})``
        when it is already at hand with the current encoder."""
        self.normalize_protos()
        with torch.no_grad():
            rep = run(self.encoders.state_net, batch.obs)
            if next_rep is None:
                next_rep = run(self.encoders.state_net, batch.next_obs)
            target = sinkhorn_knopp(self.cluster_scores(next_rep, run), self.sinkhorn_iters)
        log_p = F_nn.log_softmax(self.cluster_scores(rep, run), dim=-1)
        return -member_mean((target * log_p).sum(dim=-1), self.members)

    def update_prototypes(self, batch: Batch, run: Runner = call_network,
                          next_rep: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        loss = self.prototype_loss(batch, run, next_rep)
        self.step(loss)
        return {"proto_loss": loss.detach()}

    # Reward ------------------------------------------------------------------------------------
    @torch.no_grad()
    def score_and_assign(self, batch: Batch, run: Runner = call_network
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Cluster the batch's ``s_{t+n}`` and reward it: ``(reward (N, 1), cluster (N,),
        g(s_{t+n}) (N, c), metrics)``. Not pure: it draws from torch's random stream and updates
        the running variance."""
        next_rep = run(self.encoders.state_net, batch.next_obs)
        cluster = self.assign(next_rep, run)
        c = self.entropy.config
        reward, metrics = partitioned_apt_reward(next_rep, cluster, skill_index(batch.z), self.num_clusters, c.k,
                                                 c.clip, self.constraint_factor, self.entropy.stats)
        return reward, cluster, next_rep, metrics

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        return self.score_and_assign(batch, run)[0]
