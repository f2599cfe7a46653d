"""Pieces shared by the pretrain / zeroshot / finetune workflows.

* seeding and device set-up;
* :class:`MetricWindow` -- keeps per-update metric tensors on the device and reads them back in one
  host sync every ``log_every`` steps, checking for NaN/inf losses at the same time;
* loading a pre-trained agent from a run directory with the checks that keep users from mixing
  runs (wrong agent, wrong config, missing or corrupt files);
* the progress bar.
"""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from dvfb import envs
from dvfb.agents import Agent, make_agent
from dvfb.config import to_dict
from dvfb.errors import CheckpointError, ConfigError, NonFiniteLossError
from dvfb.runs import RunDir, list_snapshots, load_snapshot
from dvfb.workflows.config import PretrainConfig, agent_sections, load_run_config, resolve_device, run_config_from_dict

SNAPSHOT_PREFIX = "snapshot_"
# Format of agent snapshots. 1: written before the agent registry (DVFB/FB only, no "format"
# key); 2: adds the format, the domain, and the agent's full run config for every method.
SNAPSHOT_FORMAT = 2


def seed_everything(seed: int) -> np.random.Generator:
    """Seed torch and Python; return the numpy Generator the workflow draws uniform actions from."""
    torch.manual_seed(seed)
    random.seed(seed)
    return np.random.default_rng(seed)


def setup_torch(config: PretrainConfig) -> torch.device:
    if config.torch_threads > 0:
        torch.set_num_threads(config.torch_threads)
    return resolve_device(config.device)


def rng_state(generator: np.random.Generator) -> dict:
    return {"torch": torch.get_rng_state(), "python": random.getstate(),
            "numpy": generator.bit_generator.state,
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def restore_rng_state(state: dict, generator: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    random.setstate(state["python"])
    generator.bit_generator.state = state["numpy"]
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class MetricWindow:
    """Per-update metric tensors kept on the device, read back once per window.

    ``flush`` stacks the window into one tensor, copies it to the host (the only sync), raises
    :class:`NonFiniteLossError` naming the first update and loss that went NaN/inf, and returns
    the window means.
    """

    def __init__(self) -> None:
        self.steps: list[int] = []
        self.rows: list[dict[str, torch.Tensor]] = []

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        self.steps.append(step)
        self.rows.append(metrics)

    def flush(self) -> dict[str, float]:
        if not self.rows:
            return {}
        keys = list(self.rows[0])
        table = torch.stack([torch.stack([row[k].float().reshape(()) for k in keys]) for row in self.rows])
        values = table.cpu().numpy()
        steps, self.steps, self.rows = self.steps, [], []
        bad = ~np.isfinite(values)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise NonFiniteLossError(
                f"non-finite value {keys[col]}={values[row, col]} at step {steps[row]}; training "
                "stopped and the last good checkpoint was kept")
        return dict(zip(keys, values.mean(0).tolist()))


def check_action(action: np.ndarray, step: int, window: MetricWindow) -> None:
    """Stop on a non-finite action (a diverged actor) before MuJoCo rejects it.

    Flushing the window first names the first non-finite loss when one is there.
    """
    if not np.isfinite(action).all():
        window.flush()
        raise NonFiniteLossError(f"the policy produced a non-finite action at step {step}; "
                                 "training stopped and the last good checkpoint was kept")


def progress_bar(total: int, initial: int, desc: str, enabled: bool | None = None) -> tqdm:
    """A frames progress bar (rate in frames/s, ETA). ``enabled=None``: only on a terminal."""
    return tqdm(total=total, initial=initial, desc=desc, unit="frame", unit_scale=True,
                dynamic_ncols=True, disable=(None if enabled is None else not enabled), smoothing=0.05)


# ---------------------------------------------------------------------------------------------
# Snapshots of pre-trained agents


def snapshot_name(frames: int) -> str:
    return f"{SNAPSHOT_PREFIX}{frames}"


def snapshot_state(agent: Agent, config: PretrainConfig, frames: int) -> dict:
    """A self-describing snapshot: the agent's name, its run config, the dims, the format version
    and the state of its pre-trained modules."""
    return {"kind": "pretrained_agent", "format": SNAPSHOT_FORMAT, "agent": agent.name, "domain": config.domain,
            "config": to_dict(config), "frames": frames, "obs_dim": agent.obs_dim, "action_dim": agent.action_dim,
            "modules": {k: m.state_dict() for k, m in agent.pretrained_modules().items()}}


def available_snapshots(run: RunDir) -> list[int]:
    """Frames of the run's agent snapshots, ascending."""
    names = list_snapshots(run)
    return sorted(int(n[len(SNAPSHOT_PREFIX):]) for n in names
                  if n.startswith(SNAPSHOT_PREFIX) and n[len(SNAPSHOT_PREFIX):].isdigit())


def open_pretrained_run(run_path: str | Path) -> tuple[RunDir, PretrainConfig]:
    """Open a pre-training run and apply its ``torch_threads`` (acting is batch-1 forward passes,
    which slow down badly when OpenMP threads compete for busy cores)."""
    run = RunDir.open(run_path)
    try:
        config = load_run_config(run.config_path)
    except ConfigError as exc:
        if str(run.config_path) in str(exc):
            raise
        raise ConfigError(f"{run.config_path}: {exc}") from exc
    if config.torch_threads > 0:
        torch.set_num_threads(config.torch_threads)
    return run, config


def check_snapshot(state: dict, config: PretrainConfig, where: str) -> None:
    """Refuse a snapshot of another method, domain, configuration or format, naming both sides."""
    if state.get("kind") != "pretrained_agent":
        raise CheckpointError(f"{where} is not a dvfb agent snapshot")
    fmt = state.get("format", 1)
    if not isinstance(fmt, int) or fmt > SNAPSHOT_FORMAT:
        raise CheckpointError(f"{where} has snapshot format {fmt!r}, newer than this dvfb reads "
                              f"({SNAPSHOT_FORMAT}); upgrade dvfb")
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


def load_pretrained_agent(run: RunDir, config: PretrainConfig, snapshot: int | None = None,
                          device: str | torch.device | None = None) -> tuple[Agent, int]:
    """Rebuild the run's agent from a snapshot (the newest by default), through the registry.

    Raises :class:`CheckpointError` if the run has no snapshot, the snapshot is unreadable, or it
    was written by another method, for another domain or shape, or with another configuration
    than the run's ``config.json``.
    """
    frames = available_snapshots(run)
    if not frames:
        raise CheckpointError(f"run {run.path} has no pre-trained snapshot in {run.snapshots_dir}; "
                              "has pre-training finished?")
    if snapshot is None:
        snapshot = frames[-1]
    elif snapshot not in frames:
        raise CheckpointError(f"run {run.path} has no snapshot at {snapshot} frames; available: {frames}")
    state = load_snapshot(run, snapshot_name(snapshot), map_location="cpu")
    where = f"snapshot {run.snapshots_dir / snapshot_name(snapshot)}.pt"
    check_snapshot(state, config, where)
    device = device if device is not None else resolve_device(config.device)
    return agent_from_snapshot(state, config, device, where), snapshot


def agent_from_snapshot(state: dict, config: PretrainConfig, device: str | torch.device, where: str) -> Agent:
    """Build the snapshot's agent (registry) and load its pre-trained modules; a module of another
    shape is an error that names both shapes."""
    agent = make_agent(config.agent, state["obs_dim"], state["action_dim"], config, device)
    try:
        for key, module in agent.pretrained_modules().items():
            module.load_state_dict(state["modules"][key])
    except (KeyError, RuntimeError) as exc:
        raise CheckpointError(f"{where} does not fit the configured networks: {exc}") from exc
    return agent


def check_task_in_domain(task: str, domain: str) -> None:
    """A zero-shot/fine-tuning task must share the pre-training domain's dynamics (tasks.md §5)."""
    if task not in envs.TASKS:
        envs.make(task)  # raises ConfigError listing the valid names
    task_domain = envs.TASKS[task].domain
    if task_domain != domain:
        raise ConfigError(f"task {task!r} belongs to domain {task_domain!r}, but the run was pre-trained "
                          f"on {domain!r}; valid tasks: {', '.join(envs.tasks_of_domain(domain))}")
