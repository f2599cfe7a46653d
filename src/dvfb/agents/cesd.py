"""CeSD, constrained ensemble exploration for skill discovery (docs/methods.md, "CeSD").

The skill is a 16-way one-hot; its index is also the index of a state prototype and of one member
of an ensemble critic. Each update (CeSD's order, :meth:`CeSDAgent.update`):

1. CIC's NCE step on ``(s_t, s_{t+n}, skill)`` (:class:`~dvfb.rewards.cesd.CeSDReward`);
2. every ``s_{t+n}`` draws a prototype cluster; the partitioned reward: APT entropy within the
   cluster plus the constraint bonus, 0 for clusters of at most k states;
3. critic step: ensemble member k of Q1 and Q2 regresses ``y_k = r + gamma^n min(Q1'_k, Q2'_k)``
   only on the states of cluster k (a K x N binary mask multiplies prediction and target; the MSE
   averages over all K*N entries, zeros included);
4. actor step on ``-mean_{k,i} z_ik min(Q1_k, Q2_k)(s_i, pi(s_i, z_i))`` (each state uses the head
   of its own skill; the mean over K*N scales it by 1/K);
5. prototype step (swapped assignment on Sinkhorn targets);
6. target EMA.

The critic (:class:`EnsembleCritic`) does not see the skill: a shared trunk
``LNT([s, a] -> 512)`` (orthogonal init) feeds Q1 and Q2, each K members ``512 -> 1024 -> 1`` with
PyTorch's default Linear init, all 2K members one :class:`~dvfb.nets.TwinHead`. In fine-tuning
the URLB fine-tuner rebuilds this critic with :meth:`CeSDCore.build_critic`, copies ``trunk`` and
calls :meth:`CeSDCore.update` without a mask: every member then regresses the extrinsic target,
and the actor still uses the head of the rollout skill.
"""

from __future__ import annotations

from dataclasses import dataclass
import torch
from torch import nn

from dvfb.agents.ddpg import DDPG_SMALL, DDPGConfig, DDPGCore, IntrinsicDDPGAgent
from dvfb.agents.registry import AgentSpec, register
from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import TwinHead, call_network, layernorm_tanh_layer, orthogonal_init_, training_action
from dvfb.nets.members import member_mean, with_head_axis
from dvfb.nets.skills import SkillSpec
from dvfb.rewards.cesd import CeSDReward
from dvfb.rewards.contrastive import CICConfig

__all__ = ["CeSDAgent", "CeSDConfig", "CeSDCore", "EnsembleCritic"]


@dataclass
class CeSDConfig(CICConfig):
    """CeSD's skill, its CIC module (inherited fields: encoder width, NCE temperature 0.5, APT
    settings, learning rate), prototypes, constraint and ensemble critic (official CeSD values;
    the per-domain ones are walker's)."""

    skill_dim: int = param(16, "Number of skills: one-hot width, number of prototypes and of ensemble members "
                           "of each of Q1 and Q2.", at_least=1)
    skill_every: int = param(50, "Resample the skill every this many steps (and at every episode start).",
                             at_least=1)
    knn_k: int = param(16, "Neighbours k of the within-cluster APT reward; only clusters with more than k "
                       "states are rewarded (the official code's threshold 16 equals its k).", at_least=1)
    proto_temperature: float = param(0.1, "Temperature T_p of the prototype softmax, the cluster draws and "
                                     "Sinkhorn.", above=0)
    sinkhorn_iters: int = param(6, "Sinkhorn iterations of the prototype targets (official: walker 6, quadruped 5, "
                                "jaco 4; the DVFB authors' copy uses walker's 6 on every domain).", at_least=1)
    constraint_factor: float = param(1.0, "lambda_c of the constraint bonus lambda_c / (1 + off-skill states of the "
                                     "cluster) (official: walker and quadruped 1.0, jaco 0.1).", at_least=0)
    critic_trunk_dim: int = param(512, "Width of the ensemble critic's shared LNT trunk on [s, a].", at_least=1)
    critic_hidden_dim: int = param(1024, "Hidden width of every ensemble member of Q1 and Q2.", at_least=1)


class EnsembleCritic(nn.Module):
    """``Q1_k(s, a), Q2_k(s, a)``, k = 1..K: a shared ``LNT([s, a] -> trunk)`` and 2K members
    ``trunk -> hidden -> ReLU -> 1`` (one :class:`~dvfb.nets.TwinHead`, default Linear init; head
    ``t*K + k`` is member k of Q_{t+1}). Returns ``(2, K, N, 1)``. The skill argument is accepted
    for the core's calling convention and ignored: CeSD's critic does not take the skill."""

    def __init__(self, obs_dim: int, action_dim: int, trunk_dim: int, hidden_dim: int, ensemble_size: int):
        super().__init__()
        self.ensemble_size = ensemble_size
        self.trunk = orthogonal_init_(layernorm_tanh_layer(obs_dim + action_dim, trunk_dim))
        self.heads = TwinHead(trunk_dim, hidden_dim, 1, num_heads=2 * ensemble_size, init="default")

    def forward(self, obs: torch.Tensor, skill: torch.Tensor | None, action: torch.Tensor) -> torch.Tensor:
        q = self.heads(self.trunk(torch.cat([obs, action], dim=-1)))  # (2K, N, 1)
        return q.view(*q.shape[:-3], 2, self.ensemble_size, *q.shape[-2:])  # a group: (M, 2, K, N, 1)


class CeSDCore(DDPGCore):
    """The DDPG core with CeSD's ensemble critic, its masked critic loss and its per-skill actor
    loss (see the module docstring). ``skill_dim`` is the ensemble size."""

    def __init__(self, obs_dim: int, skill_dim: int, action_dim: int, config: DDPGConfig,
                 trunk_dim: int = 512, head_hidden_dim: int = 1024):
        # Set before the base constructor, which builds the critic.
        self.trunk_dim, self.head_hidden_dim = trunk_dim, head_hidden_dim
        super().__init__(obs_dim, skill_dim, action_dim, config)

    def build_critic(self) -> nn.Module:
        return EnsembleCritic(self.obs_dim, self.action_dim, self.trunk_dim, self.head_hidden_dim, self.skill_dim)

    def critic_values(self, critic: nn.Module, obs: torch.Tensor, skill: torch.Tensor, action: torch.Tensor,
                      run=call_network) -> torch.Tensor:
        """``(2, K, N, 1)``: the K members of Q1 and of Q2."""
        return run(critic, obs, skill, action)

    def critic_loss(self, batch: Batch, skill: torch.Tensor, reward: torch.Tensor, run=call_network,
                    mask: torch.Tensor | None = None) -> torch.Tensor:
        """``sum_{Q1, Q2} mean_{k, i} (m_ki Q_k(s_i, a_i) - m_ki y_ki)^2`` with
        ``y_k = r + gamma^n min(Q1'_k, Q2'_k)(s_{t+n}, a')``; ``mask`` ``(K, N)`` (1 where state i
        belongs to cluster k); None: every member regresses every state (fine-tuning)."""
        c = self.config
        with torch.no_grad():
            next_action = training_action(run(self.actor, batch.next_obs, skill), c.stddev, c.stddev_clip,
                                          self.generator)
            next_v = self.critic_values(self.critic_target, batch.next_obs, skill, next_action, run).amin(-4)
            m = self.members
            target = with_head_axis(reward, m) + with_head_axis(batch.discount, m) * next_v  # (K, N, 1)
        q = self.critic_values(self.critic, batch.obs, skill, batch.action, run)  # (2, K, N, 1)
        if mask is not None:
            keep = mask.unsqueeze(-1).to(q.dtype)
            q, target = q * with_head_axis(keep, m), target * keep
        return (q - with_head_axis(target, m)).pow(2).mean(dim=(-3, -2, -1)).sum(-1)

    def actor_loss(self, obs: torch.Tensor, skill: torch.Tensor, run=call_network) -> torch.Tensor:
        """``-mean_{k, i} z_ik min(Q1_k, Q2_k)(s_i, a_i)``, ``a_i`` a clipped-noise sample of pi."""
        c = self.config
        action = training_action(run(self.actor, obs, skill), c.stddev, c.stddev_clip, self.generator)
        q = self.critic_values(self.critic, obs, skill, action, run).amin(-4).squeeze(-1)  # (K, N)
        return -member_mean(skill.mT * q, self.members)

    def update(self, batch: Batch, reward: torch.Tensor, metrics: dict, run=call_network,
               mask: torch.Tensor | None = None) -> None:
        """Critic step, actor step, target EMA. Without ``mask`` (the fine-tuner's call) every
        ensemble member regresses the target on every state."""
        self.train_step(batch, reward, metrics, run, mask=mask)
        self.update_target()


class CeSDAgent(IntrinsicDDPGAgent):
    name = "cesd"
    reward_section = "cesd"

    def build_core(self) -> CeSDCore:
        # The ensemble's widths live in CeSD's own section.
        c = self.reward_config
        return CeSDCore(self.obs_dim, self.skill.dim, self.action_dim, self.ddpg, trunk_dim=c.critic_trunk_dim,
                        head_hidden_dim=c.critic_hidden_dim)

    def declare_skill(self) -> SkillSpec:
        c = self.reward_config
        return SkillSpec("one_hot", c.skill_dim, every=c.skill_every)

    def build_reward(self) -> CeSDReward:
        c = self.reward_config
        return CeSDReward(self.obs_dim, self.skill.dim, c, c.proto_temperature, c.sinkhorn_iters, c.constraint_factor)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """CIC step -> clusters and reward -> critic -> actor -> prototypes -> target EMA."""
        metrics: dict[str, torch.Tensor] = {}
        run = self.net_runner
        metrics.update(self.intrinsic.update(batch, run))
        reward, cluster, next_rep, info = self.intrinsic.score_and_assign(batch, run)
        metrics.update(info)
        heads = torch.arange(self.skill.dim, device=cluster.device)
        mask = heads.unsqueeze(-1) == cluster.unsqueeze(-2)  # (K, N): state i regresses head k = its cluster
        self.core.train_step(batch, reward, metrics, run, mask=mask)
        # g is unchanged since the reward (the critic and actor steps do not touch it): reuse g(s_{t+n}).
        metrics.update(self.intrinsic.update_prototypes(batch, run, next_rep))
        self.core.update_target()
        return metrics


register(AgentSpec(
    name="cesd", agent_cls=CeSDAgent, family="skill_discovery",
    summary="CeSD: 16 one-hot skills, each an ensemble critic head exploring its own prototype cluster under a "
            "state-distribution constraint (Bai et al.)",
    sections={"ddpg": DDPGConfig, "cesd": CeSDConfig}, zero_shot="skill_selection", finetuner="urlb",
    presets={"small": {"ddpg": DDPG_SMALL,
                       "cesd": {"hidden_dim": 256, "critic_trunk_dim": 128, "critic_hidden_dim": 256}}}))
