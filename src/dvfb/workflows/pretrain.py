"""Reward-free online pre-training (algorithm.md §7.1) with snapshots and exact resume.

The loop, per environment step ``t``:

* at an episode start: reset, draw a skill from the method's prior (``z ~ p(z)`` for FB; none for
  methods without skills), store the reset observation;
* if ``t % update_z_every == 0``: draw a new rollout skill (§5.2);
* act uniformly while ``t < seed_frames``, otherwise with a rollout sample of ``pi(s, skill)``;
* if ``t >= seed_frames`` and ``t % update_every == 0``: one agent update on a batch drawn as the
  agent's :class:`~dvfb.agents.base.ReplayNeeds` say (before stepping, as the authors' code does);
* step the environment, store ``(a, task reward, discount, s', skill)``. The task reward is stored
  for logging only: the reward-free update never reads it (tasks.md §3).

The loop talks to the method only through the :class:`~dvfb.agents.base.Agent` interface.

Resume checkpoints are written at episode ends, so a resumed run starts a fresh episode exactly
where the uninterrupted run would have, with the same RNG streams, replay content, optimiser
states and counters.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from dvfb import envs
from dvfb.agents import make_agent
from dvfb.config import to_dict
from dvfb.errors import CheckpointError, ConfigError, NonFiniteLossError
from dvfb.replay import ReplayBuffer
from dvfb.runs import MetricsLogger, RunDir, load_checkpoint, save_checkpoint, save_snapshot, write_json_atomic
from dvfb.workflows.common import (
    MetricWindow,
    check_action,
    progress_bar,
    restore_rng_state,
    rng_state,
    seed_everything,
    setup_torch,
    snapshot_name,
    snapshot_state,
)
from dvfb.workflows.config import PretrainConfig, load_run_config

log = logging.getLogger(__name__)

RESUME_KIND = "pretrain_resume"
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
    """Pre-train ``config.agent`` on ``config.domain`` into ``run_path``; returns the run directory."""
    if config.domain not in envs.DOMAINS:
        raise ConfigError(f"unknown domain {config.domain!r}; choose one of {', '.join(envs.DOMAINS)}")
    if resume:
        run = RunDir.open(run_path)
        _check_resume_config(load_run_config(run.config_path), config)
        run.save_config(config)
    else:
        run = RunDir.create(run_path, config, overwrite=overwrite, command=command)
    device = setup_torch(config)
    rng = seed_everything(config.seed)
    env = envs.make(config.domain, seed=config.seed, reward_free=True)
    obs_dim = env.observation_space.shape[0]
    action_dim = env.action_space.shape[0]
    agent = make_agent(config.agent, obs_dim, action_dim, config, device)
    replay = ReplayBuffer(config.replay_capacity, obs_dim, action_dim, agent.skill_dim,
                          max_episode_length=envs.TASKS[envs.pretrain_task(config.domain)].episode_length,
                          device=device)
    needs = agent.replay_needs()

    step, episode, last_checkpoint = 0, 0, 0
    first_reset = True
    if resume:
        try:
            state = load_checkpoint(run, None, map_location=device)
        except CheckpointError as exc:
            raise CheckpointError(f"cannot resume {run.path}: {exc}") from exc
        if state.get("kind") != RESUME_KIND or state.get("agent") != config.agent:
            raise CheckpointError(f"{run.path}: the latest checkpoint is not a {config.agent} pre-training checkpoint")
        agent.load_training_state(state["agent_state"])
        replay.load_state_dict(state["replay"])
        restore_rng_state(state["rng"], rng)
        env.unwrapped.set_rng_state(state["env_rng"])
        step, episode, last_checkpoint = state["step"], state["episode"], state["step"]
        first_reset = False
        log.info("resumed %s at step %d", run.path, step)

    # Records up to the checkpointed step belong to the restored state; later ones are redone.
    logger = MetricsLogger(run, purge_step=step + 1 if resume else None)
    window = MetricWindow()
    snapshots = set(config.snapshot_frames) | {config.frames}
    bar = progress_bar(config.frames, step, f"pretrain {config.agent} {config.domain}", progress)
    started = time.time()
    start_step = step
    episode_return, episode_start = 0.0, True
    obs = skill = skill_host = None

    def draw_skill() -> None:
        nonlocal skill, skill_host
        drawn = agent.sample_skill(1)
        skill = None if drawn is None else drawn[0]
        skill_host = None if skill is None else skill.cpu().numpy()  # what the replay stores; once per draw

    def save_resume() -> None:
        save_checkpoint(run, {
            "kind": RESUME_KIND, "agent": config.agent, "config": to_dict(config), "step": step,
            "episode": episode, "agent_state": agent.training_state(), "replay": replay.state_dict(),
            "rng": rng_state(rng), "env_rng": env.unwrapped.get_rng_state()}, f"resume_{step}")

    try:
        while step < config.frames:
            if episode_start:
                obs, _ = env.reset(seed=config.seed) if first_reset else env.reset()
                first_reset = False
                draw_skill()
                replay.start_episode(obs)
                episode_return, episode_start = 0.0, False
            if step % config.update_z_every == 0:
                draw_skill()
            if step < config.seed_frames:
                action = rng.uniform(-1.0, 1.0, action_dim).astype(np.float32)
            else:
                action = agent.act(obs, skill, explore=True)
            if step >= config.seed_frames and step % config.update_every == 0:
                window.add(step, agent.update(needs.sample(replay)))
            check_action(action, step, window)
            obs, _, terminated, truncated, info = env.step(action)
            task_reward = info["task_reward"]
            replay.add(action, task_reward, 0.0 if terminated else 1.0, obs, skill_host)
            episode_return += task_reward
            step += 1
            bar.update(1)

            if step % config.log_every == 0 or step == config.frames:
                means = window.flush()
                if means:
                    elapsed = time.time() - started
                    means["fps"] = (step - start_step) / max(elapsed, 1e-9)
                    logger.log(step, means, prefix="train")
            if step in snapshots:
                window.flush()
                save_snapshot(run, snapshot_state(agent, config, step), snapshot_name(step))
            if terminated or truncated:
                episode += 1
                episode_start = True
                logger.log(step, {"episode": episode, "episode_task_reward": episode_return}, prefix="episode")
                if step - last_checkpoint >= config.checkpoint_every or step >= config.frames:
                    window.flush()
                    save_resume()
                    last_checkpoint = step
    except NonFiniteLossError:
        logger.close()
        bar.close()
        raise
    bar.close()
    elapsed = time.time() - started
    write_json_atomic(run.path / "pretrain_summary.json", {
        "agent": config.agent, "domain": config.domain, "frames": step, "episodes": episode,
        "wall_clock_s": elapsed, "frames_per_s": (step - start_step) / max(elapsed, 1e-9),
        "resumed_from": start_step if resume else None, "device": str(device)})
    logger.close()
    return run
