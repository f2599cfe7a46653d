"""``dvfb dataset export``: a pre-training run's replay as a dataset (docs/methods.md, "Datasets";
the format is :mod:`dvfb.data.datasets`'s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.data.buffer import PHYSICS_COLUMN
from dvfb.data.datasets import DatasetInfo, ProgressFactory, check_output_dir, physics_slice, write_dataset
from dvfb.runs import PRETRAIN_RESUME_KIND
from dvfb.runs.layout import PretrainRun


def default_export_dir(run: str | Path) -> Path:
    """Where ``export_run`` writes by default: ``RUN/dataset``."""
    return Path(run) / "dataset"


def export_run(run: str | Path, out: str | Path | None = None,
               progress: ProgressFactory | None = None) -> DatasetInfo:
    """Write the pre-training replay of ``run`` (its latest resume checkpoint: the final one of a
    finished run) as a dataset in ``out`` (default ``RUN/dataset``), one finished episode at a time.

    The run must have been pre-trained with ``--replay.record-physics true``; ``out`` must not
    exist or be empty. Every check is made before anything is written; a failure while writing
    removes what was written.
    """
    run = PretrainRun.open(run)
    config = run.config
    out = Path(out) if out is not None else default_export_dir(run.path)
    no_physics = (f"{run.path} was pre-trained without --replay.record-physics, so its replay holds no physics "
                  "states to relabel from; pre-train with --replay.record-physics true")
    if not config.replay.record_physics:
        raise ConfigError(no_physics)
    check_output_dir(out)
    state = run.resume_state(mmap=True)
    if state is None:
        raise CheckpointError(f"{run.path} has no resume checkpoint to export its replay from")
    if state.get("kind") != PRETRAIN_RESUME_KIND:
        raise ConfigError(f"{run.path}: the latest checkpoint is not a pre-training checkpoint")
    replay = state["replay"]
    physics = physics_slice(replay.get("columns") or {})
    if physics is None:
        raise ConfigError(no_physics)
    domain, agent = config.domain, config.agent
    task = get_spec(agent).task_of(config) or envs.pretrain_task(domain)
    env = envs.make(task, seed=0).unwrapped
    layout = [list(part) for part in env.physics_layout]
    obs_dim, action_dim = int(replay["obs_dim"]), int(replay["action_dim"])
    if physics.stop - physics.start != env.physics_width:
        raise ConfigError(f"{run.path}: its physics states have {physics.stop - physics.start} values, {task}'s "
                          f"environment has {env.physics_width} (made by another version?)")
    lengths = torch.as_tensor(replay["lengths"]).to(torch.int64).numpy()
    # The newest episode is in progress only in a checkpoint written mid-episode; one written at an
    # episode end has the episode that just ended still open in the replay (no reset came yet).
    finished = len(lengths) - (1 if replay["episode_open"] and "episode_state" in state else 0)
    if finished < 1:
        raise ConfigError(f"{run.path}: its replay holds no finished episode yet (checkpoint of step {state['step']})")
    first_index = int(replay.get("episodes_begun", len(lengths))) - len(lengths)
    starts = np.concatenate([[0], np.cumsum(lengths + 1)])
    rows, rows64 = replay["rows"], replay["rows_float64"]
    reward_col, discount_col = obs_dim + action_dim, obs_dim + action_dim + 1

    def episodes():
        for i in range(finished):
            steps = int(lengths[i])
            if steps == 0:  # (an episode is stored once it has a step; kept out should one not have)
                continue
            block = rows[starts[i]:starts[i + 1]].numpy()  # this episode's rows only (mapped from the file)
            arrays = {"observation": block[:, :obs_dim].copy(),
                      "action": np.zeros((steps + 1, action_dim), np.float32),
                      "reward": np.zeros((steps + 1, 1), np.float32),
                      "discount": np.ones((steps + 1, 1), np.float32),
                      PHYSICS_COLUMN: rows64[starts[i]:starts[i + 1], physics].numpy().copy()}
            arrays["action"][1:] = block[:steps, obs_dim:reward_col]
            arrays["reward"][1:, 0] = block[:steps, reward_col]
            arrays["discount"][1:, 0] = block[:steps, discount_col]
            yield first_index + i, arrays

    info = DatasetInfo(
        domain=domain, task=task, pretrain_task=task, source_run=str(run.path.resolve()), agent=agent,
        seed=config.seed, frames=int(state["step"]), obs_dim=obs_dim, action_dim=action_dim,
        physics_width=env.physics_width, physics_layout=layout, episode_length=envs.TASKS[task].episode_length,
        episodes=finished, transitions=int(lengths[:finished].sum()), files=[])
    return write_dataset(out, info, episodes(), progress, "dataset export")
