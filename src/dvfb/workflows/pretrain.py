"""Reward-free online pre-training (docs/methods.md §7.1) with snapshots and exact resume.

The loop (:mod:`dvfb.training.loop`, shared with fine-tuning), per environment step ``t``:

* at an episode start: reset, store the reset observation;
* draw a new rollout skill from the method's prior when its declared rule says so
  (``agent.skill.due(t, episode_start)``: for FB at every episode start and when ``t`` is a multiple
  of ``fb.skill_every``, §5.2; never for methods without skills);
* act uniformly while ``t < seed_frames``, otherwise with a rollout sample of ``pi(s, skill)``;
* if ``t >= seed_frames`` and ``t % update_every == 0``: one agent update on a batch drawn as the
  agent's :class:`~dvfb.agents.base.ReplayNeeds` say (before stepping, as the authors' code does);
* step the environment, store ``(a, task reward, discount, s', skill)``. The task reward is stored
  for logging only: the reward-free update never reads it (docs/tasks.md §3). The supervised
  reference (docs/methods.md, "Supervised reference") is the one method that trains on it: its
  environment is its task's.

The loop talks to the method only through the :class:`~dvfb.agents.base.Agent` interface; this
module adds the method's skill rule, the logging, the snapshots and what a checkpoint holds.

Resume checkpoints are written at episode ends, so a resumed run starts a fresh episode exactly
where the uninterrupted run would have, with the same RNG streams, replay content, optimiser
states and counters. On SIGTERM/SIGINT a checkpoint is written after the current step, mid-episode
if need be: it then also holds the environment's full MuJoCo state, the current observation and
skill, and the resumed run continues that episode exactly as the uninterrupted one does.

With ``--replay.record-physics`` the replay also stores the environment's physics state with every
observation (docs/methods.md, "Datasets"), and the run ends with a resume checkpoint of its last
step (mid-episode if need be) when the last one is older, so that its final checkpoint holds every
episode it finished: what ``dvfb dataset export`` reads.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec, make_agent
from dvfb.config import replace, to_dict
from dvfb.datasets import read_dataset, read_info
from dvfb.errors import CheckpointError, ConfigError, RunDirError
from dvfb.replay import ReplayBuffer, physics_columns
from dvfb.runs import (
    PRETRAIN_RESUME_KIND,
    MetricsLogger,
    RunDir,
    RunLock,
    load_checkpoint,
    read_json,
    remove_orphaned_checkpoints,
    save_checkpoint,
    save_snapshot,
    write_json_atomic,
)
from dvfb.training import loop
from dvfb.training.loop import DatasetSource, EpisodeState, OnlineCollector
from dvfb.training.monitor import MetricWindow, Progress, ResumeCheckpoints, notify
from dvfb.training.seeding import check_resume_format, restore_rng_state, rng_state, run_generator, seed_everything
from dvfb.workflows.resources import check_memory, check_replay, check_task_in_domain, learner_state_bytes, setup_torch
from dvfb.workflows.snapshots import snapshot_name, snapshot_state
from dvfb.workflows.config import PretrainConfig, load_run_config

log = logging.getLogger(__name__)

RESUME_KIND = PRETRAIN_RESUME_KIND
# Format of resume checkpoints. 1: before runs owned their random streams; 2: adds the state of the
# run's torch generator (every skill draw, policy noise and batch). Format 1 cannot resume exactly.
RESUME_FORMAT = 2
# Fields that may change between a run and its resumption without changing what is computed.
RESUMABLE_CHANGES = ("frames", "device", "torch_threads", "log_every")
# perf options that only change how the same operations execute (perf.precision changes numerics).
RESUMABLE_PERF_CHANGES = ("compile", "cuda_graphs")


def _check_resume_config(stored: PretrainConfig, requested: PretrainConfig) -> None:
    a, b = to_dict(stored), to_dict(requested)
    for d in (a, b):
        for k in RESUMABLE_PERF_CHANGES:
            d["perf"].pop(k, None)
    diffs = sorted(k for k in a if k not in RESUMABLE_CHANGES and a[k] != b[k])
    if diffs:
        raise ConfigError(f"--resume with a different configuration: {', '.join(diffs)} differ from the "
                          "run's config.json; resume with the original options")


def pretrain(config: PretrainConfig, run_path: str | Path, *, resume: bool = False, overwrite: bool = False,
             progress: bool | None = None, command: list[str] | None = None) -> RunDir:
    """Pre-train ``config.agent`` on ``config.domain`` into ``run_path``; returns the run directory.

    Everything that can be checked is checked before the run directory is touched: the options,
    the device, the memory the replay buffer and the networks need. One process writes a run
    directory at a time (:class:`~dvfb.runs.RunLock`). SIGTERM or SIGINT finish the current step,
    write a checkpoint (mid-episode if need be) and raise :class:`~dvfb.errors.RunInterrupted`;
    ``resume`` continues exactly from it. A failed resume changes no file; resuming a finished run
    is a no-op. Disk errors (full, read-only, permissions) end the run with one line and leave the
    previous checkpoint intact.
    """
    run_path = Path(run_path)
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite contradict each other: --resume continues the run in "
                          f"{run_path}, --overwrite deletes it; pass one of them")
    envs.check_domain(config.domain)
    if resume and not (run_path / "config.json").is_file():
        RunDir.open(run_path)  # names what is missing
    # The supervised reference learns from its task's reward; every other method is reward-free
    # and its environment records the domain's default task reward for logging only.
    trained_task = get_spec(config.agent).task_of(config)
    if trained_task is not None:
        check_task_in_domain(trained_task, config.domain)
    dataset_info = None
    if config.dataset:
        if trained_task is not None:
            raise ConfigError(f"{config.agent} learns from its task's reward online; offline training (--dataset) "
                              "is for the reward-free methods")
        dataset_info = read_info(config.dataset)
        if dataset_info.domain != config.domain:
            raise ConfigError(f"--dataset {config.dataset} holds {dataset_info.domain} data; this run is on "
                              f"{config.domain} (pass --domain {dataset_info.domain})")
        # Offline, every step of the loop is one update (docs/methods.md, "Offline training").
        config = replace(config, seed_frames=0, update_every=1)
    device = setup_torch(config)
    rng = seed_everything(config.seed)
    env = envs.make(trained_task or config.domain, seed=config.seed, reward_free=True)
    obs_dim = env.observation_space.shape[0]
    action_dim = env.action_space.shape[0]
    agent = make_agent(config.agent, obs_dim, action_dim, config, device)
    episode_length = envs.TASKS[trained_task or envs.pretrain_task(config.domain)].episode_length
    check_replay(config.replay_capacity, "--replay-capacity", agent.replay_needs(), episode_length, config.domain)
    columns = physics_columns(env.unwrapped.physics_width) if config.replay.record_physics else None
    capacity = config.replay_capacity if dataset_info is None else dataset_info.transitions
    check_memory({"replay": ReplayBuffer.estimate_nbytes(capacity, obs_dim, action_dim, agent.skill_dim,
                                                         episode_length, columns),
                  "networks": learner_state_bytes(agent)}, f"pretrain {config.agent} {config.domain}", device)
    dataset = None
    if dataset_info is not None:
        if (dataset_info.obs_dim, dataset_info.action_dim) != (obs_dim, action_dim):
            raise ConfigError(f"--dataset {config.dataset} has observations of {dataset_info.obs_dim} and actions of "
                              f"{dataset_info.action_dim} values; {config.domain} has {obs_dim} and {action_dim}")
        # Read whole before the run directory exists: a bad file creates nothing.
        dataset, _ = read_dataset(config.dataset, device, agent.skill_dim, progress=progress)
    lock = RunLock(run_path)
    with lock:
        try:
            return _pretrain_locked(config, run_path, resume, overwrite, progress, command, device, rng, env, agent,
                                    episode_length, columns, dataset, dataset_info)
        except BaseException:
            lock.remove_if_created()
            raise


def _pretrain_locked(config, run_path, resume, overwrite, progress, command, device, rng, env, agent,
                     episode_length, columns, dataset=None, dataset_info=None) -> RunDir:
    obs_dim, action_dim = agent.obs_dim, agent.action_dim
    state = None
    if resume:
        run = RunDir.open(run_path)
        _check_resume_config(load_run_config(run.config_path), config)
        finished = _finished_frames(run)
        if finished is not None and finished >= config.frames:
            notify(f"[pretrain] {run.path} already finished at {finished} frames (>= --frames {config.frames}); "
                   "nothing to resume")
            return run
        remove_orphaned_checkpoints(run)
        try:
            state = load_checkpoint(run, None, map_location=device)
        except CheckpointError as exc:
            raise CheckpointError(f"cannot resume {run.path}: {exc}") from exc
        if state.get("kind") != RESUME_KIND or state.get("agent") != config.agent:
            raise CheckpointError(f"{run.path}: the latest checkpoint is not a {config.agent} pre-training checkpoint")
        check_resume_format(state, run.path)
        if state["step"] >= config.frames:
            raise ConfigError(f"--frames {config.frames} is not beyond the checkpoint's step {state['step']}; "
                              "pass a larger --frames to extend the run")
    else:
        run = RunDir.create(run_path, config, overwrite=overwrite, command=command)
    offline = dataset is not None
    # What an offline checkpoint records instead of the replay: which data it trained on.
    fingerprint = None if not offline else {"path": str(Path(config.dataset).resolve()), "episodes": dataset_info.episodes,
                                            "transitions": dataset_info.transitions, "files": list(dataset_info.files)}
    replay = dataset if offline else ReplayBuffer(
        config.replay_capacity, obs_dim, action_dim, agent.skill_dim, max_episode_length=episode_length, device=device,
        sampler=config.replay.sampler(), columns=columns)
    needs = agent.replay_needs()

    step = 0
    episode = EpisodeState()
    # The run's own random stream: skill draws, policy noise, the agent's modules and its batches.
    generator = run_generator(config.seed, device)
    agent.use_generator(generator)
    if state is not None:
        try:
            agent.load_training_state(state["agent_state"])
            generator.set_state(state["generator"])
            if offline:
                if state.get("dataset", {}).get("files") != fingerprint["files"]:
                    raise ValueError(f"the run trained on other data than --dataset {config.dataset} now holds")
            else:
                replay.load_state_dict(state["replay"])
            restore_rng_state(state["rng"], rng)
            env.unwrapped.set_rng_state(state["env_rng"])
            episode_state = state.get("episode_state")
            if episode_state is not None:  # a checkpoint written mid-episode (on a signal)
                env.unwrapped.set_episode_state(episode_state["env"])
                episode.obs = np.asarray(episode_state["obs"], dtype=np.float32)
                skill = episode_state["skill"]
                episode.set_skill(None if skill is None else skill.to(device))
                episode.episode_return, episode.episode_start = float(episode_state["episode_return"]), False
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise CheckpointError(f"cannot resume {run.path}: the checkpoint does not fit this run ({exc})") from exc
        step, episode.episode = state["step"], state["episode"]
        # Only now, with the checkpoint loaded, may the run's config change (a larger --frames).
        run.save_config(config)
        notify(f"[pretrain] resuming {run.path} from step {step} (of {config.frames})")

    # Records up to the checkpointed step belong to the restored state; later ones are redone.
    logger = MetricsLogger(run, purge_step=step + 1 if resume else None)
    window = MetricWindow(agent.nonfinite_hint)
    snapshots = set(config.snapshot_frames) | {config.frames}
    bar = Progress(config.frames, step, f"pretrain {config.agent} {config.domain}", progress)
    started = time.time()
    start_step = step

    def next_skill(t: int, episode_start: bool, current):
        # The method's declared rule (docs/methods.md, "Skills"); its prior draws the new skill.
        return agent.sample_skill(1)[0] if agent.skill.due(t, episode_start) else current

    collector = DatasetSource() if offline else OnlineCollector(
        env, replay, agent, rng, next_skill, lambda t: t < config.seed_frames, reward_key="task_reward",
        first_reset_seed=None if state is not None else config.seed, state=episode,
        physics=env.unwrapped.physics_state if columns else None)

    def save_resume(mid_episode: bool = False) -> None:
        checkpoint = {
            "kind": RESUME_KIND, "format": RESUME_FORMAT, "agent": config.agent, "config": to_dict(config),
            "step": step, "generator": generator.get_state(),
            "episode": episode.episode, "agent_state": agent.training_state(),
            **({"dataset": fingerprint} if offline else {"replay": replay.state_dict()}),
            "rng": rng_state(rng), "env_rng": env.unwrapped.get_rng_state()}
        if mid_episode:
            checkpoint["episode_state"] = {
                "env": env.unwrapped.get_episode_state(), "obs": torch.as_tensor(episode.obs),
                "skill": None if episode.skill is None else episode.skill.cpu(),
                "episode_return": episode.episode_return}
        save_checkpoint(run, checkpoint, f"resume_{step}")

    def after_step(t: int) -> None:
        nonlocal step
        step = t  # what a checkpoint written at this step records
        if t % config.log_every == 0 or t == config.frames:
            means = window.flush()
            if means:
                means["fps"] = (t - start_step) / max(time.time() - started, 1e-9)
                logger.log(t, means, prefix="train")
        if t in snapshots:
            window.flush()
            save_snapshot(run, snapshot_state(agent, config, t), snapshot_name(t))

    def after_episode(t: int, ended: EpisodeState) -> None:
        logger.log(t, {"episode": ended.episode, "episode_task_reward": ended.episode_return}, prefix="episode")

    checkpoints = ResumeCheckpoints(save_resume, window, config.checkpoint_every, config.frames, "pre-training",
                                    run.path, last=step if state is not None else None)
    try:
        with checkpoints:
            step = loop.run(step, config.frames, collector, lambda: agent.update(needs.sample(replay, generator)),
                            config.seed_frames, config.update_every, window, checkpoints, bar, after_step,
                            None if offline else after_episode)
            if columns:  # a dataset's run: the final checkpoint holds every finished episode
                checkpoints.ensure(step, mid_episode=not episode.episode_start)
    finally:
        bar.close()
        logger.close()
    elapsed = time.time() - started
    write_json_atomic(run.path / "pretrain_summary.json", {
        "agent": config.agent, "domain": config.domain, "frames": step, "episodes": episode.episode,
        "wall_clock_s": elapsed, "frames_per_s": (step - start_step) / max(elapsed, 1e-9),
        "resumed_from": start_step if resume else None, "device": str(device)})
    return run


def _finished_frames(run: RunDir) -> int | None:
    """Frames of a finished pre-training (its summary), None when it has not finished."""
    path = run.path / "pretrain_summary.json"
    if not path.is_file():
        return None
    summary = read_json(path, RunDirError)
    frames = summary.get("frames") if isinstance(summary, dict) else None
    return frames if isinstance(frames, int) else None
