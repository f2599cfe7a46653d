"""Conservative FB (Jeen et al., NeurIPS 2024): VC-FB and MC-FB, FB with a CQL-style penalty for
offline data (docs/methods.md, "Conservative FB").

FB's update is unchanged; its FB step adds ``alpha * P`` with one of two penalties that push down
the values of actions the data do not support, relative to the dataset's actions:

* ``value`` (VC-FB): ``P = sum_k [ mean_i LSE_j Q_k(x_ij, a_ij, z_i) - mean_i Q_k(s_i, a_i, z_i) ]``
  with ``Q_k = F_k . z``;
* ``measure`` (MC-FB): the same on every successor measure ``M_k = F_k . B(s'_l)`` of the batch:
  ``P = sum_k [ mean_{i,l} LSE_j M_k(x_ij, a_ij, z_i; s'_l) - mean_{i,l} M_k(s_i, a_i, z_i; s'_l) ]``
  (B keeps its gradient here, so the penalty also shapes B).

The ``j`` index runs over ``samples`` actions per row (12 by default, as in the authors' code):
half uniform in the action box at ``s_i``, and the rest split equally between policy samples at
``s_i``, policy samples at ``s'_i`` (evaluated at ``s'_i``) and copies of the dataset action --
without density corrections, at temperature 1, with the training z of the row. ``alpha`` is tuned
by dual ascent on ``log alpha`` (starting at ``alpha = 1``) so that ``P`` settles at ``target``
(50); with ``lagrange = false`` it is the constant ``alpha``.

The penalty is a component of FB's learner (:class:`ConservativePenalty`); VC-FB and MC-FB are two
registered methods (``vcfb``, ``mcfb``), two-line subclasses of :class:`ConservativeFBAgent` (FB's
learner with its ``conservative`` section) that fix the penalty.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dvfb.agents.fb import FB_SMALL, FBAgent, FBComponent, FBConfig, FBStep, fb_finetune_label
from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.nets import adam, skill_values, training_action
from dvfb.nets.execution import PerfConfig
from dvfb.nets.members import minimise, rand, row_products, with_head_axis

PENALTIES = ("value", "measure")


def repeat_rows(x: torch.Tensor, times: int) -> torch.Tensor:
    """``times`` copies of the rows of ``x`` along the batch axis (-2), as ``x.repeat(times, 1)``."""
    return x.repeat(*([1] * (x.dim() - 2)), times, 1)


@dataclass
class ConservativeConfig:
    """The conservative penalty of VC-FB / MC-FB (docs/methods.md, "Conservative FB")."""

    samples: int = param(12, "Actions per batch row in the log-sum-exp (authors: 12).", at_least=4)
    uniform_share: float = param(0.5, "Share of those actions drawn uniformly; the rest are split equally "
                                 "between pi(s), pi(s') and the dataset action.", at_least=0, at_most=1)
    lagrange: bool = param(True, "Tune alpha by dual ascent towards --conservative.target; false: constant "
                           "--conservative.alpha.")
    target: float = param(50.0, "The penalty value alpha's dual ascent aims at (authors: 50).")
    alpha: float = param(0.01, "The constant weight with --conservative.lagrange false.", at_least=0)
    alpha_lr: float = param(1e-4, "Adam learning rate of log alpha.", above=0)
    alpha_max: float = param(1e6, "Upper clamp of alpha.", above=0)

    def counts(self) -> tuple[int, int]:
        """(uniform actions, actions of each of the three other groups) per row."""
        uniform = round(self.samples * self.uniform_share)
        rest = self.samples - uniform
        if rest % 3:
            raise ConfigError(f"--conservative.samples {self.samples} with --conservative.uniform-share "
                              f"{self.uniform_share} leaves {rest} actions, which do not split into three equal groups")
        return uniform, rest // 3


class ConservativePenalty(FBComponent):
    """The value- or measure-conservative penalty (see the module docstring) as a part of FB's
    learner: the learner's ``log_alpha`` and ``alpha_optimizer``, the penalty ``P`` from the step's F
    and B, and the FB objective ``fb_total + alpha * P`` with alpha stepped first."""

    def __init__(self, penalty: str, conservative: ConservativeConfig):
        if penalty not in PENALTIES:
            raise ValueError(f"penalty must be one of {PENALTIES}, got {penalty!r}")
        self.penalty, self.conservative = penalty, conservative
        self.num_uniform, self.num_each = conservative.counts()

    def build(self, learner: FBAgent) -> None:
        # log alpha = 0: alpha starts at 1 (the authors' initial Lagrange multiplier).
        learner.log_alpha = torch.nn.Parameter(torch.zeros(()))

    def optimizers(self, learner: FBAgent) -> dict[str, torch.optim.Optimizer]:
        return {"alpha_optimizer": adam([learner.log_alpha], self.conservative.alpha_lr, fused=False)}

    @torch.no_grad()
    def penalty_actions(self, learner: FBAgent, batch, z: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The sampled (non-dataset) actions, their states and z's, ``(J' N, .)`` each, group by group:
        uniform at s, pi(s, z) at s, pi(s', z) at s' (training noise)."""
        c = learner.config
        n = batch.obs.shape[-2]
        uniform = rand((self.num_uniform * n, learner.action_dim), learner.generator, learner.device) * 2 - 1
        z_each = repeat_rows(z, self.num_each)
        obs_each, next_each = repeat_rows(batch.obs, self.num_each), repeat_rows(batch.next_obs, self.num_each)
        policy = training_action(learner.actor(obs_each, z_each), c.stddev, c.stddev_clip, learner.generator)
        next_policy = training_action(learner.actor(next_each, z_each), c.stddev, c.stddev_clip, learner.generator)
        states = torch.cat([repeat_rows(batch.obs, self.num_uniform), obs_each, next_each], dim=-2)
        actions = torch.cat([uniform, policy, next_policy], dim=-2)
        return states, actions, repeat_rows(z, self.num_uniform + 2 * self.num_each)

    def conservative_penalty(self, learner: FBAgent, batch, z: torch.Tensor, forward: torch.Tensor,
                             backward: torch.Tensor) -> torch.Tensor:
        """``P`` of the module docstring; ``forward`` is F at the dataset actions, ``(2, N, d)``,
        ``backward`` the online B of the batch's s', ``(N, d)``."""
        m = learner.members
        n = batch.obs.shape[-2]
        states, actions, zs = self.penalty_actions(learner, batch, z)
        sampled = learner.net_runner(learner.forward_map, states, actions, zs)  # (2, J'N, d)
        sampled = sampled.view(*sampled.shape[:-2], -1, n, sampled.shape[-1])  # (2, J', N, d)
        # A group's (M, N, d) tensors get the head and J' axes of sampled's (M, 2, J', N, d).
        if self.penalty == "value":
            dataset_values = skill_values(forward, z)  # (2, N)
            sampled_values = (sampled * with_head_axis(with_head_axis(z, m), m)).sum(-1)  # (2, J', N)
        else:
            dataset_values = row_products(forward, backward, m)  # (2, N, N)
            sampled_values = row_products(sampled, backward, m)  # (2, J', N, N)
        # The dataset action is one of the groups inside the log-sum-exp (its num_each copies).
        j = 2 if m else 1  # the J' axis
        shape = dataset_values.shape
        copies = dataset_values.unsqueeze(j).expand(*shape[:j], self.num_each, *shape[j:])
        logsumexp = torch.cat([sampled_values, copies], dim=j).logsumexp(dim=j)  # (2, N) or (2, N, N)
        return (logsumexp.flatten(j).mean(-1) - dataset_values.flatten(j).mean(-1)).sum(-1)

    def alpha_step(self, learner: FBAgent, penalty: torch.Tensor) -> torch.Tensor:
        """One dual-ascent step on log alpha (alpha grows while P > target); the new alpha, detached."""
        c = self.conservative
        if not c.lagrange:
            return torch.full(learner.log_alpha.shape, c.alpha, device=learner.device)  # a group: (M,)
        alpha = learner.log_alpha.exp().clamp(0, c.alpha_max)  # a group: (M,), each member's own
        alpha_loss = -0.5 * alpha * (penalty.detach() - c.target)
        minimise(learner.alpha_optimizer, alpha_loss)
        return learner.log_alpha.detach().exp().clamp(0, c.alpha_max)

    def representation_terms(self, learner: FBAgent, step: FBStep) -> dict[str, torch.Tensor]:
        return {"conservative_penalty": self.conservative_penalty(learner, step.batch, step.z, step.forward,
                                                                  step.backward)}

    def representation_objective(self, learner: FBAgent, objective: torch.Tensor, losses: dict,
                                 metrics: dict) -> torch.Tensor:
        penalty = losses["conservative_penalty"]
        alpha = self.alpha_step(learner, penalty)  # stepped first; the FB step uses the new alpha
        total = objective + alpha * penalty
        metrics.update(conservative_alpha=alpha, fb_conservative_total=total.detach())
        return total


class ConservativeFBAgent(FBAgent):
    """FB's learner with a :class:`ConservativePenalty` (``penalty_term``); the two registered
    methods are its subclasses, which fix ``penalty``."""

    penalty: str = ""

    def __init__(self, obs_dim: int, action_dim: int, config: FBConfig, conservative: ConservativeConfig,
                 device: str | torch.device = "cpu", perf: PerfConfig | None = None):
        self.conservative = conservative
        super().__init__(obs_dim, action_dim, config, device, perf, [ConservativePenalty(self.penalty, conservative)])

    @classmethod
    def from_config(cls, obs_dim, action_dim, config, device="cpu") -> ConservativeFBAgent:
        return cls(obs_dim, action_dim, config.fb, config.conservative, device, config.perf)

    @property
    def penalty_term(self) -> ConservativePenalty:
        return self.parts[0]


class VCFBAgent(ConservativeFBAgent):
    """VC-FB: the penalty on ``Q = F.z``."""

    name = "vcfb"
    penalty = "value"


class MCFBAgent(ConservativeFBAgent):
    """MC-FB: the penalty on every ``M = F.B(s')`` of the batch."""

    name = "mcfb"
    penalty = "measure"


# Registration (beside the agents).
from dvfb.agents.registry import AgentSpec, register  # noqa: E402


def conservative_label(name: str):
    return lambda run, finetune: fb_finetune_label(name, finetune)


for _cls, _paper in ((VCFBAgent, "VC-FB"), (MCFBAgent, "MC-FB")):
    register(AgentSpec(
        name=_cls.name, agent_cls=_cls, family="forward-backward",
        summary=f"{_paper}: FB with the {_cls.penalty}-conservative penalty and a tuned weight, for offline data "
                "(Jeen et al.)",
        sections={"fb": FBConfig, "conservative": ConservativeConfig}, zero_shot="reward_inference",
        finetuner="dual_value", presets={"small": {"fb": FB_SMALL}}, label=conservative_label(_cls.name), column=3))
