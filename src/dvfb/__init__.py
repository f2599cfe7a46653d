"""dvfb: online unsupervised zero-shot reinforcement learning (DVFB and baselines).

``dvfb.load(run_dir)`` loads a pre-trained agent (:mod:`dvfb.workflows.api`); the ``dvfb`` command runs
everything else.
"""

from dvfb.core.version import __version__  # noqa: F401 (the package's version, re-exported)


def load(run_dir, snapshot=None, device=None):
    """A pre-training run's model, to infer a task's skill and act (:class:`dvfb.workflows.api.PretrainedModel`)."""
    # lazy: the API (torch, the agents) takes ~1.5 s to import; `import dvfb` alone takes ~0.2 ms
    from dvfb.workflows.api import load as _load

    return _load(run_dir, snapshot, device)
