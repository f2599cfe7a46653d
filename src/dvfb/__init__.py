"""dvfb: online unsupervised zero-shot reinforcement learning (DVFB and baselines)."""

__version__ = "0.1.0"
