"""Training: the one rollout loop (:mod:`~dvfb.training.rollout`) with its observers and
evaluations, and what watches a training loop: metric windows, the checkpoint schedule, signals,
progress and the run's random streams (docs/methods.md, "Training loop"; docs/architecture.md)."""
