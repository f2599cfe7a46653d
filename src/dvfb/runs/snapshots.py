"""Snapshots of pre-trained agents (``RUN/snapshots/snapshot_<frames>.pt``): writing them, and loading
a run's agent with the checks that keep users from mixing runs (wrong agent, domain, configuration or
shape; missing or corrupt files). Older snapshot formats are read through :mod:`dvfb.runs.migrations`."""

from __future__ import annotations

import torch

from dvfb.agents import Agent, Model, make_model
from dvfb.core.config import to_dict
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.nets.execution import resolve_device
from dvfb.runs.checkpoints import load_snapshot
from dvfb.runs.layout import PretrainRun, snapshot_name
from dvfb.runs.migrations import SNAPSHOT_FORMAT, check_snapshot_format
from dvfb.runs.run_config import PretrainConfig, agent_sections, run_config_from_dict

# Snapshot formats: 1 was written before the agent registry (DVFB/FB only, no "format" key); 2 adds
# the format, the domain, and the agent's full run config for every method.
SNAPSHOT_KIND = "pretrained_agent"


def snapshot_state(agent: Agent | Model, config: PretrainConfig, frames: int, modules: dict | None = None,
                   statistics: dict | None = None) -> dict:
    """A self-describing snapshot: the method's name, its run config, the dims, the format version
    and the state of its pre-trained modules (``modules``: their state dicts, a group member's or a
    model's; given with a :class:`Model`, which has no ``pretrained_modules``), and the statistics
    of its pre-training data (:meth:`~dvfb.agents.base.Model.data_statistics`) where it has any."""
    if modules is None:
        modules = {k: m.state_dict() for k, m in agent.pretrained_modules().items()}
    state = {"kind": SNAPSHOT_KIND, "format": SNAPSHOT_FORMAT, "agent": config.agent, "domain": config.domain,
             "config": to_dict(config), "frames": frames, "obs_dim": agent.obs_dim, "action_dim": agent.action_dim,
             "modules": modules}
    if statistics:
        state["statistics"] = statistics
    return state


def check_snapshot(state: dict, config: PretrainConfig, where: str) -> None:
    """Refuse a snapshot of another method, domain, configuration or format, naming both sides."""
    if state.get("kind") != SNAPSHOT_KIND:
        raise CheckpointError(f"{where} is not a dvfb agent snapshot")
    check_snapshot_format(state, where)
    if state.get("agent") != config.agent:
        raise CheckpointError(f"{where} was written by agent {state.get('agent')!r} but the run is configured for "
                              f"agent {config.agent!r}")
    stored = state.get("config")
    if not isinstance(stored, dict):
        raise CheckpointError(f"{where} has no run config")
    domain = state.get("domain", stored.get("domain"))
    if domain != config.domain:
        raise CheckpointError(f"{where} was trained on domain {domain!r} but the run is configured for domain "
                              f"{config.domain!r}")
    try:
        # Through the same strict reader, so that fields added since the snapshot take their defaults.
        stored_sections = agent_sections(run_config_from_dict(stored, where))
    except ConfigError as exc:
        raise CheckpointError(f"{where}: {exc}") from exc
    wanted = agent_sections(config)
    diffs = [f"{section}.{key}: snapshot {stored_sections[section].get(key)!r}, run {value!r}"
             for section, values in wanted.items() for key, value in values.items()
             if stored_sections[section].get(key) != value]
    if diffs:
        raise CheckpointError(f"{where} was written with another configuration than the run's config.json ("
                              + "; ".join(diffs[:4]) + (" ..." if len(diffs) > 4 else "") + ")")


def load_model(run: PretrainRun, snapshot: int | None = None,
               device: str | torch.device | None = None) -> tuple[Model, int]:
    """The run's model (:class:`~dvfb.agents.base.Model`: no optimiser) from a snapshot (the newest
    by default), through the registry; and the snapshot's frames.

    Raises :class:`CheckpointError` if the run has no snapshot, the snapshot is unreadable, or it
    was written by another method, for another domain or shape, or with another configuration
    than the run's ``config.json``.
    """
    config = run.config
    frames = run.snapshot_frames()
    if not frames:
        raise CheckpointError(f"run {run.path} has no pre-trained snapshot in {run.snapshots_dir}; "
                              "has pre-training finished?")
    if snapshot is None:
        snapshot = frames[-1]
    elif snapshot not in frames:
        raise CheckpointError(f"run {run.path} has no snapshot at {snapshot} frames; available: {frames}")
    state = load_snapshot(run, snapshot_name(snapshot), map_location="cpu")
    where = f"snapshot {run.snapshot_path(snapshot)}"
    check_snapshot(state, config, where)
    device = device if device is not None else resolve_device(config.device)
    return model_from_snapshot(state, config, device, where), snapshot


def model_from_snapshot(state: dict, config: PretrainConfig, device: str | torch.device, where: str) -> Model:
    """Build the snapshot's model (registry) and load its modules; a module of another shape is an
    error that names both shapes."""
    model = make_model(config.agent, state["obs_dim"], state["action_dim"], config, device)
    try:
        model.load_snapshot(state["modules"])
    except (KeyError, RuntimeError) as exc:
        raise CheckpointError(f"{where} does not fit the configured networks: {exc}") from exc
    statistics = state.get("statistics") or {}
    model.statistics = {k: v for k, v in statistics.items() if isinstance(v, torch.Tensor)}
    return model
