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

from dvfb.config import param


@dataclass
class InferenceConfig:
    """Zero-shot task inference and evaluation (§8 of docs/methods.md)."""

    steps: int = param(10_000, "Reward-labelled environment steps collected in the task.")
    random_action_steps: int = param(4000, "Of those, the first steps use uniform actions.")
    samples: int = param(10_000, "Transitions drawn from the inference data to infer z_r.")
    with_replacement: bool = param(True, "Draw the inference samples with replacement (authors' code).")
    reward_quantile: float | None = param(0.99, "Keep samples with reward >= this quantile; none = no filter.")
    eval_episodes: int = param(50, "Mean-action evaluation episodes with the inferred z_r.")


@dataclass
class PolicyEvaluationConfig:
    """Zero-shot of a method without skills: mean-action episodes of its single policy."""

    eval_episodes: int = param(50, "Mean-action evaluation episodes of the pre-trained policy.")


@dataclass
class FinetuneProtocol:
    """Budget and schedule of a fine-tuning run (§9 of docs/methods.md; URLB protocol)."""

    frames: int = param(100_000, "Fine-tuning environment steps (the inference steps are not counted).")
    eval_every: int = param(10_000, "Evaluate every this many fine-tuning steps (and at 0 and the end).")
    eval_episodes: int = param(50, "Mean-action episodes per evaluation.")
    seed_frames: int = param(4000, "Steps before the first update (uniform actions where the family uses "
                             "them: URLB-style agents; FB-family agents act with pi(s, z_r)).")
    update_every: int = param(2, "One update every this many steps.")
    replay_capacity: int = param(1_000_000, "Fine-tuning replay capacity in transitions.")
    checkpoint_every: int = param(10_000, "Write a resume checkpoint every this many steps (at episode ends).")
