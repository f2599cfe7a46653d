"""Intrinsic-reward modules, each on the interface of :class:`~dvfb.rewards.base.IntrinsicReward`
(update on a batch, score a batch), shared by DVFB and the exploration baselines.

* :mod:`~dvfb.rewards.rnd` -- RND novelty;
* :mod:`~dvfb.rewards.contrastive` -- NCE, DVFB's contrastive entropy, CIC;
* :mod:`~dvfb.rewards.knn` -- the particle-based (kNN) entropy estimators;
* :mod:`~dvfb.rewards.disagreement` -- ensemble disagreement;
* :mod:`~dvfb.rewards.icm` -- ICM with the APT (kNN) reward;
* :mod:`~dvfb.rewards.proto` -- Proto-RL's prototypes and queue reward.
"""

from dvfb.rewards.base import IntrinsicReward

__all__ = ["IntrinsicReward"]
