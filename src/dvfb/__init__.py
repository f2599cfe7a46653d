"""dvfb: online unsupervised zero-shot reinforcement learning (DVFB and baselines).

``dvfb.load(run_dir)`` loads a pre-trained agent (:mod:`dvfb.workflows.api`); the ``dvfb`` command runs
everything else.
"""

__version__ = "0.1.0"


def load(run_dir, snapshot=None, device=None):
    """A pre-training run's model, to infer a task's skill and act (:class:`dvfb.workflows.api.PretrainedModel`)."""
    from dvfb.workflows.api import load as _load  # lazy: torch and the agents are imported on first use only

    return _load(run_dir, snapshot, device)
