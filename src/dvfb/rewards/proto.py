"""Proto: prototypical representation + kNN-to-queue novelty (docs/methods.md, "Proto").

Networks (the encoder is the identity on states):

* predictor ``Linear(s -> pred)`` and its EMA target (tau 0.05, updated at the end of every update);
* projector ``MLP(pred -> proj -> pred)``;
* prototypes, a bias-free ``Linear(pred -> num_protos)`` whose rows are re-normalised to unit
  length (in place, without gradient) before every use.

Loss (swapped prediction, one Adam over predictor, projector and prototypes): with
``u = normalize(projector(predictor(s)))`` and ``t = normalize(target_predictor(s'))``,
``log p = log_softmax(protos(u) / T)``, ``q = sinkhorn_knopp(protos(t) / T)``,
``loss = -mean_i sum_j q_ij log p_ij``.

Reward on ``s' = batch.next_obs`` (no gradient): ``z = normalize(predictor(s'))``; every prototype
draws one row of the batch from the softmax of its scores over the batch; those ``num_protos`` rows
of ``z`` enter a FIFO queue (initially zeros); ``r = ||z - (topk-th nearest queue entry)||``, no log,
no normalisation. The queue is a buffer and its pointer extra state, so a checkpoint resumes exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import call_network, make_target, mlp, orthogonal_init_, soft_update_
from dvfb.nets.members import MemberGenerators, member_mean, take_rows
from dvfb.rewards.base import IntrinsicReward, Runner
from dvfb.rewards.knn import nearest_distances


@dataclass
class ProtoConfig:
    """Proto's networks, queue and Sinkhorn settings (URLB ``proto`` defaults)."""

    pred_dim: int = param(128, "Output width of the predictor (and of the projector).", at_least=1)
    proj_dim: int = param(512, "Hidden width of the projector.", at_least=1)
    num_protos: int = param(512, "Number of prototypes; also the candidates enqueued per update.", at_least=1)
    temperature: float = param(0.1, "Softmax / Sinkhorn temperature T of the prototype scores.", above=0)
    topk: int = param(3, "The reward is the distance to the topk-th nearest queue entry.", at_least=1)
    queue_size: int = param(2048, "Length of the FIFO queue of candidates.", at_least=1)
    target_tau: float = param(0.05, "EMA rate of the target predictor.", above=0, at_most=1)
    sinkhorn_iters: int = param(3, "Sinkhorn-Knopp iterations of the target assignment.", at_least=1)
    lr: float = param(1e-4, "Adam learning rate of predictor, projector and prototypes.", above=0)


def sinkhorn_knopp(scores: torch.Tensor, iters: int = 3) -> torch.Tensor:
    """Soft equipartitioned assignment ``(N, P)`` of N samples to P prototypes from ``scores``
    (``(N, P)``, already divided by the temperature); each returned row sums to 1.

    As URLB: subtract the global maximum (so ``exp`` cannot overflow), exponentiate, transpose to
    ``(P, N)``, normalise the total to 1, then ``iters`` times scale the prototype rows to mass
    ``1/P`` and the sample columns to mass ``1/N``; finally every sample column is normalised to 1.
    A group's ``(M, N, P)`` scores give ``(M, N, P)``, each member shifted and normalised on its own.
    """
    if scores.dim() == 2:
        q = (scores - scores.max()).exp().T  # (P, N)
        q = q / q.sum()
    else:  # the "global" max and total are each member's own
        q = (scores - scores.amax(dim=(-2, -1), keepdim=True)).exp().mT  # (M, P, N)
        q = q / q.sum(dim=(-2, -1), keepdim=True)
    num_protos, n = q.shape[-2:]
    for _ in range(iters):
        q = q * ((1.0 / num_protos) / q.sum(dim=-1, keepdim=True))
        q = q * ((1.0 / n) / q.sum(dim=-2, keepdim=True))
    q = q / q.sum(dim=-2, keepdim=True)
    return q.mT


def sample_one_per_row(prob: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """One index per row of ``prob`` (``(P, N)``, rows summing to 1), drawn from that row: ``(P,)``;
    a group's ``(M, P, N)`` with :class:`~dvfb.nets.members.MemberGenerators` gives ``(M, P)``,
    member k's drawn from its own stream.

    This is exactly what ``torch.multinomial(prob, 1)`` computes on its one-sample path (the
    exponential race ``argmax(prob / E)``, ``E ~ Exp(1)`` from torch's generator, so the same draws
    under the same seed), without the validity check that some torch versions perform by reading
    a value back to the host on every call.
    """
    if isinstance(generator, MemberGenerators):
        race = torch.stack([torch.empty_like(p).exponential_(1.0, generator=g) for p, g in zip(prob, generator)])
    else:
        race = torch.empty_like(prob).exponential_(1.0, generator=generator)
    return (prob / race).argmax(dim=-1)


class ProtoReward(IntrinsicReward):
    """Prototypical representation learning with a kNN-to-queue reward."""

    def __init__(self, obs_dim: int, action_dim: int = 0, config: ProtoConfig | None = None):
        super().__init__()
        self.config = c = config if config is not None else ProtoConfig()
        if not 1 <= c.num_protos <= c.queue_size:
            raise ConfigError("proto needs 1 <= num_protos <= queue_size, "
                              f"got {c.num_protos} and {c.queue_size}")
        if not 1 <= c.topk <= c.queue_size:
            raise ConfigError(f"proto needs 1 <= topk <= queue_size, got {c.topk}")
        self.predictor = nn.Linear(obs_dim, c.pred_dim)
        self.projector = mlp(c.pred_dim, c.proj_dim, c.pred_dim)
        self.protos = nn.Linear(c.pred_dim, c.num_protos, bias=False)
        orthogonal_init_(self)
        # Created after the init so that it starts as an exact copy of the online predictor.
        self.predictor_target = make_target(self.predictor)
        # A buffer, so that it follows .to(device) and is saved in checkpoints.
        self.register_buffer("queue", torch.zeros(c.queue_size, c.pred_dim))
        # A Python int (no device tensor to read back when slicing); saved via get_extra_state.
        self.queue_ptr = 0

    # Checkpointed pointer ---------------------------------------------------------------------
    def get_extra_state(self) -> dict:
        return {"queue_ptr": self.queue_ptr}

    def set_extra_state(self, state: dict) -> None:
        self.queue_ptr = int(state["queue_ptr"])

    # Pieces -----------------------------------------------------------------------------------
    @torch.no_grad()
    def normalize_protos(self) -> None:
        """Rescale every prototype row to unit L2 norm, in place (the optimiser moves them off)."""
        self.protos.weight.copy_(F_nn.normalize(self.protos.weight, dim=-1))

    def loss(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """Swapped-prediction loss: online scores on ``s`` against Sinkhorn targets on ``s'``."""
        c = self.config
        online = F_nn.normalize(run(self.projector, run(self.predictor, batch.obs)), dim=-1)
        log_p = F_nn.log_softmax(run(self.protos, online) / c.temperature, dim=-1)
        with torch.no_grad():
            target = F_nn.normalize(run(self.predictor_target, batch.next_obs), dim=-1)
            q = sinkhorn_knopp(run(self.protos, target) / c.temperature, c.sinkhorn_iters)
        return -member_mean((q * log_p).sum(dim=-1), self.members)

    def enqueue(self, candidates: torch.Tensor) -> None:
        """Write ``candidates`` (``(num_protos, pred_dim)``) at the pointer, FIFO, wrapping around.
        A group's queue ``(M, queue_size, pred_dim)`` takes ``(M, num_protos, pred_dim)``; the
        members share the pointer (they enqueue in lockstep)."""
        size, count, ptr = self.queue.shape[-2], candidates.shape[-2], self.queue_ptr
        first = min(count, size - ptr)
        self.queue[..., ptr:ptr + first, :] = candidates[..., :first, :]
        if first < count:  # only when queue_size is not a multiple of num_protos
            self.queue[..., :count - first, :] = candidates[..., first:, :]
        self.queue_ptr = (ptr + count) % size

    # Interface ----------------------------------------------------------------------------------
    def update(self, batch: Batch, run: Runner = call_network) -> dict[str, torch.Tensor]:
        self.normalize_protos()
        loss = self.loss(batch, run)
        self.step(loss)
        # Only score() reads the online predictor afterwards, so updating the target here is the
        # same as URLB's update after the reward computation.
        soft_update_(self.predictor_target, self.predictor, self.config.target_tau)
        return {"proto_loss": loss.detach()}

    @torch.no_grad()
    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        """Distance of ``z(s')`` to its topk-th nearest queue entry, ``(N, 1)``. Not pure: it draws
        from torch's RNG and pushes ``num_protos`` candidates into the queue first."""
        self.normalize_protos()  # the update's optimiser step moved the prototypes
        z = F_nn.normalize(run(self.predictor, batch.next_obs), dim=-1)
        scores = run(self.protos, z).mT  # (num_protos, N)
        candidates = sample_one_per_row(F_nn.softmax(scores, dim=-1), self.generator)  # one batch row per prototype
        self.enqueue(take_rows(z, candidates))
        return nearest_distances(z, self.queue, self.config.topk)[..., -1:]
