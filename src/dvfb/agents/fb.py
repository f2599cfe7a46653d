"""The forward-backward (FB) family: :class:`FBModel` (the pre-trained agent: actor, F, B and their
inference) and :class:`FBAgent` (the learner of online and offline FB, and of its variants by
composition).

Implements docs/methods.md §4.1-§4.3, §5 (task vectors), §7.8-§7.11 (FB loss, auxiliary implicit-
reward Q loss, orthonormality, actor) and §8.2 (z inference). A variant is a small subclass that
chooses its model and the :class:`FBComponent` s its learner composes: DVFB
(:mod:`dvfb.agents.dvfb`) adds an exploration critic and its intrinsic reward, VC-FB and MC-FB
(:mod:`dvfb.agents.conservative_fb`) a conservative penalty; the successor features
(:mod:`dvfb.agents.sf`) replace the model's B by learned features and the representation loss.

Performance notes (issue "Performance"): each forward pass is computed once per update and reused
-- the online B of the batch feeds the FB loss, the auxiliary Q loss, the orthonormality loss and
(detached) DVFB's contrastive labels; the target-policy next action feeds every TD target; twin
heads are one batched product. Metrics are returned as device tensors; nothing in the update path
synchronises with the host (tests/test_update_equivalence.py checks this, and checks every loss and
gradient of a full update against a plain reference implementation). The target EMAs are one fused
call over all target parameters, and the actor loss is built with F (and Q_P) excluded from autograd,
so its graph holds only the path from the action to the actor. How the networks execute
(precision, torch.compile) is :mod:`dvfb.nets.execution`'s business: every network call of the update
goes through the model's :attr:`~dvfb.agents.base.Model.net_runner`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import torch
from torch import nn

from dvfb.agents.base import Agent, Model, ReplayNeeds, TrainingSettings
from dvfb.core.config import param
from dvfb.data import Batch
from dvfb.nets import (
    Actor,
    BackwardMap,
    ForwardMap,
    adam,
    implicit_reward,
    make_target,
    offdiag_mean,
    orthonormality_loss,
    project_to_sphere,
    sample_z_prior,
    skill_values,
    training_action,
)
from dvfb.nets.execution import NetRunner, PerfConfig, requires_grad_disabled
from dvfb.nets.members import member_mean, minimise, rand, randperm, row_products, take_rows, with_head_axis
from dvfb.nets.skills import SkillSpec

log = logging.getLogger(__name__)

BACKWARD_INPUTS = ("state", "transition", "code_exact")


@dataclass
class FBConfig:
    """Hyper-parameters of the FB representation and its actor (docs/methods.md §12, §14)."""

    z_dim: int = param(50, "Dimension d of F, B and the task vector z.", at_least=1)
    skill_every: int = param(300, "Resample the rollout z when the step counter is a multiple of this (and at "
                             "every episode start), §5.2.", at_least=1)
    hidden_dim: int = param(1024, "Hidden width H of the actor, F and the critics.", at_least=1)
    feature_dim: int = param(512, "Feature width E of each two-stream encoder (actor, F).", at_least=1)
    backward_hidden_dim: int = param(526, "Hidden width Hb of the backward map B.", at_least=1)
    actor_arch: str = param("two_stream", "Actor architecture (§4.1).", ("two_stream", "mlp"))
    backward_input: str = param("state", "What B reads: s' (state), (s, s') (transition) or the "
                                "authors' pairings (code_exact), see D1.", BACKWARD_INPUTS)
    batch_size: int = param(1024, "Transitions per gradient update.", at_least=2)
    lr: float = param(1e-4, "Adam learning rate of every network.", above=0)
    backward_lr_coef: float = param(1.0, "B's learning rate as a multiple of lr.", above=0)
    discount: float = param(0.99, "Discount gamma.", at_least=0, at_most=1)
    tau: float = param(0.01, "EMA rate of the target networks (after every update).", above=0, at_most=1)
    stddev: float = param(0.2, "Fixed policy standard deviation sigma.", at_least=0)
    stddev_clip: float = param(0.3, "Noise clip of training samples.", at_least=0)
    mix_ratio: float = param(0.5, "Fraction of training z's replaced by projected B of replay states.",
                             at_least=0, at_most=1)
    ortho_coef: float = param(1.0, "Weight lambda of the orthonormality loss.", at_least=0)
    q_loss: bool = param(True, "Add the auxiliary implicit-reward Q loss (D10).")
    q_loss_coef: float = param(0.01, "Weight of the auxiliary Q loss.", at_least=0)
    cov_ridge: float = param(0.0, "Ridge added to Cov(B) before solving Cov x = z (D19).", at_least=0)
    fused_adam: bool = param(True, "Use torch's fused (single-kernel) Adam where available; false = "
                             "the multi-tensor (foreach) implementation. Same math either way.")


def infer_z_from_rewards(features: torch.Tensor, rewards: torch.Tensor,
                         quantile: float | None) -> tuple[torch.Tensor, dict]:
    """z_r = proj(mean over kept samples of r_i B_i) with the optional top-quantile filter (§8.2).

    If the weighted mean is (about) zero, retry without the filter; if it is still zero, return a
    zero vector and ``info["fallback"] = "zero"`` so the caller can draw a prior sample.
    """
    rewards = rewards.reshape(-1)
    info: dict = {"num_samples": int(rewards.numel()), "quantile": quantile, "fallback": None}
    keep = torch.ones_like(rewards, dtype=torch.bool)
    if quantile is not None:
        threshold = torch.quantile(rewards.double(), quantile).to(rewards.dtype)
        keep = rewards >= threshold
    z_raw = (rewards[keep].unsqueeze(-1) * features[keep]).mean(0)
    info["num_kept"] = int(keep.sum())
    if float(z_raw.norm()) < 1e-8 and quantile is not None:
        log.warning("inferred z is ~0 with the %.3g reward quantile filter; retrying without it", quantile)
        z_raw = (rewards.unsqueeze(-1) * features).mean(0)
        info["fallback"] = "no_filter"
        info["num_kept"] = int(rewards.numel())
    if float(z_raw.norm()) < 1e-8:
        info["fallback"] = "zero"
        return torch.zeros_like(z_raw), info
    return project_to_sphere(z_raw), info


class FBModel(Model):
    """A pre-trained FB agent: the actor ``pi(s, z)``, the forward map F and the backward map B, and
    their inference: ``z_r`` from reward-labelled samples (§8.2), ``z`` of a goal, the skill value
    ``Q_M = min_k F_k . z``, and B's features of transitions (reward mapping, §9.4)."""

    name = "fb"
    learns_skill_value = True
    has_statistics = True

    # The representation's targets: (online module's name, its target's name), what a learner EMAs.
    TARGETS = (("forward_map", "forward_target"), ("backward_map", "backward_target"))

    def __init__(self, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu",
                 perf: PerfConfig | None = None):
        super().__init__()
        self.obs_dim, self.action_dim, self.config = obs_dim, action_dim, config
        c = config
        self.skill = SkillSpec("sphere", c.z_dim, every=c.skill_every)
        self.settings = TrainingSettings.of(c)
        self.actor = Actor(obs_dim, c.z_dim, action_dim, c.hidden_dim, c.feature_dim, c.actor_arch)
        self.build_representation(config)  # after the actor: the networks initialise in this order
        self.device = torch.device(device)
        self.to(self.device)
        self.net_runner = NetRunner(perf, self.device)

    def build_representation(self, config: FBConfig) -> None:
        """The networks beside the actor: F and B (the successor features: psi and phi)."""
        c = config
        if c.backward_input not in BACKWARD_INPUTS:
            raise ValueError(f"backward_input must be one of {BACKWARD_INPUTS}, got {c.backward_input!r}")
        backward_in = self.obs_dim if c.backward_input == "state" else 2 * self.obs_dim
        self.forward_map = ForwardMap(self.obs_dim, self.action_dim, c.z_dim, c.hidden_dim, c.feature_dim)
        self.backward_map = BackwardMap(backward_in, c.backward_hidden_dim, c.z_dim)

    def snapshot_modules(self) -> dict[str, nn.Module]:
        return {"actor": self.actor, "forward_map": self.forward_map, "backward_map": self.backward_map}

    # Backward-map inputs (D1) -----------------------------------------------------------------
    def label_input(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """B's input for skill labels, z inference and reward mapping: s' or (s, s') (D1 c)."""
        if self.config.backward_input == "state":
            return next_obs
        return torch.cat([obs, next_obs], dim=-1)

    @torch.no_grad()
    def backward_features(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """Online B of transitions, as used for inference and reward mapping (§8.2, §9.4)."""
        return self.backward_map(self.label_input(obs, next_obs))

    # Zero-shot inference ------------------------------------------------------------------------
    @torch.no_grad()
    def infer_skill(self, obs: torch.Tensor, next_obs: torch.Tensor, reward: torch.Tensor,
                    inference) -> tuple[torch.Tensor, dict]:
        """z_r from reward-labelled transitions (§8.2) with the protocol's reward quantile; a prior
        draw if the rewards give no direction."""
        features = self.backward_features(obs, next_obs)
        z, info = infer_z_from_rewards(features, reward, inference.reward_quantile)
        if info["fallback"] == "zero":
            log.warning("inferred z is zero (all rewards 0?): falling back to a random z ~ p(z)")
            z = self.sample_skill(1)[0]
            info["fallback"] = "prior"
        return z, info

    @torch.no_grad()
    def data_statistics(self, obs: torch.Tensor, next_obs: torch.Tensor, member: int | None = None
                        ) -> dict[str, torch.Tensor]:
        """``Cov(B) = B^T B / n`` (float64) of the transitions' B features: the metric of the
        features ``phi = Cov^-1 B`` that online task inference regresses rewards on."""
        if self.members:  # a group's stacked networks read every member's copy of the rows
            obs = obs.expand(self.members, *obs.shape)
            next_obs = next_obs.expand(self.members, *next_obs.shape)
        features = self.backward_features(obs, next_obs).double()
        cov = features.mT @ features / features.shape[-2]
        return {"cov_backward": (cov if member is None else cov[member]).cpu()}

    @torch.no_grad()
    def skill_from_goal(self, goal_obs: torch.Tensor) -> torch.Tensor:
        """z = proj(B(goal)) for a goal state (state mode) or goal transition (pair modes)."""
        goal = goal_obs.reshape(1, -1).to(self.device, torch.float32)
        if self.config.backward_input != "state" and goal.shape[-1] == self.obs_dim:
            goal = torch.cat([goal, goal], dim=-1)  # a goal "transition" that stays at the goal
        return project_to_sphere(self.backward_map(goal))[0]

    def goal_widths(self) -> tuple[int, ...]:
        # B's pair inputs also take a goal transition (s, s').
        return (self.obs_dim,) if self.config.backward_input == "state" else (self.obs_dim, 2 * self.obs_dim)

    @torch.no_grad()
    def skill_value(self, obs: torch.Tensor, action: torch.Tensor, z: torch.Tensor,
                    task: torch.Tensor | None = None) -> torch.Tensor:
        """``min_k F_k(s, a, z) . z_task`` (``Q_M`` when the task is z itself) for evaluation and analysis."""
        zz = z.expand(obs.shape[0], -1) if z.dim() == 1 else z
        tt = zz if task is None else (task.expand(obs.shape[0], -1) if task.dim() == 1 else task)
        return skill_values(self.forward_map(obs, action, zz), tt).amin(0)

    def nonfinite_hint(self, metric_names: list[str]) -> str:
        if any("implicit_reward" in k for k in metric_names):
            return ("the implicit reward B Cov(B)^-1 z is not finite: Cov(B) is singular or ill-conditioned, add "
                    "a ridge with --fb.cov-ridge 1e-6 (or larger)")
        return ""


@dataclass
class FBStep:
    """What one update has computed so far, handed to the components: the batch, the training z's,
    the target policy's next actions, the online B of the batch (with its graph), the target B's
    input, B's detached labels of the transitions, and F at the batch's actions once the
    representation loss has it (with its graph)."""

    batch: Batch
    z: torch.Tensor
    next_action: torch.Tensor
    backward: torch.Tensor | None = None
    target_input: torch.Tensor | None = None
    labels: torch.Tensor | None = None
    forward: torch.Tensor | None = None
    extra: dict = field(default_factory=dict)


class FBComponent:
    """A part of an FB-family learner that a variant composes (DVFB's exploration critic, the
    conservative penalties of VC-FB and MC-FB). Every hook is optional.

    :meth:`build` makes its networks after the model's and the targets (so that initialisation draws
    in that order) and registers them on the learner under their names (the learner's state stays
    flat); :meth:`optimizers` makes its optimisers after the learner's. In an update:
    :meth:`before_representation` runs after the training z's and B's labels are drawn (DVFB trains
    its reward modules and Q_P there); :meth:`representation_terms` adds losses computed from the
    step's F and B; :meth:`representation_objective` weighs them into what the representation's
    optimiser minimises; :meth:`actor_bonus` adds a per-sample term to the actor's objective.
    """

    def build(self, learner: FBAgent) -> None:
        pass

    def optimizers(self, learner: FBAgent) -> dict[str, torch.optim.Optimizer]:
        return {}

    def target_pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        return []

    def update_networks(self) -> list[nn.Module]:
        return []

    def actor_frozen(self) -> list[nn.Module]:
        """Networks the actor loss differentiates through, but only with respect to the action."""
        return []

    def before_representation(self, learner: FBAgent, step: FBStep, metrics: dict) -> None:
        pass

    def representation_terms(self, learner: FBAgent, step: FBStep) -> dict[str, torch.Tensor]:
        return {}

    def representation_objective(self, learner: FBAgent, objective: torch.Tensor, losses: dict,
                                 metrics: dict) -> torch.Tensor:
        return objective

    def actor_bonus(self, learner: FBAgent, obs: torch.Tensor, z: torch.Tensor, action: torch.Tensor,
                    skill_value: torch.Tensor, metrics: dict) -> torch.Tensor | None:
        return None


class FBAgent(Agent):
    """Online (or offline) FB: reward-free pre-training of F, B and pi(s, z) (docs/methods.md §7
    with alpha = 0), and of every variant that composes :class:`FBComponent` s."""

    name = "fb"
    model_cls: type[FBModel] = FBModel

    @classmethod
    def config_section(cls, config):
        """The run config's section of the family's hyper-parameters."""
        return config.fb

    @classmethod
    def components(cls, config) -> list[FBComponent]:
        """The components the method composes, from its run config (FB: none)."""
        return []

    @classmethod
    def from_config(cls, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu") -> FBAgent:
        return cls(obs_dim, action_dim, cls.config_section(config), device, config.perf, cls.components(config))

    @classmethod
    def model_from_config(cls, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu") -> FBModel:
        return cls.model_cls(obs_dim, action_dim, cls.config_section(config), device, config.perf)

    def __init__(self, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu",
                 perf: PerfConfig | None = None, components: list[FBComponent] = ()):
        super().__init__()
        self.config = config
        self.adopt(self.make_model(obs_dim, action_dim, config, device, perf))
        model = self.model
        for online, target in model.TARGETS:
            self.add_module(target, make_target(getattr(model, online)))
        self.parts = list(components)
        for part in self.parts:
            part.build(self)
        self.to(model.device)
        optimizers = self.make_optimizers()
        optimizers["actor_optimizer"] = adam(self.actor.parameters(), config.lr, config.fused_adam)
        for part in self.parts:
            optimizers.update(part.optimizers(self))
        self.optimizer_names = list(optimizers)
        for name, optimizer in optimizers.items():
            setattr(self, name, optimizer)
        # All (target, online) parameter pairs, EMA-updated by one fused call per update (§3.5).
        pairs = [(t, o) for tm, om in self.target_pairs() for t, o in zip(tm.parameters(), om.parameters())]
        self._ema_target_params = [t for t, _ in pairs]
        self._ema_online_params = [o for _, o in pairs]
        frozen = [self.forward_map] + [m for part in self.parts for m in part.actor_frozen()]
        self._actor_frozen_params = [p for m in frozen for p in m.parameters()]
        self.net_runner.compile(self.update_networks())

    def make_model(self, obs_dim: int, action_dim: int, config, device, perf) -> FBModel:
        """The model the learner trains (a variant with more than FB's section overrides this)."""
        return self.model_cls(obs_dim, action_dim, config, device, perf)

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """The representation's optimiser (FB: one for F and B, B at ``backward_lr_coef`` times lr)."""
        c = self.config
        return {"fb_optimizer": adam([{"params": self.forward_map.parameters()},
                                      {"params": self.backward_map.parameters(), "lr": c.lr * c.backward_lr_coef}],
                                     lr=c.lr, fused=c.fused_adam)}

    def target_pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        """(target, online) networks that follow their online network by EMA after every update."""
        own = [(getattr(self, target), getattr(self, online)) for online, target in self.model.TARGETS]
        return own + [pair for part in self.parts for pair in part.target_pairs()]

    def update_networks(self) -> list[nn.Module]:
        """Every network the update calls (what ``perf.compile`` compiles)."""
        own = [self.actor, self.forward_map, self.backward_map, self.forward_target, self.backward_target]
        return own + [m for part in self.parts for m in part.update_networks()]

    # Skills, replay and acting ---------------------------------------------------------------------
    @property
    def policy_stddev(self) -> float:
        return self.config.stddev

    def replay_needs(self) -> ReplayNeeds:
        return ReplayNeeds(self.config.batch_size, self.config.discount, nstep=1,
                           need_future=self.config.backward_input == "code_exact")

    # Backward-map inputs (D1) -----------------------------------------------------------------
    def backward_inputs(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """The (online, target) inputs of B for the columns of the FB loss."""
        mode = self.config.backward_input
        if mode == "state":
            return batch.next_obs, batch.next_obs
        if mode == "transition":
            pair = torch.cat([batch.obs, batch.next_obs], dim=-1)
            return pair, pair
        # code_exact (D1 a): online B(s_t, s_{t+2}), target B(s_{t+1}, s_{t+2}).
        if batch.future_obs is None:
            raise ValueError("backward_input='code_exact' needs batches sampled with need_future=True")
        return (torch.cat([batch.obs, batch.future_obs], dim=-1),
                torch.cat([batch.next_obs, batch.future_obs], dim=-1))

    @torch.no_grad()
    def training_z(self, batch: Batch) -> torch.Tensor:
        """Prior z's with a ``mix_ratio`` share replaced by projected B of replay data (§5.3)."""
        c = self.config
        n = batch.obs.shape[-2]
        z = sample_z_prior(n, c.z_dim, self.device, self.generator)
        if c.mix_ratio <= 0:
            return z
        perm = randperm(n, self.generator, self.device)
        if c.backward_input == "state":
            goal_input = take_rows(batch.obs, perm)
        elif c.backward_input == "transition":
            goal_input = torch.cat([take_rows(batch.obs, perm), take_rows(batch.next_obs, perm)], dim=-1)
        else:  # code_exact (D1 b): pairs of unrelated states
            goal_input = torch.cat([batch.obs, take_rows(batch.obs, perm)], dim=-1)
        goals = project_to_sphere(self.net_runner(self.backward_map, goal_input))
        replace = rand((n, 1), self.generator, self.device) < c.mix_ratio
        return torch.where(replace, goals, z)

    # The update ---------------------------------------------------------------------------------
    def prepare(self, batch: Batch) -> FBStep:
        """The update's first part (§7.2): the training z's, the target policy's next actions, the
        online B of the batch and B's detached labels."""
        c = self.config
        run = self.net_runner
        z = self.training_z(batch)
        with torch.no_grad():
            next_action = training_action(run(self.actor, batch.next_obs, z), c.stddev, c.stddev_clip, self.generator)
        online_input, target_input = self.backward_inputs(batch)
        backward = run(self.backward_map, online_input)  # reused by the FB, Q and ortho losses
        if c.backward_input == "code_exact":
            with torch.no_grad():
                labels = run(self.backward_map, self.model.label_input(batch.obs, batch.next_obs))
        else:
            labels = backward.detach()
        return FBStep(batch, z, next_action, backward, target_input, labels)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        """One full pre-training update in the order of §7.2. Returns detached metric tensors."""
        metrics: dict[str, torch.Tensor] = {}
        step = self.prepare(batch)
        for part in self.parts:
            part.before_representation(self, step, metrics)
        self.representation_step(step, metrics)
        self._actor_step(batch.obs, step.z, metrics)
        self.soft_update_targets()
        return metrics

    def representation_step(self, step: FBStep, metrics: dict) -> None:
        """One step of the representation's optimiser on its losses and the components' terms."""
        losses = self.representation_losses(step)
        for part in self.parts:
            losses.update(part.representation_terms(self, step))
        objective = losses[self.objective_key]
        for part in self.parts:
            objective = part.representation_objective(self, objective, losses, metrics)
        minimise(getattr(self, self.representation_optimizer), objective)
        metrics.update({k: v.detach() for k, v in losses.items()})

    # What the representation step minimises: the loss of that name, with the representation's optimiser.
    objective_key = "fb_total"
    representation_optimizer = "fb_optimizer"

    @torch.no_grad()
    def soft_update_targets(self) -> None:
        """EMA of every target network (§3.5), one fused call over all their parameters."""
        torch._foreach_lerp_(self._ema_target_params, self._ema_online_params, self.config.tau)

    def representation_losses(self, step: FBStep) -> dict[str, torch.Tensor]:
        """The representation's losses: FB's (:meth:`fb_losses`), F at the batch's actions kept in
        ``step.forward`` for the components."""
        return self.fb_losses(step.batch, step.z, step.next_action, step.backward, step.target_input, step)

    def fb_losses(self, batch: Batch, z: torch.Tensor, next_action: torch.Tensor, backward: torch.Tensor,
                  target_input: torch.Tensor, step: FBStep | None = None) -> dict[str, torch.Tensor]:
        """FB loss (§7.8), auxiliary Q loss (§7.9) and orthonormality loss (§7.10)."""
        c = self.config
        run = self.net_runner
        discount = batch.discount  # (N, 1): scales row i
        with torch.no_grad():
            target_forward = run(self.forward_target, batch.next_obs, next_action, z)  # (2, N, d)
            target_backward = run(self.backward_target, target_input)  # (N, d)
            # A group's tensors carry a leading member axis: the head axis is always -3 here.
            heads = self.members
            target_m = row_products(target_forward, target_backward, heads).amin(-3)  # (N, N)
        forward = run(self.forward_map, batch.obs, batch.action, z)  # (2, N, d)
        if step is not None:
            step.forward = forward
        m = row_products(forward, backward, heads)  # (2, N, N)
        offdiag = offdiag_mean((m - with_head_axis(discount * target_m, heads)).pow(2))  # (2,)
        diag = m.diagonal(dim1=-2, dim2=-1).mean(-1)  # (2,)
        fb_loss = (0.5 * offdiag - diag).sum(-1)

        ortho_loss = orthonormality_loss(backward, self.members)
        losses = {"fb_loss": fb_loss, "fb_offdiag": offdiag.mean(-1), "fb_diag": diag.mean(-1),
                  "ortho_loss": ortho_loss}
        total = fb_loss + c.ortho_coef * ortho_loss
        if c.q_loss:
            with torch.no_grad():
                reward = implicit_reward(backward.detach(), z, c.cov_ridge)
                next_q = skill_values(target_forward, z).amin(-2)
                target_q = reward + discount.squeeze(-1) * next_q
            q = skill_values(forward, z)  # (2, N)
            q_loss = (q - with_head_axis(target_q, heads)).pow(2).mean(-1).sum(-1)
            losses["fb_q_loss"] = q_loss
            # Logged so that a singular Cov(B) is named as such when the metrics are read back (D19).
            losses["implicit_reward"] = member_mean(reward, self.members)
            total = total + c.q_loss_coef * q_loss
        losses["fb_total"] = total
        return losses

    def actor_loss(self, obs: torch.Tensor, z: torch.Tensor, metrics: dict) -> torch.Tensor:
        """``-mean(Q_M + bonus)`` with ``Q_M = min_k F_k(s, a~, z) . z`` (§7.11)."""
        c = self.config
        run = self.net_runner
        action = training_action(run(self.actor, obs, z), c.stddev, c.stddev_clip, self.generator)
        skill_value = skill_values(run(self.forward_map, obs, action, z), z).amin(-2)
        objective = skill_value
        for part in self.parts:
            bonus = part.actor_bonus(self, obs, z, action, skill_value, metrics)
            if bonus is not None:
                objective = objective + bonus
        metrics["skill_value"] = member_mean(skill_value.detach(), self.members)
        return -member_mean(objective, self.members)

    def _actor_step(self, obs: torch.Tensor, z: torch.Tensor, metrics: dict) -> None:
        # F (and Q_P) are differentiated only with respect to the action: excluding their
        # parameters from autograd keeps their weight-only branches out of the graph.
        with requires_grad_disabled(self._actor_frozen_params):
            loss = self.actor_loss(obs, z, metrics)
        # Only the actor's leaves receive gradients: F and the critics are not touched (§7.11).
        minimise(self.actor_optimizer, loss, inputs=list(self.actor.parameters()))
        metrics["actor_loss"] = loss.detach()

    # Checkpointing -------------------------------------------------------------------------------
    def pretrained_modules(self) -> dict[str, nn.Module]:
        """What fine-tuning and zero-shot need from pre-training (§7.1, §9.1), and the targets."""
        return {"actor": self.actor, "forward_map": self.forward_map, "backward_map": self.backward_map,
                "forward_target": self.forward_target, "backward_target": self.backward_target}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {name: getattr(self, name) for name in self.optimizer_names}


# Registration (beside the agent).
from dvfb.agents.registry import AgentSpec, config_field, register  # noqa: E402


def fb_finetune_label(name: str, finetune) -> str:
    """The fine-tuning ablations of the FB family: ``_wo_svf`` (eta = 0), ``_wo_map`` (no mapping)."""
    if finetune is not None:
        if float(config_field(finetune, "eta", 0.5)) == 0.0:
            name += "_wo_svf"
        if not config_field(finetune, "reward_mapping", True):
            name += "_wo_map"
    return name


# Widths and batch of the CPU-sized preset (docs/results/cpu_experiment.md): the method's constants
# are kept, only the networks shrink so that one update costs tens of milliseconds on 2 cores.
FB_SMALL = {"hidden_dim": 256, "feature_dim": 128, "backward_hidden_dim": 256, "batch_size": 256}

register(AgentSpec(
    name="fb", agent_cls=FBAgent, family="forward-backward",
    summary="online FB: successor measures F.B, actor maximising F(s, a, z).z (Touati et al.)",
    sections={"fb": FBConfig}, zero_shot="reward_inference", finetuner="dual_value",
    # Configs written before the registry carried DVFB's exploration section, unused by FB.
    moved_fields={"update_z_every": "fb.skill_every", "exploration": None},
    presets={"small": {"fb": FB_SMALL}, "code": {"fb": {"backward_input": "code_exact"},
                                                 "finetune": {"qf_coef": 50.0, "eta": 1.0}}},
    label=lambda run, finetune: fb_finetune_label("fb", finetune), column=1))
