"""The two protocol interfaces and their registries (docs/methods.md, "Protocols").

A method's :class:`~dvfb.agents.registry.AgentSpec` names one zero-shot protocol and one
fine-tuner; each is a registered class with its own typed config, which becomes the run config's
``inference`` and ``finetune`` section. Workflows, ``dvfb.load``, the CLI and the analyses call the
protocol; none of them knows which family it serves.

* :class:`ZeroShotProtocol` -- turns a pre-trained model and a task into the skill its policy is
  evaluated with (or None for a single policy), owning its data collection and its result fields;
* :class:`Finetuner` -- trains a pre-trained model on a task's reward: its updates, its replay
  needs, the rollout skill of every step, and its resumable state;
* :class:`FinetuneSchedule` -- the budget and schedule every fine-tuner's config shares.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from dvfb.agents.registry import get_spec
from dvfb.core.config import param, require_updates
from dvfb.core.errors import ConfigError
from dvfb.nets.learner import Learner, ReplayNeeds

# Where the skill of a task can come from: interaction with the task (every protocol), samples of
# states with rewards computed by a function or relabelled from a dataset's physics, or a goal
# state (protocols that infer skills).
SKILL_SOURCES = ("rewards", "reward_fn", "dataset", "goal")
# What a protocol without a source lacks, as its refusal says it (docs/methods.md, "Protocols").
_SOURCE_INFERENCE = {"rewards": "inference from the task's rewards",
                     "reward_fn": "inference from a reward function (--skill-source reward_fn)",
                     "dataset": "inference from a relabelled dataset (--skill-source dataset)",
                     "goal": "goal inference (--skill-source goal)"}


class ZeroShotProtocol:
    """Base class of the zero-shot protocols. A subclass sets ``name``, ``config_cls`` and
    ``sources`` and implements :meth:`task_skill` (and :meth:`skill_from_samples` /
    :meth:`skill_from_goal` when ``sources`` lists them)."""

    name: ClassVar[str] = ""
    config_cls: ClassVar[type]
    sources: ClassVar[tuple[str, ...]] = ("rewards",)

    def __init__(self, config: Any):
        self.config = config

    @property
    def eval_episodes(self) -> int:
        return self.config.eval_episodes

    def task_steps(self, source: str = "rewards") -> int:
        """Environment steps in the task before the evaluation (for progress bars)."""
        return 0

    @classmethod
    def check_source(cls, source: str, agent_name: str) -> None:
        """Refuse a skill source the protocol has no inference from, saying what the method lacks
        (a class method: checked before the ``--inference.*`` options, which differ by protocol)."""
        if source not in SKILL_SOURCES:
            raise ConfigError(f"skill source must be one of {SKILL_SOURCES}, got {source!r}")
        if source in cls.sources:
            return
        lacks = _SOURCE_INFERENCE[source]
        if cls.sources == ("rewards",) and cls.name == "single_policy":
            raise ConfigError(f"{agent_name!r} has no {lacks}: it has a single policy and no skill to infer "
                              "(leave out --skill-source)")
        raise ConfigError(f"{agent_name!r} has no {lacks}: its {cls.name} protocol finds the skill from "
                          f"--skill-source {', '.join(cls.sources[:-1])} or {cls.sources[-1]}")

    def task_skill(self, model, env, rng: np.random.Generator, episode_length: int, *, progress=None,
                   keep_data: bool = False) -> tuple[torch.Tensor | None, dict]:
        """The skill for the task of ``env`` from interaction with it, and what the result file
        records about how it was found."""
        raise NotImplementedError

    def skill_from_samples(self, model, obs: torch.Tensor, next_obs: torch.Tensor,
                           reward: torch.Tensor) -> tuple[torch.Tensor, dict]:
        raise ConfigError(f"the {self.name} protocol does not infer a skill from reward samples")

    def skill_from_goal(self, model, goal: np.ndarray) -> tuple[torch.Tensor, dict]:
        raise ConfigError(f"the {self.name} protocol does not infer a skill from a goal")


@dataclass
class FinetuneSchedule:
    """Budget and schedule of a fine-tuning run (§9 of docs/methods.md; URLB protocol)."""

    frames: int = param(100_000, "Fine-tuning environment steps (the inference steps are not counted).", at_least=1)
    eval_every: int = param(10_000, "Evaluate every this many fine-tuning steps (and at 0 and the end).", at_least=1)
    eval_episodes: int = param(50, "Mean-action episodes per evaluation.", at_least=1)
    seed_frames: int = param(4000, "Steps before the first update (uniform actions where the family uses "
                             "them: URLB-style agents; FB-family agents act with pi(s, z_r)).", at_least=0)
    update_every: int = param(2, "One update every this many steps.", at_least=1)
    replay_capacity: int = param(1_000_000, "Fine-tuning replay capacity in transitions.", at_least=1)
    checkpoint_every: int = param(10_000, "Write a resume checkpoint every this many steps (at episode ends).",
                                  at_least=1)

    def check(self) -> None:
        require_updates("--finetune.frames", self.frames, "--finetune.seed-frames", self.seed_frames)

    def first_update(self) -> int:
        """The step of the first update: after the seed frames (a fine-tuner may wait longer)."""
        return self.seed_frames


class Finetuner(Learner):
    """Base class of the fine-tuners: built as ``cls(model, skill, config)`` from the pre-trained
    model (:class:`~dvfb.agents.base.Model`) and the skill its zero-shot protocol found (None for a
    single policy). A fine-tuner is the learner of fine-tuning (:class:`~dvfb.nets.learner.Learner`,
    whose hooks it shares with the agents of pre-training): it owns its networks and optimisers and
    trains the model's actor. The model is one of its modules, so the default resume state
    (:meth:`~dvfb.nets.learner.Learner.training_state`) holds the model's networks and the
    fine-tuner's own, and its optimisers' states.

    ``uniform_seed_actions``: act uniformly during ``seed_frames`` (URLB) or with the policy from
    the first step (the FB family). :meth:`rollout_skill` gives the skill of every step (fixed by
    default); :meth:`keeps_inference_data` says whether the zero-shot protocol's data seed the
    fine-tuning replay. Every network call of an update goes through the model's ``net_runner``
    (``--perf.*``); :meth:`update_networks` lists what ``perf.compile`` compiles.
    """

    name: ClassVar[str] = ""
    config_cls: ClassVar[type] = FinetuneSchedule
    uniform_seed_actions: ClassVar[bool] = True
    # The registered fine-tuners this one may be chosen instead of (``--protocol``): a method whose
    # fine-tuner is listed here may use this one too (test-time search stands in for dual-value).
    replaces: ClassVar[tuple[str, ...]] = ()
    # Whether the method's zero-shot protocol finds the starting skill first (False: the fine-tuner
    # starts from no labelled data and is built with skill None, as task inference online is).
    infers_skill: ClassVar[bool] = True
    # Whether the return of every training episode goes into the curve file (protocols whose
    # claim is about tens of episodes of interaction: their per-episode curve in the report).
    records_episodes: ClassVar[bool] = False

    def __init__(self, model, skill: torch.Tensor | None, config: Any):
        super().__init__()
        self.model, self.config = model, config
        # A buffer, so that a group's fine-tuner stacks its members' skills (docs/members.md).
        self.register_buffer("skill", None if skill is None else skill.detach().clone().to(model.device))

    def update_networks(self) -> list[nn.Module]:
        """Every network the update calls (what ``perf.compile`` compiles)."""
        return []

    def compile(self) -> None:
        """Compile :meth:`update_networks` where ``perf.compile`` asks for it (after construction)."""
        self.net_runner.compile(self.update_networks())

    @classmethod
    def check_group(cls, config: Any) -> None:
        """Refuse options a group cannot fine-tune in lockstep (one line, ConfigError)."""

    @classmethod
    def keeps_inference_data(cls, config: Any) -> bool:
        return False

    @classmethod
    def replays_inference_data(cls, config: Any) -> bool:
        """Whether the kept inference data seed the fine-tuning replay; if not, the workflow hands
        them to :meth:`bind_inference_data` alone."""
        return True

    def bind_inference_data(self, data) -> None:
        """The zero-shot protocol's labelled data (a replay buffer) of a fresh run, kept apart from
        the fine-tuning replay (:meth:`replays_inference_data` false)."""

    @classmethod
    def check(cls, model, config: Any) -> None:
        """Refuse options that do not fit the model, before any work (one line, ConfigError)."""

    @classmethod
    def label(cls, config: Any) -> str:
        """What a report appends (after ``+``) to the method's name for a run of this fine-tuner
        chosen by ``--protocol``: its name, or its variant's (``lola``, ``rela``)."""
        return cls.name

    def rollout_skill(self, step: int, episode_start: bool, current: torch.Tensor | None,
                      generator: torch.Generator | None = None, obs: np.ndarray | None = None
                      ) -> torch.Tensor | None:
        """The skill to act with at ``step``; ``current`` is the one of the previous step, ``obs``
        the observation the step's action is chosen at (a group's: its member's)."""
        return self.skill

    def bind_replay(self, replay) -> None:
        """The fine-tuning replay, for fine-tuners whose rollout skill is computed from it."""

    @classmethod
    def needs_of(cls, model) -> ReplayNeeds:
        """How the fine-tuner of ``model`` samples its replay (:class:`~dvfb.nets.learner.ReplayNeeds`),
        known before it is built (the checks of a fine-tuning)."""
        raise NotImplementedError

    def replay_needs(self) -> ReplayNeeds:
        return self.needs_of(self.model)


# How a method's task reward is linear in features, read from its registered zero-shot protocol (for
# the protocols that search or infer z from rewards): "measure" -- FB and its variants, whose reward
# of z is B . Cov(B)^-1 z (features Cov^-1 B; the least-squares vector E[r B]); "regression" -- the
# successor features, whose reward of z is phi . z (features phi; a regression of r on phi).
REWARD_FEATURES = {"reward_inference": "measure", "feature_regression": "regression"}


def reward_features(model) -> str | None:
    """``"measure"``, ``"regression"`` or None (a method whose skills are not linear in reward features)."""
    try:
        return REWARD_FEATURES.get(get_spec(model.name).zero_shot)
    except ConfigError:
        return None


ZERO_SHOT_PROTOCOLS: dict[str, type[ZeroShotProtocol]] = {}
FINETUNERS: dict[str, type[Finetuner]] = {}


def register_zero_shot(cls: type[ZeroShotProtocol]) -> type[ZeroShotProtocol]:
    ZERO_SHOT_PROTOCOLS[cls.name] = cls
    return cls


def register_finetuner(cls: type[Finetuner]) -> type[Finetuner]:
    FINETUNERS[cls.name] = cls
    return cls
