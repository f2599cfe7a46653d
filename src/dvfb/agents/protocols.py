"""Config classes of the downstream protocols a method family chooses (docs/methods.md, "Protocols").

* :class:`InferenceConfig` -- zero-shot by inferring the task's skill from reward-labelled steps
  (FB, DVFB, later the successor-feature family);
* :class:`PolicyEvaluationConfig` -- zero-shot of a method without skills: its one policy;
* :class:`FinetuneProtocol` -- the fine-tuning loop's budget and schedule, shared by every
  family's fine-tuning config (dual-value in :mod:`dvfb.agents.finetune`, URLB-style in
  :mod:`dvfb.agents.ddpg`).
"""

from __future__ import annotations

from dataclasses import dataclass

from dvfb.config import param, require_updates
from dvfb.errors import ConfigError


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
        if self.random_action_steps > self.steps:
            raise ConfigError(f"--inference.random-action-steps {self.random_action_steps} must be at most "
                              f"--inference.steps {self.steps}")


@dataclass
class PolicyEvaluationConfig:
    """Zero-shot of a method without skills: mean-action episodes of its single policy."""

    eval_episodes: int = param(50, "Mean-action evaluation episodes of the pre-trained policy.", at_least=1)


@dataclass
class FinetuneProtocol:
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
