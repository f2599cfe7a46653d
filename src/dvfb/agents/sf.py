"""Successor features (SF-Lap, SF-LRA-P, SF-LRA-SR, SF-CL): docs/methods.md, "Successor features".

One agent for the four methods of the paper's Table 1; they differ only in the feature learner
``phi(s)`` (:mod:`dvfb.nets.features`, chosen by ``--sf.features``). The successor features
``psi_k(s, a, z)`` are FB's forward network (two streams, twin heads); the actor is FB's, and so
is its loss ``-mean min_k psi_k(s, a~, z) . z``, which this class inherits from
:class:`~dvfb.agents.fb.FBAgent` together with the skill prior, the EMA and the skill value. What
SF replaces: the TD loss (on the projections ``psi . z``, with ``y = phi(s') + gamma psi_bar'``
from the target head whose ``psi_bar' . z`` is smaller), the separately trained features, the
training skills (prior draws, a ``mix_ratio`` share replaced by ``sqrt(d) normalize(phi Sigma^+)``)
and the zero-shot inference (least squares of the task reward on ``phi(s')``).

As in FB, every forward pass of the update is computed once: ``phi(s')`` feeds the training
skills and the TD target (detached) and the feature loss (with its graph).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

from dvfb.agents.base import ReplayNeeds
from dvfb.agents.fb import FBAgent, FBModel, FBStep
from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import ForwardMap, adam, project_to_sphere, sample_z_prior, skill_values, training_action
from dvfb.nets.features import FEATURE_LEARNERS
from dvfb.nets.members import rand, randperm, take_rows, with_head_axis

log = logging.getLogger(__name__)

# The paper's names of the four variants (Table 1), by feature learner.
PAPER_NAMES = {"lap": "SF-Lap", "lra_p": "SF-LRA-P", "lra_sr": "SF-LRA-SR", "cl": "SF-CL"}


@dataclass
class SFConfig:
    """Hyper-parameters of the successor-feature agents (docs/methods.md, "Successor features")."""

    features: str = param("lap", "Feature learner phi: Laplacian (lap), low-rank transitions (lra_p), low-rank "
                          "successor representation (lra_sr) or contrastive (cl).", tuple(FEATURE_LEARNERS))
    z_dim: int = param(50, "Dimension d of phi, psi and the task vector z.", at_least=1)
    skill_every: int = param(300, "Resample the rollout z when the step counter is a multiple of this (and at "
                             "every episode start).", at_least=1)
    hidden_dim: int = param(1024, "Hidden width H of the actor and psi.", at_least=1)
    feature_dim: int = param(512, "Feature width E of each two-stream encoder (actor, psi).", at_least=1)
    backward_hidden_dim: int = param(526, "Hidden width Hb of phi and its auxiliary networks (the authors' "
                                     "configs: 526).", at_least=1)
    actor_arch: str = param("two_stream", "Actor architecture (§4.1).", ("two_stream", "mlp"))
    batch_size: int = param(1024, "Transitions per gradient update.", at_least=2)
    lr: float = param(1e-4, "Adam learning rate of psi and the actor.", above=0)
    feature_lr_coef: float = param(5.0, "Learning rate of phi and its auxiliary networks as a multiple of lr.",
                                   above=0)
    discount: float = param(0.99, "Discount gamma (also LRA-SR's 0.99).", at_least=0, at_most=1)
    tau: float = param(0.01, "EMA rate of the target networks.", above=0, at_most=1)
    stddev: float = param(0.2, "Fixed policy standard deviation sigma.", at_least=0)
    stddev_clip: float = param(0.3, "Noise clip of training samples.", at_least=0)
    mix_ratio: float = param(0.5, "Fraction of training z's replaced by sqrt(d) normalize(phi(s') Sigma^+) of "
                             "replay states.", at_least=0, at_most=1)
    fused_adam: bool = param(True, "Use torch's fused (single-kernel) Adam where available.")


def regress_task_vector(features: torch.Tensor, rewards: torch.Tensor) -> torch.Tensor:
    """``z_r = sqrt(d) w / ||w||`` with ``w = argmin ||features w - rewards||^2`` (float64 least
    squares); zeros when the rewards give no direction."""
    solution = torch.linalg.lstsq(features.double(), rewards.reshape(-1, 1).double()).solution[:, 0]
    if float(solution.norm()) < 1e-12:
        return torch.zeros(features.shape[1], dtype=features.dtype, device=features.device)
    return project_to_sphere(solution).to(features.dtype)


class SFModel(FBModel):
    """A pre-trained successor-feature agent: FB's actor, the successor features psi in F's place and
    the learned features phi in B's (inside the feature learner, whose snapshot holds its auxiliary
    networks too); zero-shot by the regression of rewards on phi(s')."""

    name = "sf"
    TARGETS = (("successor_map", "successor_target"),)

    def build_representation(self, config: SFConfig) -> None:
        c = config
        if c.features not in FEATURE_LEARNERS:
            raise ValueError(f"features must be one of {tuple(FEATURE_LEARNERS)}, got {c.features!r}")
        self.successor_map = ForwardMap(self.obs_dim, self.action_dim, c.z_dim, c.hidden_dim, c.feature_dim)
        self.feature_learner = FEATURE_LEARNERS[c.features](self.obs_dim, self.action_dim, c.z_dim,
                                                            c.backward_hidden_dim, c.tau, c.discount)

    @property
    def forward_map(self) -> nn.Module:
        """psi plays F's part in what SF shares with FB: the actor loss, the skill value and the
        dual-value fine-tuning's ``Q_M``."""
        return self.successor_map

    @property
    def features(self) -> nn.Module:
        """phi(s), the state features whose successor features psi learns."""
        return self.feature_learner.phi

    def snapshot_modules(self) -> dict[str, nn.Module]:
        return {"actor": self.actor, "successor_map": self.successor_map, "feature_learner": self.feature_learner}

    @torch.no_grad()
    def backward_features(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """phi(s') of transitions: what rewards are regressed on (and fine-tuning maps rewards with)."""
        return self.features(next_obs)

    def infer_skill(self, obs, next_obs, reward, inference) -> tuple[torch.Tensor, dict]:
        """z_r from the least-squares regression of the rewards on phi(s') (docs/methods.md,
        "Successor features"); a prior draw if the rewards give no direction."""
        z = regress_task_vector(self.backward_features(obs, next_obs), reward)
        info: dict = {"num_samples": int(reward.numel()), "fallback": None}
        if float(z.norm()) == 0.0:
            log.warning("the reward regression gave z = 0 (all rewards 0?): falling back to a random z ~ p(z)")
            z = self.sample_skill(1)[0]
            info["fallback"] = "prior"
        return z, info

    def skill_from_goal(self, goal_obs: torch.Tensor) -> torch.Tensor:
        raise ConfigError("successor features have no goal-reaching skill (their features are not a measure); "
                          "use --skill-source rewards or reward_fn")

    def goal_widths(self) -> tuple[int, ...]:
        return (self.obs_dim,)

    def nonfinite_hint(self, metric_names: list[str]) -> str:
        return ""


class SFAgent(FBAgent):
    """The successor features' learner: FB's, with psi's TD loss and the feature learner's loss in
    place of the FB loss, and training skills from phi (see the module docstring)."""

    name = "sf"
    model_cls = SFModel
    objective_key = "sf_total"
    representation_optimizer = "sf_optimizer"

    @classmethod
    def config_section(cls, config):
        return config.sf

    @property
    def forward_map(self) -> nn.Module:
        return self.successor_map

    @property
    def features(self) -> nn.Module:
        return self.feature_learner.phi

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        # psi and phi have separate objectives; one optimiser with a group each is the same
        # (Adam is element-wise) and steps once.
        c = self.config
        return {"sf_optimizer": adam([{"params": self.successor_map.parameters()},
                                      {"params": self.feature_learner.parameters(), "lr": c.lr * c.feature_lr_coef}],
                                     lr=c.lr, fused=c.fused_adam)}

    def update_networks(self) -> list[nn.Module]:
        return [self.actor, self.successor_map, self.successor_target, self.features]

    def replay_needs(self) -> ReplayNeeds:
        return ReplayNeeds(self.config.batch_size, self.config.discount, nstep=1)

    # Skills ----------------------------------------------------------------------------------------
    @torch.no_grad()
    def feature_skills(self, next_features: torch.Tensor) -> torch.Tensor:
        """Prior z's with a ``mix_ratio`` share replaced by ``sqrt(d) normalize(phi_perm Sigma^+)``,
        ``Sigma = Phi^T Phi / N`` of ``phi(s')`` of the batch in a random order."""
        c = self.config
        n = next_features.shape[-2]
        z = sample_z_prior(n, c.z_dim, self.device, self.generator).to(next_features.dtype)
        if c.mix_ratio <= 0:
            return z
        perm = randperm(n, self.generator, self.device)
        phi = take_rows(next_features, perm)
        cov = phi.mT @ phi / n
        goals = project_to_sphere(phi @ torch.linalg.pinv(cov, hermitian=True))
        replace = rand((n, 1), self.generator, self.device) < c.mix_ratio
        return torch.where(replace, goals, z)

    # The update ------------------------------------------------------------------------------------
    def prepare(self, batch: Batch) -> FBStep:
        """phi(s') with its graph (for the feature loss) and the training skills from it."""
        next_features = self.net_runner(self.features, batch.next_obs)
        z = self.feature_skills(next_features.detach())
        return FBStep(batch, z, None, extra={"next_features": next_features})

    def representation_losses(self, step: FBStep) -> dict[str, torch.Tensor]:
        return self.sf_losses(step.batch, step.z, step.extra["next_features"])

    def sf_losses(self, batch: Batch, z: torch.Tensor, next_features: torch.Tensor) -> dict[str, torch.Tensor]:
        """The TD loss on the projections ``psi_k . z`` and the feature learner's loss."""
        c = self.config
        run = self.net_runner
        with torch.no_grad():
            next_action = training_action(run(self.actor, batch.next_obs, z), c.stddev, c.stddev_clip, self.generator)
            target_psi = run(self.successor_target, batch.next_obs, next_action, z)  # (2, N, d)
            # The head whose value psi_bar' . z is smaller, per sample (the head axis is -3).
            pick = skill_values(target_psi, z).argmin(-2)  # (N,)
            index = pick.unsqueeze(-2).unsqueeze(-1).expand(*pick.shape[:-1], 1, *target_psi.shape[-2:])
            next_psi = target_psi.gather(-3, index).squeeze(-3)  # (N, d)
            target = ((next_features.detach() + batch.discount * next_psi) * z).sum(-1)  # (N,)
        values = skill_values(run(self.successor_map, batch.obs, batch.action, z), z)  # (2, N)
        sf_loss = (values - with_head_axis(target, self.members)).pow(2).mean(-1).sum(-1)
        feature_loss, feature_metrics = self.feature_learner.loss(batch.obs, batch.action, batch.next_obs,
                                                                  next_features)
        return {"sf_loss": sf_loss, "feature_loss": feature_loss, "sf_total": sf_loss + feature_loss,
                **feature_metrics}

    # Checkpointing -------------------------------------------------------------------------------
    def pretrained_modules(self) -> dict[str, nn.Module]:
        return {"actor": self.actor, "successor_map": self.successor_map, "successor_target": self.successor_target,
                "feature_learner": self.feature_learner}


# Registration (beside the agent).
from dvfb.agents.fb import FB_SMALL  # noqa: E402
from dvfb.agents.registry import AgentSpec, config_field, register  # noqa: E402


def sf_label(run, finetune) -> str:
    """The paper's name of the variant (SF-Lap, ...)."""
    features = config_field(config_field(run, "sf", {}) or {}, "features", "lap")
    return PAPER_NAMES.get(features, f"SF-{features}")


register(AgentSpec(
    name="sf", agent_cls=SFAgent, family="successor-features",
    summary="successor features psi(s, a, z) of learned features phi (Lap, LRA-P, LRA-SR or CL; --sf.features), "
            "zero-shot by reward regression on phi",
    sections={"sf": SFConfig}, zero_shot="feature_regression", finetuner="dual_value",
    # Fine-tuning as URLB's: a fresh critic on the task's own reward, psi unused by the actor.
    defaults={"finetune": {"eta": 0.0, "reward_mapping": False}},
    presets={"small": {"sf": FB_SMALL}}, label=sf_label, column=2))
