"""The zero-shot protocols (docs/methods.md, "Protocols"; §8).

* :class:`RewardInference` (``reward_inference``; FB, DVFB): collect reward-labelled steps in the
  task with prior skills, let the model infer the task's skill from a sample of them
  (:meth:`~dvfb.agents.base.Agent.infer_skill`); also from reward-function samples or a goal;
* :class:`FeatureRegression` (``feature_regression``; the successor features): the same data with
  skills on the pre-training schedule, the skill from a regression of the rewards on the features;
* :class:`SinglePolicy` (``single_policy``; the exploration baselines): no skill, the one policy;
* :class:`SkillSelection` (``skill_selection``; the skill-discovery methods, paper App. C.3): roll
  out a new prior skill every episode for the same budget of reward-labelled steps, with mean
  actions, and keep the skill of the best episode.

Every protocol then evaluates the skill it found with mean actions (the workflow's part).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dvfb.core.config import param
from dvfb.core.errors import ConfigError
from dvfb.data import ReplayBuffer
from dvfb.protocols.base import ZeroShotProtocol, register_zero_shot
from dvfb.training.observers import EpisodeReturns, ProgressCount, ReplayWriter
from dvfb.training.rollout import Lane, Policy, rollout

SELECTION_CANDIDATES = ("completed", "authors")


@dataclass
class InferenceConfig:
    """Zero-shot task inference and evaluation (§8 of docs/methods.md)."""

    steps: int = param(10_000, "Reward-labelled environment steps collected in the task.", at_least=1)
    random_action_steps: int = param(4000, "Of those, the first steps use uniform actions.", at_least=0)
    samples: int = param(10_000, "Transitions drawn from the inference data to infer z_r.", at_least=1)
    with_replacement: bool = param(True, "Draw the inference samples with replacement (authors' code).")
    reward_quantile: float | None = param(0.99, "Keep samples with reward >= this quantile; none = no filter.",
                                          at_least=0, at_most=1)
    eval_episodes: int = param(50, "Mean-action evaluation episodes with the inferred z_r.", at_least=1)

    def check(self) -> None:
        check_uniform_steps(self)


def check_uniform_steps(config) -> None:
    """The uniform-action steps of a collection are part of its steps."""
    if config.random_action_steps > config.steps:
        raise ConfigError(f"--inference.random-action-steps {config.random_action_steps} must be at most "
                          f"--inference.steps {config.steps}")


@dataclass
class PolicyEvaluationConfig:
    """Zero-shot of a method without skills: mean-action episodes of its single policy."""

    eval_episodes: int = param(50, "Mean-action evaluation episodes of the pre-trained policy.", at_least=1)


@dataclass
class SkillSelectionConfig:
    """Zero-shot of the skill-discovery methods: the best of the prior skills tried in the task."""

    steps: int = param(10_000, "Reward-labelled steps in the task: a new prior skill at every episode start, "
                       "mean actions.", at_least=1)
    candidates: str = param("completed", "Which episodes compete: every one completed within the steps, or the "
                            "authors' driver, which never records the episode that ends at the last step "
                            "(9 candidates of 10).", SELECTION_CANDIDATES)
    eval_episodes: int = param(50, "Mean-action evaluation episodes with the selected skill.", at_least=1)


def collect_inference_data(model, env, steps: int, random_action_steps: int, rng: np.random.Generator,
                           max_episode_length: int = 1000, progress=None, skill_schedule: bool = False
                           ) -> ReplayBuffer:
    """``steps`` reward-labelled steps in the task (§8.1), a rollout of the one loop.

    A new skill from the method's prior at every step (or, with ``skill_schedule``, when the
    method's pre-training rule says so: ``model.skill.due``); uniform actions for the first
    ``random_action_steps`` steps, then rollout samples of ``pi(s, skill)``. The buffer holds the
    episodes as they were collected (their boundaries, the environment's discounts, no skill).
    """
    obs_dim = env.observation_space.shape[0]
    action_dim = env.action_space.shape[0]
    buffer = ReplayBuffer(max(steps, max_episode_length), obs_dim, action_dim, z_dim=0,
                          max_episode_length=max_episode_length, device=model.device)

    def skill_rule(step: int, episode_start: bool, current):
        if not skill_schedule or model.skill.due(step, episode_start):
            return model.sample_skill(1)[0]
        return current

    lanes = [Lane(env, rng)]
    policy = Policy(lambda obs, skills: model.act(obs, skills, explore=True), [skill_rule],
                    lambda step: step < random_action_steps)
    observers = [ReplayWriter(lanes, [buffer], store_skill=False)]
    if progress is not None:
        observers.append(ProgressCount(progress, per="transition"))
    rollout(lanes, policy, observers, stop=steps)
    return buffer


def infer_task_vector(model, buffer: ReplayBuffer, config: InferenceConfig) -> tuple[torch.Tensor, dict]:
    """Draw the inference samples from ``buffer`` and let the model infer the task's skill (§8.2)."""
    data = buffer.transitions()
    n = data.obs.shape[0]
    if n == 0:
        raise ConfigError("no reward-labelled transitions to infer z from (inference.steps is 0?)")
    if config.with_replacement:
        index = torch.randint(0, n, (config.samples,), device=data.obs.device, generator=model.generator)
    else:
        index = torch.randperm(n, device=data.obs.device, generator=model.generator)[: config.samples]
    return model.infer_skill(data.obs[index], data.next_obs[index], data.reward[index], config)


def check_finite(name: str, values: torch.Tensor | np.ndarray) -> None:
    """Non-finite rewards or goals would give a NaN skill silently: refuse them with one line."""
    array = values.detach().cpu().numpy() if isinstance(values, torch.Tensor) else np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise ConfigError(f"{name} holds a non-finite value (NaN or inf); the skill would be NaN")


@register_zero_shot
class RewardInference(ZeroShotProtocol):
    """Infer the task's skill from reward-labelled data (FB family, §8)."""

    name = "reward_inference"
    config_cls = InferenceConfig
    sources = ("rewards", "reward_fn", "dataset", "goal")
    skill_schedule = False  # a new prior skill at every collection step (§8.1)

    def task_steps(self, source: str = "rewards") -> int:
        return self.config.steps if source == "rewards" else 0

    def task_skill(self, model, env, rng, episode_length, *, progress=None, keep_data=False):
        buffer = collect_inference_data(model, env, self.config.steps, self.config.random_action_steps, rng,
                                        episode_length, progress=progress, skill_schedule=self.skill_schedule)
        skill, info = infer_task_vector(model, buffer, self.config)
        if keep_data:
            info["buffer"] = buffer
        return skill, info

    def skill_from_samples(self, model, obs, next_obs, reward):
        check_finite("the reward function's output", reward)
        index = torch.randperm(reward.shape[0], device=reward.device, generator=model.generator)[: self.config.samples]
        return model.infer_skill(obs[index], next_obs[index], reward[index], self.config)

    def skill_from_goal(self, model, goal):
        check_finite("--goal", goal)
        return model.skill_from_goal(torch.as_tensor(np.asarray(goal), dtype=torch.float32)), {
            "goal": np.asarray(goal, dtype=float).tolist()}


@dataclass
class RegressionConfig:
    """Zero-shot of the successor-feature family: regress the task reward on the features."""

    steps: int = param(10_000, "Reward-labelled environment steps collected in the task (prior skills on the "
                       "pre-training schedule).", at_least=1)
    random_action_steps: int = param(4000, "Of those, the first steps use uniform actions.", at_least=0)
    samples: int = param(10_000, "Transitions drawn from the collected data for the regression.", at_least=1)
    with_replacement: bool = param(True, "Draw the regression samples with replacement (authors' driver).")
    eval_episodes: int = param(50, "Mean-action evaluation episodes with the inferred z_r.", at_least=1)

    def check(self) -> None:
        check_uniform_steps(self)


@register_zero_shot
class FeatureRegression(RewardInference):
    """Successor features (paper App. C; docs/methods.md, "Successor features"): reward-labelled
    steps with prior skills redrawn on the pre-training schedule, then the model's least-squares
    regression of the rewards on its features gives ``z_r`` (:meth:`~dvfb.agents.base.Agent.infer_skill`)."""

    name = "feature_regression"
    config_cls = RegressionConfig
    sources = ("rewards", "reward_fn", "dataset")
    skill_schedule = True


@register_zero_shot
class SinglePolicy(ZeroShotProtocol):
    """Methods without skills: their one pre-trained policy is the zero-shot policy."""

    name = "single_policy"
    config_cls = PolicyEvaluationConfig

    def task_skill(self, model, env, rng, episode_length, *, progress=None, keep_data=False):
        return None, {"strategy": "single_policy"}


def best_candidate(returns: list[float]) -> int:
    """Index of the highest return (the first of equal ones)."""
    if not returns:
        raise ConfigError("skill selection completed no episode: --inference.steps must cover at least one "
                          "whole episode of the task")
    return int(np.argmax(np.asarray(returns, dtype=np.float64)))


@register_zero_shot
class SkillSelection(ZeroShotProtocol):
    """Skill-discovery methods (paper App. C.3; docs/methods.md, "Protocols"): a new prior skill at
    every episode start, mean actions, for ``steps`` reward-labelled steps; the skill of the best
    episode return is the task's skill. The result records every candidate and the one chosen."""

    name = "skill_selection"
    config_cls = SkillSelectionConfig

    def task_steps(self, source: str = "rewards") -> int:
        return self.config.steps

    def task_skill(self, model, env, rng, episode_length, *, progress=None, keep_data=False):
        # The run's own stream for the candidate skills, derived from its numpy generator.
        generator = torch.Generator(device=model.device).manual_seed(int(rng.integers(2**62)))
        steps = self.config.steps

        def new_skill_per_episode(step: int, episode_start: bool, current):
            return model.sample_skill(1, generator=generator)[0] if episode_start else current

        lanes = [Lane(env)]
        # The authors' driver records an episode when the next one starts, so the episode that
        # ends at the last step is never compared (docs/methods.md, "Protocols").
        completed = self.config.candidates == "completed"
        episodes = EpisodeReturns(lanes, keep_skills=True, accept=lambda step: completed or step < steps)
        observers = [episodes] + ([ProgressCount(progress, per="transition")] if progress is not None else [])
        policy = Policy(lambda obs, skills: model.act(obs, skills, explore=False), [new_skill_per_episode])
        rollout(lanes, policy, observers, stop=steps)
        skills = episodes.skills[0]
        candidates = [{"skill": skill.cpu().tolist(), "return": float(total)}
                      for skill, total in zip(skills, episodes.returns[0])]
        chosen = best_candidate([c["return"] for c in candidates])
        info = {"protocol": self.name, "candidates": candidates, "chosen": chosen,
                "chosen_return": candidates[chosen]["return"], "selection_steps": steps}
        return skills[chosen], info
