"""DVFB: FB plus an exploration critic driven by an intrinsic reward (RND + contrastive entropy).

docs/methods.md §0, §7.2-§7.7, §7.11. The skill value Q_M = F . z keeps learning the successor
measure; a separate z-conditioned twin critic Q_P learns from the intrinsic reward
``r_rnd + beta * r_ce`` and the actor maximises ``Q_M + alpha * Q_P``. The learner is FB's with one
component, :class:`ExplorationCritic`; the model is FB's. "DVFB w/o CE" is
``use_ce = false`` (no contrastive module at all, ``r = r_rnd``). ``exploration.reward`` swaps the
whole intrinsic reward for one of the paper's Table 8 variants (docs/methods.md, "DVFB with other
intrinsic rewards"): ICM-APT, Proto or CIC, the same :mod:`dvfb.rewards` modules the baselines use.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from dvfb.agents.fb import FB_SMALL, FBAgent, FBComponent, FBConfig, FBStep, fb_finetune_label
from dvfb.agents.registry import AgentSpec, config_field, register
from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import TwinCritic, adam, make_target, twin_td_loss
from dvfb.nets.members import member_mean, minimise, per_member
from dvfb.rewards.contrastive import CE_AGGREGATES, CE_NEIGHBOURS, CICConfig, CICReward, ContrastiveEntropyReward
from dvfb.rewards.icm import ICMAPTConfig, ICMAPTReward
from dvfb.rewards.proto import ProtoConfig, ProtoReward
from dvfb.rewards.rnd import RNDReward

EXPLORATION_REWARDS = ("rnd_ce", "icm_apt", "proto", "cic")
# The batch column of B's labels, the skill DVFB's contrastive modules pair each transition with.
LABEL_COLUMN = "b_label"


@dataclass
class ExplorationConfig:
    """DVFB's exploration part (docs/methods.md §7.3-§7.7, §14)."""

    reward: str = param("rnd_ce", "Intrinsic reward of Q_P: rnd_ce (RND + beta * CE, the paper's), or the Table 8 "
                        "variants icm_apt, proto, cic (settings in the --icm-apt.*, --proto.*, --cic.* sections).",
                        EXPLORATION_REWARDS)
    alpha: float = param(5.0, "Weight of Q_P in the actor objective (D2; authors' code: 50).", at_least=0)
    alpha_mode: str = param("constant", "constant alpha, or adaptive alpha_t = 2 mean(Q_M)/mean(Q_P).",
                            ("constant", "adaptive"))
    beta: float = param(0.5, "Weight of the contrastive-entropy reward (D4).", at_least=0)
    use_ce: bool = param(True, "Use the contrastive-entropy term; false gives 'DVFB w/o CE'.")
    rnd_input: str = param("next_obs", "Which state RND scores: s' (paper) or s (authors' code), D6.",
                           ("next_obs", "obs"))
    rnd_rep_dim: int = param(512, "Output width of the RND networks.", at_least=1)
    rnd_obs_clip: float = param(5.0, "Clip of the batch-normalised RND input.", above=0)
    contrastive_hidden_dim: int = param(1024, "Hidden width of the contrastive encoders.", at_least=1)
    ce_k: int = param(12, "Number of neighbours k of the CE reward.", at_least=1)
    ce_neighbours: str = param("least_similar", "Which skills are the CE neighbours (D7).", CE_NEIGHBOURS)
    ce_aggregate: str = param("log_of_mean", "log of the mean or mean of the logs (D7).", CE_AGGREGATES)
    ce_temperature: float = param(1.0, "Temperature of the CE reward.", above=0)
    nce_temperature: float = param(1.0, "Temperature T of the NCE loss (D14).", above=0)
    nce_exact_positive: bool = param(False, "Subtract the exact positive term in the NCE denominator.")


class ExplorationCritic(FBComponent):
    """DVFB's part of the learner (docs/methods.md §7.2-§7.7, §7.11): the exploration critic Q_P,
    its target, and the intrinsic-reward modules it learns from (RND + contrastive entropy, or a
    Table 8 variant); the actor's bonus ``alpha * Q_P``. Its networks are the learner's
    ``exploration_critic``, ``exploration_critic_target``, ``rnd``, ``contrastive`` and
    ``variant_reward`` (those the reward has)."""

    def __init__(self, exploration: ExplorationConfig, icm_apt: ICMAPTConfig | None = None,
                 proto: ProtoConfig | None = None, cic: CICConfig | None = None):
        self.exploration = exploration
        self.variant_configs = {"icm_apt": icm_apt or ICMAPTConfig(), "proto": proto or ProtoConfig(),
                                "cic": cic or CICConfig()}
        self.rnd = self.contrastive = self.variant_reward = None

    def build(self, learner: FBAgent) -> None:
        c, e = learner.config, self.exploration
        obs_dim, action_dim = learner.obs_dim, learner.action_dim
        self.critic = TwinCritic(obs_dim, action_dim, c.z_dim, c.hidden_dim)
        self.critic_target = make_target(self.critic)
        if e.reward == "rnd_ce":
            self.rnd = RNDReward(obs_dim, c.hidden_dim, e.rnd_rep_dim, e.rnd_obs_clip, e.rnd_input)
            # The skill labels are B's outputs, so the encoders' skill dimension is z_dim (§4.6).
            self.contrastive = (ContrastiveEntropyReward(
                obs_dim, c.z_dim, e.contrastive_hidden_dim, e.ce_k, e.ce_neighbours, e.ce_aggregate,
                e.ce_temperature, e.nce_temperature, e.nce_exact_positive) if e.use_ce else None)
        elif e.reward == "icm_apt":
            self.variant_reward = ICMAPTReward(obs_dim, action_dim, self.variant_configs["icm_apt"])
        elif e.reward == "proto":
            self.variant_reward = ProtoReward(obs_dim, action_dim, self.variant_configs["proto"])
        else:  # cic: its NCE pairs each transition with B's label, as DVFB's own CE module does
            self.variant_reward = CICReward(obs_dim, c.z_dim, self.variant_configs["cic"])
        for module in (self.contrastive, self.variant_reward):
            if module is not None:
                module.skill_column = LABEL_COLUMN  # the modules that pair rows with a skill read B's
        learner.add_module("exploration_critic", self.critic)
        learner.add_module("exploration_critic_target", self.critic_target)
        for name in ("rnd", "contrastive", "variant_reward"):  # None where the reward has no such module
            learner.add_module(name, getattr(self, name))

    def _reward_modules(self) -> dict[str, torch.nn.Module]:
        """The intrinsic-reward modules, under the names of their optimisers."""
        modules = {"rnd_optimizer": self.rnd, "contrastive_optimizer": self.contrastive,
                   "exploration_reward_optimizer": self.variant_reward}
        return {k: m for k, m in modules.items() if m is not None}

    def optimizers(self, learner: FBAgent) -> dict[str, torch.optim.Optimizer]:
        c = learner.config
        optimizers = {"critic_optimizer": adam(self.critic.parameters(), c.lr, c.fused_adam)}
        for name, module in self._reward_modules().items():
            lr = c.lr if name != "exploration_reward_optimizer" else self.variant_configs[self.exploration.reward].lr
            module.make_optimizer(lr, c.fused_adam)
            optimizers[name] = module.optimizer
        return optimizers

    def target_pairs(self):
        return [(self.critic_target, self.critic)]

    def update_networks(self):
        nets = [self.critic, self.critic_target]
        if self.rnd is not None:
            nets += [self.rnd.networks.predictor, self.rnd.networks.target]
        if self.contrastive is not None:
            enc = self.contrastive.encoders
            nets += [enc.state_net, enc.transition_net, enc.skill_net]
        return nets

    def actor_frozen(self):
        return [self.critic]

    # Intrinsic reward ----------------------------------------------------------------------------
    def intrinsic_reward(self, learner: FBAgent, batch: Batch, labels: torch.Tensor, metrics: dict) -> torch.Tensor:
        """Train the reward modules on the batch, then score it with the updated modules (§7.2 steps 3-6).

        The CE and CIC encoders pair each transition with B's (detached) label of it (§4.6): the
        label travels in its own column, ``b_label``, which those modules read (their
        ``skill_column``); ``batch.z`` stays the stored rollout skill.
        """
        e = self.exploration
        run = learner.net_runner
        labelled = dataclasses.replace(batch, columns={**batch.columns, LABEL_COLUMN: labels})
        if self.variant_reward is not None:
            reward = self.variant_reward.update_and_score(labelled, metrics, run)
        else:
            reward = self.rnd.update_and_score(labelled, metrics, run)
            if self.contrastive is not None:
                metrics.update(self.contrastive.update(labelled, run))
                if e.beta != 0:
                    with torch.no_grad():  # the just-updated encoders (§7.2 step 6)
                        ce = self.contrastive.score(labelled, run)
                    metrics["ce_reward"] = member_mean(ce, learner.members)
                    reward = reward + e.beta * ce
        metrics["intrinsic_reward"] = member_mean(reward, learner.members)
        return reward

    def critic_loss(self, learner: FBAgent, batch: Batch, z: torch.Tensor, next_action: torch.Tensor,
                    reward: torch.Tensor) -> torch.Tensor:
        """Twin TD loss of Q_P on the intrinsic reward (§7.7)."""
        run = learner.net_runner
        with torch.no_grad():
            next_q = run(self.critic_target, batch.next_obs, z, next_action).amin(-3)  # (N, 1)
            target = reward + batch.discount * next_q
        q = run(self.critic, batch.obs, z, batch.action)  # (2, N, 1)
        return twin_td_loss(q, target)

    def before_representation(self, learner: FBAgent, step: FBStep, metrics: dict) -> None:
        reward = self.intrinsic_reward(learner, step.batch, step.labels, metrics)
        loss = self.critic_loss(learner, step.batch, step.z, step.next_action, reward)
        minimise(learner.critic_optimizer, loss)
        metrics["exploration_critic_loss"] = loss.detach()

    def actor_bonus(self, learner: FBAgent, obs, z, action, skill_value, metrics):
        e = self.exploration
        exploration_value = learner.net_runner(self.critic, obs, z, action).amin(-3).squeeze(-1)
        m = learner.members
        if e.alpha_mode == "adaptive":  # one alpha per member, from its own means
            alpha = per_member((2 * member_mean(skill_value, m) / member_mean(exploration_value, m)).detach(),
                               exploration_value)
        else:
            alpha = e.alpha
        metrics["exploration_value"] = member_mean(exploration_value.detach(), m)
        return alpha * exploration_value


class DVFBAgent(FBAgent):
    """FB + the exploration critic Q_P (docs/methods.md §7): FB's learner with an
    :class:`ExplorationCritic` (``explorer``), configured by ``exploration``."""

    name = "dvfb"

    def __init__(self, obs_dim: int, action_dim: int, config: FBConfig, exploration: ExplorationConfig,
                 device: str | torch.device = "cpu", perf=None, icm_apt: ICMAPTConfig | None = None,
                 proto: ProtoConfig | None = None, cic: CICConfig | None = None):
        self.exploration = exploration
        super().__init__(obs_dim, action_dim, config, device, perf, [ExplorationCritic(exploration, icm_apt, proto, cic)])

    @classmethod
    def from_config(cls, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu") -> DVFBAgent:
        return cls(obs_dim, action_dim, config.fb, config.exploration, device, config.perf,
                   config.icm_apt, config.proto, config.cic)

    @property
    def explorer(self) -> ExplorationCritic:
        return self.parts[0]


def dvfb_label(run, finetune) -> str:
    """``dvfb``, ``dvfb_wo_ce`` (paper Table 3) or ``dvfb_<reward>`` (Table 8), plus the FB family's
    fine-tuning ablation suffixes."""
    exploration = config_field(run, "exploration") or {}
    reward = config_field(exploration, "reward", "rnd_ce")
    if reward != "rnd_ce":
        name = f"dvfb_{reward}"
    elif not config_field(exploration, "use_ce", True):
        name = "dvfb_wo_ce"
    else:
        name = "dvfb"
    return fb_finetune_label(name, finetune)


register(AgentSpec(
    name="dvfb", agent_cls=DVFBAgent, family="forward-backward",
    summary="DVFB: FB plus an exploration critic on RND + contrastive entropy, actor on Q_M + alpha Q_P",
    sections={"fb": FBConfig, "exploration": ExplorationConfig, "icm_apt": ICMAPTConfig, "proto": ProtoConfig,
              "cic": CICConfig},
    zero_shot="reward_inference", finetuner="dual_value", moved_fields={"update_z_every": "fb.skill_every"},
    presets={"small": {"fb": FB_SMALL, "exploration": {"contrastive_hidden_dim": 256, "rnd_rep_dim": 128},
                       "icm_apt": {"hidden_dim": 256, "rep_dim": 128},
                       "cic": {"hidden_dim": 256}},
             "code": {"fb": {"backward_input": "code_exact"}, "exploration": {"alpha": 50.0, "rnd_input": "obs"},
                      "finetune": {"qf_coef": 50.0, "eta": 1.0}}},
    label=dvfb_label, column=0,
    # The paper's ablations (Tables 7 and 9-12): alpha and beta of pre-training, eta of fine-tuning
    # (and the authors' Q_F weight, which preset code changes with it).
    coefficients=(("exploration.alpha", "alpha"), ("exploration.alpha_mode", "alpha"), ("exploration.beta", "beta"),
                  ("finetune.eta", "eta"), ("finetune.eta_mode", "eta"), ("finetune.qf_coef", "qf"))))
