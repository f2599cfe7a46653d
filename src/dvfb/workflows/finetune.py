"""Dual-value fine-tuning of a pre-trained run on a task (algorithm.md §9).

Protocol: load the snapshot's actor, F and B; collect the inference steps and infer z_r (§8.1-8.2);
evaluate zero-shot (the curve's point at 0 frames); then ``finetune.frames`` steps of rollouts
with ``pi(s, z_r)`` (no uniform phase), one :class:`DualValueFinetuner` update every
``update_every`` steps after ``seed_frames``, and an evaluation every ``eval_every`` steps.

Each fine-tuning run has its own directory ``RUN/finetune/<name>/`` (default name: the task) with
its config, metrics, resume checkpoints and ``curve.json`` (frames, mean and std return).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents.finetune import DualValueFinetuner, FinetuneConfig
from dvfb.config import merge, param, to_dict
from dvfb.errors import CheckpointError, ConfigError
from dvfb.replay import ReplayBuffer
from dvfb.runs import MetricsLogger, RunDir, load_checkpoint, save_checkpoint, write_json_atomic
from dvfb.workflows.common import (
    MetricWindow,
    check_action,
    check_task_in_domain,
    load_pretrained_agent,
    open_pretrained_run,
    progress_bar,
    restore_rng_state,
    rng_state,
    seed_everything,
)
from dvfb.workflows.config import InferenceConfig
from dvfb.workflows.evaluate import collect_inference_data, evaluate_policy
from dvfb.workflows.zeroshot import infer_task_vector

RESUME_KIND = "finetune_resume"


@dataclass
class FinetuneRunConfig:
    """A fine-tuning run: which pre-trained snapshot, which task, and the protocol."""

    pretrain_run: str = param("", "Path of the pre-training run directory.")
    agent: str = param("dvfb", "Agent of the pre-training run (copied for reports).")
    domain: str = param("walker", "Domain of the pre-training run.")
    task: str = param("walker_walk", "Downstream task.")
    snapshot: int = param(0, "Pre-training snapshot (frames) the agent starts from.")
    seed: int = param(0, "Seed of the task environment and the fine-tuning randomness.")
    device: str = param("auto", "Torch device.")
    inference: InferenceConfig = field(default_factory=InferenceConfig, metadata={"help": "Zero-shot part."})
    finetune: FinetuneConfig = field(default_factory=FinetuneConfig, metadata={"help": "Fine-tuning part."})


def finetune(run_path: str | Path, task: str, *, snapshot: int | None = None, inference: dict | None = None,
             finetune: dict | None = None, seed: int | None = None, name: str | None = None,
             resume: bool = False, overwrite: bool = False, progress: bool | None = None,
             device: str | None = None) -> RunDir:
    """Fine-tune a pre-trained run on ``task``; returns the fine-tuning run directory."""
    run, config = open_pretrained_run(run_path)
    check_task_in_domain(task, config.domain)
    agent, snapshot = load_pretrained_agent(run, config, snapshot, device)
    run_config = FinetuneRunConfig(
        pretrain_run=str(run.path), agent=config.agent, domain=config.domain, task=task, snapshot=snapshot,
        seed=config.seed if seed is None else seed, device=str(agent.device),
        inference=merge(config.inference, inference or {}), finetune=merge(config.finetune, finetune or {}))
    cfg = run_config.finetune
    path = run.path / "finetune" / (name or task)
    if resume:
        ft_run = RunDir.open(path)
        stored = to_dict(ft_run.load_config(FinetuneRunConfig))
        requested = to_dict(run_config)
        for key in ("device",):
            stored.pop(key), requested.pop(key)
        stored["finetune"].pop("frames"), requested["finetune"].pop("frames")
        if stored != requested:
            diffs = sorted(k for k in stored if stored[k] != requested[k])
            raise ConfigError(f"--resume with a different configuration: {', '.join(diffs)} differ from {path}/config.json")
        ft_run.save_config(run_config)
    else:
        ft_run = RunDir.create(path, run_config, overwrite=overwrite)

    rng = seed_everything(run_config.seed)
    env = envs.make(task, seed=run_config.seed)
    eval_env = envs.make(task, seed=run_config.seed)  # same seed as the training env, as in [C]
    max_len = envs.TASKS[task].episode_length
    replay = ReplayBuffer(cfg.replay_capacity, agent.obs_dim, agent.action_dim, agent.config.z_dim,
                          max_episode_length=max_len, device=agent.device)
    started = time.time()

    if resume:
        try:
            state = load_checkpoint(ft_run, None, map_location=agent.device)
        except CheckpointError as exc:
            raise CheckpointError(f"cannot resume {path}: {exc}") from exc
        if state.get("kind") != RESUME_KIND:
            raise CheckpointError(f"{path}: the latest checkpoint is not a fine-tuning checkpoint")
        z = state["z"].to(agent.device)
        finetuner = DualValueFinetuner(agent, z, cfg)
        finetuner.load_training_state(state["finetuner"])
        replay.load_state_dict(state["replay"])
        restore_rng_state(state["rng"], rng)
        env.unwrapped.set_rng_state(state["env_rng"])
        eval_env.unwrapped.set_rng_state(state["eval_env_rng"])
        step, curve, inference_info = state["step"], state["curve"], state["inference_info"]
        logger = MetricsLogger(ft_run, purge_step=step + 1)
    else:
        inference_buffer = collect_inference_data(agent, env, run_config.inference.steps,
                                                  run_config.inference.random_action_steps, rng, max_len)
        z, inference_info = infer_task_vector(agent, inference_buffer, run_config.inference)
        if cfg.keep_inference_data:
            _copy_transitions(inference_buffer, replay, z)
        del inference_buffer  # the inference data are discarded (§8.2 step 6) unless kept above
        finetuner = DualValueFinetuner(agent, z, cfg)
        logger = MetricsLogger(ft_run)
        returns = evaluate_policy(agent, eval_env, z, cfg.eval_episodes)
        curve = [_curve_point(0, returns)]
        logger.log(0, {"eval_return": curve[-1]["mean_return"]}, prefix="eval")
        step = 0
    _write_curve(ft_run, run_config, curve, inference_info, z)

    window = MetricWindow()
    z_host = z.cpu().numpy()  # z_r is fixed: the replay's copy is made once, not every step
    bar = progress_bar(cfg.frames, step, f"finetune {task}", progress)
    last_checkpoint = step
    episode_start = True
    obs = None
    while step < cfg.frames:
        if episode_start:
            obs, _ = env.reset()
            replay.start_episode(obs)
            episode_start = False
        action = agent.act(obs, z, explore=True)
        if step >= cfg.seed_frames and step % cfg.update_every == 0:
            window.add(step, finetuner.update(replay.sample(agent.config.batch_size, agent.config.discount)))
        check_action(action, step, window)
        obs, reward, terminated, truncated, _ = env.step(action)
        replay.add(action, reward, 0.0 if terminated else 1.0, obs, z_host)
        step += 1
        bar.update(1)
        if step % 1000 == 0 or step == cfg.frames:
            means = window.flush()
            if means:
                logger.log(step, means, prefix="train")
        if step % cfg.eval_every == 0 or step == cfg.frames:
            returns = evaluate_policy(agent, eval_env, z, cfg.eval_episodes)
            curve.append(_curve_point(step, returns))
            logger.log(step, {"eval_return": curve[-1]["mean_return"]}, prefix="eval")
            _write_curve(ft_run, run_config, curve, inference_info, z)
        if terminated or truncated:
            episode_start = True
            if step - last_checkpoint >= cfg.checkpoint_every or step >= cfg.frames:
                window.flush()
                save_checkpoint(ft_run, {
                    "kind": RESUME_KIND, "step": step, "z": z.cpu(), "curve": curve,
                    "inference_info": inference_info, "finetuner": finetuner.training_state(),
                    "replay": replay.state_dict(), "rng": rng_state(rng),
                    "env_rng": env.unwrapped.get_rng_state(), "eval_env_rng": eval_env.unwrapped.get_rng_state()},
                    f"resume_{step}")
                last_checkpoint = step
    bar.close()
    logger.close()
    write_json_atomic(ft_run.path / "finetune_summary.json", {
        "task": task, "frames": step, "wall_clock_s": time.time() - started,
        "zero_shot_return": curve[0]["mean_return"], "final_return": curve[-1]["mean_return"]})
    return ft_run


def _curve_point(frames: int, returns: list[float]) -> dict:
    return {"frames": frames, "mean_return": float(np.mean(returns)), "std_return": float(np.std(returns)),
            "returns": returns}


def _write_curve(run: RunDir, config: FinetuneRunConfig, curve: list[dict], inference_info: dict,
                 z: torch.Tensor) -> None:
    write_json_atomic(run.path / "curve.json", {
        "task": config.task, "domain": config.domain, "agent": config.agent, "seed": config.seed,
        "snapshot": config.snapshot, "z": z.cpu().tolist(), "inference_info": inference_info, "curve": curve})


def _copy_transitions(source: ReplayBuffer, target: ReplayBuffer, z: torch.Tensor) -> None:
    """Replay the inference episodes into the fine-tuning buffer with z = z_r (D12 option)."""
    data = source.transitions()
    z_np = z.cpu().numpy()
    obs, next_obs = data.obs.cpu().numpy(), data.next_obs.cpu().numpy()
    action, reward = data.action.cpu().numpy(), data.reward.cpu().numpy()[:, 0]
    for i in range(obs.shape[0]):
        if i == 0 or not np.array_equal(obs[i], next_obs[i - 1]):
            target.start_episode(obs[i])
        target.add(action[i], float(reward[i]), 1.0, next_obs[i], z_np)
