"""The task's own reward as a "reward module" (docs/methods.md, "Supervised reference").

The supervised reference is the DDPG core trained on the extrinsic reward; giving that reward the
interface of the intrinsic modules keeps it one more method on the core rather than a second loop.
The replay already stores the task reward of every step, and a batch's ``reward`` is its n-step
discounted sum, which is exactly what URLB's fine-tuner trains on.
"""

from __future__ import annotations

import torch

from dvfb.data import Batch
from dvfb.rewards.base import IntrinsicReward, Runner
from dvfb.nets import call_network


class TaskReward(IntrinsicReward):
    """Scores every row with the stored task reward (n-step sum); learns nothing."""

    def score(self, batch: Batch, run: Runner = call_network) -> torch.Tensor:
        return batch.reward
