"""Test-time search over the skill z of a frozen FB-family model (docs/methods.md, "Latent search";
Sikchi et al. 2025, arXiv 2504.07896): LoLA, or ReLA as an option.

Nothing pre-trained changes: the actor, F and B (SF's psi and phi) stay bit-identical, and only the
skill the policy acts with moves. Both methods start from the zero-shot skill ``z_r`` of the method's
own zero-shot protocol and read the task's reward model ``w_r`` (the unprojected, unfiltered
least-squares reward vector, in reward units) once from the labelled inference steps. LoLA keeps
those steps in its replay (it never samples them); ReLA keeps them apart, so that its replay holds
only its own fine-tuning steps, unless ``rela_inference_replay`` mixes them in.

* **LoLA** (lookahead latent adaptation, the default): a search distribution ``N(mu, sigma^2 I)`` on
  the unit sphere. Every rollout segment (``horizon`` steps, or fewer where an episode ends first)
  acts with its own sample ``z_i = normalize(mu + sigma eps_i)`` (the policy gets ``proj(z_i)``); its
  return is ``R_i = sum_{t<m} gamma^t r_t + gamma^m V_i`` with the frozen terminal value
  ``V_i = min_k F_k(s_m, mean pi(s_m, z_i), z_i) . w``; after ``samples`` segments one Adam step on
  ``mu`` follows the score-function gradient with leave-one-out baselines, and ``mu`` is normalised
  again. The segments are closed, and ``mu`` stepped, in :meth:`LatentSearchFinetuner.rollout_skill`,
  from the rewards the replay holds; :meth:`~LatentSearchFinetuner.update` only reports.
* **ReLA** (residual latent adaptation): ``Q(s, a) = F(s, a, z) . w_r + Q_res(s, a)``, with a small
  twin residual critic trained by TD on ``r - phi(s') . w_r`` and one global z ascending
  ``min_k F_k(s, a~, z) . w_r + min_k Q_res(s, a~)`` through the frozen actor and F, then projected.

Evaluation (the workflow's) acts with mean actions and ``proj(mu)`` (LoLA) or ``proj(z)`` (ReLA).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from dvfb.agents.base import Model, ReplayNeeds
from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from dvfb.nets import (
    TwinCritic,
    adam,
    freeze_,
    make_target,
    project_to_sphere,
    skill_values,
    soft_update_,
    training_action,
    twin_td_loss,
)
from dvfb.nets.members import minimise, randn
from dvfb.protocols.base import REWARD_FEATURES, Finetuner, FinetuneSchedule, register_finetuner, reward_features

METHODS = ("lola", "rela")
TERMINAL_VALUES = ("w_r", "mu", "z", "none")
ROLLOUT_ACTIONS = ("auto", "mean", "sample")

# The reward vector w_r is the unprojected, unfiltered counterpart of the skill the method's own
# zero-shot protocol infers (protocols.base.reward_features): FB's E[r B(s')] (= argmin_w
# E[(r - B Cov^-1 w)^2], the measure M = F B^T rho), or the successor features' regression
# argmin_w E[(r - phi(s') w)^2].


@dataclass
class LatentSearchConfig(FinetuneSchedule):
    """Test-time search over z (LoLA; ReLA as an option) for the FB family: the shared budget and
    schedule, with no seed phase, and the options of docs/methods.md, "Latent search"."""

    seed_frames: int = param(0, "Steps before the first update (the policy acts with its searched z from "
                             "step 0; only ReLA's updates wait for these).", at_least=0)
    replay_capacity: int = param(200_000, "Fine-tuning replay capacity in transitions (the inference steps "
                                 "and every fine-tuning step fit at the default budget).", at_least=1)
    method: str = param("lola", "lola: search N(mu, sigma^2) over z by lookahead returns of rollout segments; "
                        "rela: a residual critic and gradient ascent on one z.", METHODS)
    sigma: float = param(0.2, "LoLA: standard deviation of the search distribution on the unit sphere.", above=0)
    lr: float = param(0.05, "LoLA: Adam learning rate of the search mean mu (renormalised after every step).",
                      above=0)
    horizon: int = param(250, "LoLA: steps per rollout segment H (a segment also ends with its episode).",
                         at_least=1)
    samples: int = param(8, "LoLA: segments (z samples) per update of mu, k (leave-one-out needs 2).", at_least=2)
    terminal_value: str = param("w_r", "LoLA: the reward vector w of the terminal value min F(s_H, pi(s_H, z_i), "
                                "z_i) . w: w_r (the reward model), mu (the search mean on the unit sphere), z "
                                "(the segment's sample z_i on the unit sphere), or none.", TERMINAL_VALUES)
    rollout_actions: str = param("auto", "Actions of the fine-tuning rollouts: mean, sample (the pre-training "
                                 "policy noise), or auto (LoLA mean, ReLA sample).", ROLLOUT_ACTIONS)
    cov_ridge: float = param(0.0, "Ridge added to Cov of the inference features in the reward model "
                             "(ReLA's residual).", at_least=0)
    rela_hidden_dim: int = param(256, "ReLA: hidden width of the twin residual critic Q_res(s, a).", at_least=1)
    rela_lr: float = param(1e-4, "ReLA: Adam learning rate of the residual critic.", above=0)
    rela_z_lr: float = param(1e-4, "ReLA: Adam learning rate of z (projected back to the sphere after every "
                             "step).", above=0)
    rela_tau: float = param(0.005, "ReLA: EMA rate of the residual critic's target.", above=0, at_most=1)
    rela_batch_size: int = param(1024, "ReLA: transitions per update.", at_least=1)
    rela_inference_replay: bool = param(False, "ReLA: also replay the labelled inference steps in its updates; "
                                        "false: its replay holds only the fine-tuning steps (Sikchi et al.), "
                                        "the inference steps give w_r only, and its first update waits for "
                                        "rela_batch_size steps of its own.")

    def uses_inference_replay(self) -> bool:
        """Whether the labelled inference steps are in the fine-tuning replay: LoLA keeps them there
        (it never samples them); ReLA only with ``rela_inference_replay``."""
        return self.method != "rela" or self.rela_inference_replay

    def first_update(self) -> int:
        """ReLA without the inference steps starts from an empty replay: it waits for a batch's worth
        of its own steps, so that its first batches are not a handful of transitions repeated."""
        if self.uses_inference_replay():
            return self.seed_frames
        return max(self.seed_frames, self.rela_batch_size)

    def check(self) -> None:
        super().check()
        if self.frames <= self.first_update():
            raise ConfigError(f"--finetune.frames {self.frames} must be larger than --finetune.rela-batch-size "
                              f"{self.rela_batch_size}: ReLA's replay holds only its own fine-tuning steps and its "
                              "first update waits for a batch of them (or pass --finetune.rela-inference-replay true)")


# ---------------------------------------------------------------------------------------------
# The pieces of the search, as functions (tests/test_latent_search.py checks each by hand)


def leave_one_out(returns: torch.Tensor) -> torch.Tensor:
    """``A_i = R_i - mean_{j != i} R_j = (k R_i - sum_j R_j) / (k - 1)`` over the last axis."""
    k = returns.shape[-1]
    return (k * returns - returns.sum(-1, keepdim=True)) / (k - 1)


def segment_return(rewards, discounts, gamma: float, terminal_value: float) -> float:
    """``sum_{t<m} gamma^t r_t + gamma^m (prod_t d_t) V`` in float64, for a segment of ``m`` steps
    with the environment's discounts ``d_t`` (0 where the episode terminated: no terminal value)."""
    rewards = np.asarray(rewards, dtype=np.float64).reshape(-1)
    discounts = np.asarray(discounts, dtype=np.float64).reshape(-1)
    m = rewards.shape[0]
    # The weight of r_t is gamma^t times the discounts of the steps before it.
    alive = np.concatenate([[1.0], np.cumprod(discounts)[:-1]])
    weights = gamma ** np.arange(m, dtype=np.float64) * alive
    return float(weights @ rewards + gamma ** m * np.prod(discounts) * terminal_value)


def search_loss(mu: torch.Tensor, samples: torch.Tensor, advantages: torch.Tensor, sigma: float) -> torch.Tensor:
    """``mean_i A_i (-log N(z_i; mu, sigma^2 I))`` without the terms that do not depend on mu, i.e.
    ``mean_i A_i ||z_i - mu||^2 / (2 sigma^2)``; its gradient is ``-mean_i A_i (z_i - mu) / sigma^2``."""
    return (advantages * (samples - mu).pow(2).sum(-1)).mean() / (2 * sigma ** 2)


def reward_model(features: torch.Tensor, reward: torch.Tensor, kind: str, ridge: float = 0.0
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The least-squares reward model of labelled transitions ``features (N, d)`` (B or phi of s'),
    ``reward (N,)``, in float64: ``(w_r, coef)`` with ``r ~ features . coef``, where
    ``coef = (Cov + ridge I)^-1 E[r features]`` and ``Cov = features^T features / N``, and ``w_r`` the
    vector the skill value reads (``Q_r = F . w_r``): ``E[r B]`` for the measure ``F B^T rho``
    (``kind = "measure"``, FB, where ``coef = Cov^-1 w_r`` makes ``phi = Cov^-1 B``), ``coef`` for
    successor features (``"regression"``)."""
    features, reward = features.double(), reward.double().reshape(-1)
    n, d = features.shape
    moment = features.T @ reward / n
    cov = features.T @ features / n + ridge * torch.eye(d, dtype=torch.float64, device=features.device)
    coef = torch.linalg.lstsq(cov.cpu(), moment.cpu().unsqueeze(-1), driver="gelsd").solution[:, 0]
    coef = coef.to(features.device)
    return (moment if kind == "measure" else coef), coef


# ---------------------------------------------------------------------------------------------


@register_finetuner
class LatentSearchFinetuner(Finetuner):
    """LoLA (or ReLA) on a pre-trained FB-family model, all of whose networks stay frozen (see the
    module docstring). Chosen with ``--protocol latent_search`` instead of dual-value fine-tuning."""

    name = "latent_search"
    config_cls = LatentSearchConfig
    uniform_seed_actions = False
    replaces = ("dual_value",)
    infers_skill = True
    records_episodes = True

    @classmethod
    def label(cls, config) -> str:
        return config.method if hasattr(config, "method") else config.get("method", "lola")

    def __init__(self, model: Model, z: torch.Tensor, config: LatentSearchConfig):
        nn.Module.__init__(self)
        self.model, self.config = model, config
        self.rela = config.method == "rela"
        settings, device = model.settings, model.device
        for module in model.snapshot_modules().values():  # the actor too: only z moves
            freeze_(module)
        z = z.detach().clone().to(device)
        d = z.shape[-1]
        self.register_buffer("w_r", torch.zeros(d, device=device))
        self.register_buffer("residual_coef", torch.zeros(d, device=device))
        self.register_buffer("reward_model_ready", torch.zeros((), dtype=torch.bool, device=device))
        self.register_buffer("start", z / z.norm())  # mu_0 on the unit sphere: the zero-shot skill's direction
        self._replay = None
        # The evaluation skill, proj(mu) or proj(z): at first the zero-shot skill itself (already on the
        # sphere), so that the curve's point at 0 is the zero-shot policy bit for bit.
        self.register_buffer("skill", z.clone())
        if self.rela:
            self.z = nn.Parameter(project_to_sphere(z))
            self.residual_critic = TwinCritic(model.obs_dim, model.action_dim, 0, config.rela_hidden_dim).to(device)
            self.residual_critic_target = make_target(self.residual_critic)
            self.residual_optimizer = adam(self.residual_critic.parameters(), config.rela_lr, settings.fused_adam)
            self.z_optimizer = adam([self.z], config.rela_z_lr, settings.fused_adam)
            self._rollout_z = self.skill.clone()
        else:
            self.mu = nn.Parameter(self.start.clone())
            self.search_optimizer = adam([self.mu], config.lr, settings.fused_adam)
            self._segment_start: int | None = None  # the step the open segment began at
            self._episode_begin = 0  # the first step of the episode in progress
            self._segment_z: torch.Tensor | None = None  # its sample z_i (unit norm)
            self._segment_skill: torch.Tensor | None = None  # proj(z_i), what the policy gets
            self._pending_z: list[torch.Tensor] = []
            self._pending_returns: list[float] = []
            self._metrics = self._search_metrics(0.0, 0.0, 0)
        self._mean_actions = {"auto": not self.rela, "mean": True, "sample": False}[config.rollout_actions]

    # The fine-tuner's interface ---------------------------------------------------------------
    @classmethod
    def check(cls, model: Model, config: LatentSearchConfig) -> None:
        if not model.learns_skill_value:
            raise ConfigError(f"latent search needs a model with a skill value F . z (the FB family); "
                              f"{model.name!r} has none")
        if reward_features(model) is None:
            raise ConfigError(f"latent search reads a reward vector the way the FB family's zero-shot protocols "
                              f"do ({', '.join(REWARD_FEATURES)}); {model.name!r} uses another")

    @classmethod
    def check_group(cls, config: LatentSearchConfig) -> None:
        raise ConfigError("latent search fine-tunes one run at a time (its segments and search state are the "
                          "run's own): fine-tune the members separately")

    @classmethod
    def keeps_inference_data(cls, config: LatentSearchConfig) -> bool:
        return True  # the labelled inference steps give the reward model w_r

    @classmethod
    def replays_inference_data(cls, config: LatentSearchConfig) -> bool:
        return config.uses_inference_replay()

    @classmethod
    def needs_of(cls, model: Model) -> ReplayNeeds:
        return ReplayNeeds(model.settings.batch_size, model.settings.discount)

    def replay_needs(self) -> ReplayNeeds:
        # LoLA reads its segments' rows itself; its update's batch is never used, so it is one row.
        size = self.config.rela_batch_size if self.rela else 1
        return ReplayNeeds(size, self.model.settings.discount)

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        if self.rela:
            return {"residual_critic": self.residual_optimizer, "z": self.z_optimizer}
        return {"search": self.search_optimizer}

    def update_networks(self) -> list[nn.Module]:
        if self.rela:
            return [self.model.actor, self.model.forward_map, self.residual_critic, self.residual_critic_target]
        return []

    def act(self, obs, skills, explore: bool):
        """The rollouts' actions (``rollout_actions``); evaluations (``explore`` false) act with the mean."""
        return self.model.act(obs, skills, explore and not self._mean_actions)

    @property
    def discount(self) -> float:
        return self.model.settings.discount

    def bind_inference_data(self, data) -> None:
        """The labelled inference episodes kept apart from the replay (ReLA's default): the reward
        model is fitted on all of them, once."""
        if not bool(self.reward_model_ready):
            self._fit_reward_model(data)

    def bind_replay(self, replay) -> None:
        """The fine-tuning replay. Where it holds the labelled inference episodes (LoLA; ReLA with
        ``rela_inference_replay``) and the reward model is not fitted yet, it is fitted on all of
        them, once (a resume loads it from the checkpoint instead)."""
        self._replay = replay
        if not bool(self.reward_model_ready):
            self._fit_reward_model(replay)

    def _fit_reward_model(self, buffer) -> None:
        if len(buffer) == 0:
            raise ConfigError("latent search needs the labelled inference steps; it was given none")
        data = buffer.transitions(gamma=1.0)
        features = self.model.backward_features(data.obs, data.next_obs)
        w_r, coef = reward_model(features, data.reward[:, 0], reward_features(self.model), self.config.cov_ridge)
        if not (torch.isfinite(w_r).all() and torch.isfinite(coef).all()):
            raise ConfigError("the reward model of the inference steps is not finite; add --finetune.cov-ridge 1e-6")
        self.w_r.copy_(w_r.to(self.w_r))
        self.residual_coef.copy_(coef.to(self.residual_coef))
        self.reward_model_ready.fill_(True)

    def rollout_skill(self, step: int, episode_start: bool, current: torch.Tensor | None,
                      generator: torch.Generator | None = None, obs: np.ndarray | None = None) -> torch.Tensor:
        """ReLA: ``proj(z)``. LoLA: the open segment's ``proj(z_i)``; a segment that has run ``horizon``
        steps, or whose episode ended, is closed first (its return joins the pending samples, and the
        k-th one steps mu), and a new one opens with a fresh sample from ``generator``."""
        if self.rela:
            return self._rollout_z
        if self._segment_start is not None and (episode_start or step - self._segment_start >= self.config.horizon):
            self._close_segment(step)
        if episode_start:
            self._episode_begin = step
        if self._segment_start is None:
            self._open_segment(step, generator if generator is not None else self.generator)
        return self._segment_skill

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        if self.rela:
            return self._rela_update(batch)
        return self._metrics  # LoLA's step is made when k segments are complete; these are the last one's

    # LoLA --------------------------------------------------------------------------------------
    def _open_segment(self, step: int, generator: torch.Generator | None) -> None:
        mu = self.mu.detach()
        eps = randn(mu.shape, generator, mu.device, mu.dtype)
        sample = mu + self.config.sigma * eps
        self._segment_z = sample / sample.norm()
        self._segment_skill = project_to_sphere(self._segment_z)
        self._segment_start = step

    def _close_segment(self, step: int) -> None:
        """The return of the segment that ends before ``step``, from the replay's newest rows: the
        segment lies in the episode that began at ``_episode_begin``, which is whole in the replay."""
        steps = step - self._segment_start
        data = self._replay.transitions(gamma=1.0, limit=step - self._episode_begin)
        if data.reward.shape[0] < steps:
            raise RuntimeError(f"the replay holds {data.reward.shape[0]} steps of the episode, the segment has {steps}")
        value = self.terminal_value(data.next_obs[-1], self._segment_z)
        rewards = data.reward[-steps:, 0].double().cpu().numpy()
        discounts = data.discount[-steps:, 0].double().cpu().numpy()
        self._pending_z.append(self._segment_z)
        self._pending_returns.append(segment_return(rewards, discounts, self.discount, value))
        self._segment_start = self._segment_z = self._segment_skill = None
        if len(self._pending_returns) == self.config.samples:
            self.search_step(torch.stack(self._pending_z), torch.tensor(self._pending_returns, dtype=torch.float64))
            self._pending_z, self._pending_returns = [], []

    @torch.no_grad()
    def terminal_value(self, last_obs: torch.Tensor, sample: torch.Tensor) -> float:
        """``V_i = min_k F_k(s_H, mean pi(s_H, z_i), z_i) . w`` with ``w`` as ``terminal_value`` says:
        ``w_r``, ``mu`` or ``z_i`` (both unit vectors), 0 for none; the networks see ``proj(z_i)``."""
        which = self.config.terminal_value
        if which == "none":
            return 0.0
        skill = project_to_sphere(sample).unsqueeze(0)
        obs = last_obs.reshape(1, -1)
        # mu and z_i are read on the unit sphere, as the spec writes them and the public
        # re-implementation does (docs/methods.md, "Latent search"): only the networks see proj(z_i).
        task = {"w_r": self.w_r, "mu": self.mu.detach(), "z": sample}[which]
        action = self.model.actor(obs, skill)
        return float(self.model.skill_value(obs, action, skill, task=task)[0])

    def search_step(self, samples: torch.Tensor, returns: torch.Tensor) -> None:
        """One Adam step on mu from ``samples (k, d)`` (unit vectors) and their returns ``(k,)`` (float64),
        then mu back onto the unit sphere and the evaluation skill ``proj(mu)``."""
        advantages = leave_one_out(returns).to(self.mu.dtype)
        before = self.mu.detach().clone()
        minimise(self.search_optimizer, search_loss(self.mu, samples, advantages, self.config.sigma))
        with torch.no_grad():
            self.mu.div_(self.mu.norm())
            self.skill.copy_(project_to_sphere(self.mu))
            angle = torch.arccos((before @ self.mu).clamp(-1.0, 1.0))
        self._metrics = self._search_metrics(float(returns.mean()), float(angle),
                                             int(self._metrics["search_updates"]) + 1)

    def _search_metrics(self, mean_return: float, angle: float, updates: int) -> dict[str, torch.Tensor]:
        device = self.model.device
        with torch.no_grad():
            cos = (self.mu.detach() @ self.start).clamp(-1.0, 1.0)
        return {"search_return": torch.tensor(mean_return, device=device),
                "search_step_angle": torch.tensor(angle, device=device),
                "search_start_cos": cos.float(),
                "search_updates": torch.tensor(float(updates), device=device)}

    # ReLA --------------------------------------------------------------------------------------
    def residual_target(self, batch: Batch, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(y, r_res)``: ``r_res = r - phi(s') . w_r`` (``phi . w_r = features(s') . coef``) and
        ``y = r_res + gamma d min_k Q_res_target(s', a')`` with ``a'`` a training sample of
        ``pi(s', z)``; ``(N, 1)`` each. ``z`` is ``(N, d)``."""
        settings, run = self.model.settings, self.net_runner
        with torch.no_grad():
            features = self.model.backward_features(batch.obs, batch.next_obs)
            residual = batch.reward - (features @ self.residual_coef).unsqueeze(-1)
            next_action = training_action(run(self.model.actor, batch.next_obs, z), settings.stddev,
                                          settings.stddev_clip, self.generator)
            none = batch.next_obs.new_zeros(batch.next_obs.shape[0], 0)
            next_q = run(self.residual_critic_target, batch.next_obs, none, next_action).amin(-3)
            return residual + batch.discount * next_q, residual

    def _rela_update(self, batch: Batch) -> dict[str, torch.Tensor]:
        settings, run, actor = self.model.settings, self.net_runner, self.model.actor
        n = batch.obs.shape[0]
        none = batch.obs.new_zeros(n, 0)
        target, residual = self.residual_target(batch, self.z.detach().expand(n, -1))
        q = run(self.residual_critic, batch.obs, none, batch.action)
        critic_loss = twin_td_loss(q, target)
        minimise(self.residual_optimizer, critic_loss)

        z = self.z.expand(n, -1)
        action = training_action(run(actor, batch.obs, z), settings.stddev, settings.stddev_clip, self.generator)
        fb_value = skill_values(run(self.model.forward_map, batch.obs, action, z), self.w_r.expand(n, -1)).amin(-2)
        residual_value = run(self.residual_critic, batch.obs, none, action).amin(-3).squeeze(-1)
        objective = (fb_value + residual_value).mean()
        minimise(self.z_optimizer, -objective, inputs=[self.z])
        with torch.no_grad():
            self.z.copy_(project_to_sphere(self.z))
            self.skill.copy_(self.z)
            start_cos = (self.z @ self.start) / math.sqrt(self.z.shape[-1])
        self._rollout_z = self.skill.clone()  # a new tensor: the rollout stores the new skill's copy
        soft_update_(self.residual_critic_target, self.residual_critic, self.config.rela_tau)
        return {"residual_critic_loss": critic_loss.detach(), "residual_reward": residual.mean(),
                "fb_value": fb_value.detach().mean(), "residual_value": residual_value.detach().mean(),
                "z_start_cos": start_cos}

    # Resume --------------------------------------------------------------------------------------
    def _own_state(self) -> dict[str, torch.Tensor]:
        return {k: v for k, v in self.state_dict().items() if not k.startswith("model.")}

    def training_state(self) -> dict:
        state = {"finetuner": self._own_state(),
                 "optimizers": {name: opt.state_dict() for name, opt in self.optimizers().items()}}
        if not self.rela:
            d = self.mu.shape[-1]
            state["search"] = {
                "segment_start": -1 if self._segment_start is None else self._segment_start,
                "episode_begin": self._episode_begin,
                "segment_z": None if self._segment_z is None else self._segment_z.cpu(),
                "pending_z": (torch.stack(self._pending_z) if self._pending_z else torch.zeros(0, d)).cpu(),
                "pending_returns": torch.tensor(self._pending_returns, dtype=torch.float64),
                "metrics": {k: v.cpu() for k, v in self._metrics.items()}}
        return state

    def load_training_state(self, state: dict) -> None:
        own = self._own_state()
        missing = set(own) - set(state["finetuner"])
        if missing:
            raise KeyError(f"fine-tuning checkpoint lacks {sorted(missing)}")
        self.load_state_dict({**self.state_dict(), **state["finetuner"]})
        for name, optimizer in self.optimizers().items():
            optimizer.load_state_dict(state["optimizers"][name])
        if self.rela:
            self._rollout_z = self.skill.clone()
            return
        device = self.model.device
        search = state["search"]
        start = int(search["segment_start"])
        self._segment_start = None if start < 0 else start
        self._episode_begin = int(search["episode_begin"])
        segment = search["segment_z"]
        self._segment_z = None if segment is None else segment.to(device)
        self._segment_skill = None if segment is None else project_to_sphere(self._segment_z)
        self._pending_z = [row.to(device) for row in search["pending_z"]]
        self._pending_returns = [float(r) for r in search["pending_returns"]]
        self._metrics = {k: v.to(device) for k, v in search["metrics"].items()}
