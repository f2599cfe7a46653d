"""Fine-tuning of a pre-trained run on a task (docs/methods.md §9; docs/methods.md, "Protocols").

Protocol: load the snapshot; obtain the task's skill by the method's registered zero-shot protocol
(FB family: collect the inference steps and infer z_r, §8.1-8.2; skill discovery: select the best
prior skill; methods without skills: none); evaluate zero-shot (the curve's point at 0 frames);
build the method's registered fine-tuner (dual-value for the FB family, URLB's for the DDPG
agents); then ``finetune.frames`` steps of rollouts with ``pi(s, skill)`` (the skill of every step
from the fine-tuner; uniform actions during ``seed_frames`` where it asks for them), one
fine-tuner update every ``update_every`` steps after ``seed_frames``, and an evaluation every
``eval_every`` steps.

Each fine-tuning run has its own directory ``RUN/finetune/<name>/`` (default name: the task) with
its config, metrics, resume checkpoints and ``curve.json`` (frames, mean and std return).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.protocols import finetuner_class, zero_shot_protocol
from dvfb.config import from_dict, merge, param, to_dict
from dvfb.errors import CheckpointError, ConfigError, RunDirError
from dvfb.replay import ReplayBuffer
from dvfb.runs import (
    MetricsLogger,
    RunDir,
    RunLock,
    check_writable,
    load_checkpoint,
    read_json,
    remove_orphaned_checkpoints,
    save_checkpoint,
    write_json_atomic,
)
from dvfb.training import loop
from dvfb.training.loop import EpisodeState, OnlineCollector
from dvfb.training.monitor import MetricWindow, Progress, ResumeCheckpoints, notify
from dvfb.training.seeding import check_resume_format, restore_rng_state, rng_state, run_generator, seed_everything
from dvfb.workflows.resources import check_replay, check_task_in_domain
from dvfb.workflows.snapshots import load_pretrained_agent, open_pretrained_run
from dvfb.workflows.config import protocol_fields
from dvfb.workflows.evaluate import Evaluation, evaluate_policy
from dvfb.workflows.zeroshot import task_skill

RESUME_KIND = "finetune_resume"
RESUME_FORMAT = 2  # as pre-training's: 2 holds the run's torch generator


@dataclass
class FinetuneRunConfig:
    """A fine-tuning run: which pre-trained snapshot, which task, and the protocol.

    A run's config is an instance of :func:`finetune_run_config_class` ``(agent)``, which adds the
    family's ``inference`` and ``finetune`` sections.
    """

    pretrain_run: str = param("", "Path of the pre-training run directory.")
    agent: str = param("dvfb", "Agent of the pre-training run (copied for reports).")
    domain: str = param("walker", "Domain of the pre-training run.")
    task: str = param("walker_walk", "Downstream task.")
    snapshot: int = param(0, "Pre-training snapshot (frames) the agent starts from.")
    seed: int = param(0, "Seed of the task environment and the fine-tuning randomness.")
    device: str = param("auto", "Torch device.")


@functools.cache
def finetune_run_config_class(agent: str) -> type:
    spec = get_spec(agent)
    cls = dataclasses.make_dataclass(f"{spec.agent_cls.__name__}FinetuneRunConfig", protocol_fields(agent),
                                     bases=(FinetuneRunConfig,))
    cls.__module__ = __name__
    return cls


def load_finetune_run_config(run: RunDir) -> FinetuneRunConfig:
    """A fine-tuning run's ``config.json``, strictly, as its method's config class."""
    data = read_json(run.config_path, ConfigError)
    if not isinstance(data, dict) or not isinstance(data.get("agent"), str):
        raise ConfigError(f"{run.config_path}: not a dvfb fine-tuning config")
    try:
        return from_dict(finetune_run_config_class(data["agent"]), data)
    except ConfigError as exc:
        raise ConfigError(f"{run.config_path}: {exc}") from exc


def check_run_name(name: str) -> str:
    """A fine-tuning run's name is one path component under ``RUN/finetune/``: never ``..``, a
    path or a hidden name, which would write (or, with --overwrite, delete) outside it."""
    if not name or name in (".", "..") or "/" in name or "\\" in name or name.startswith("."):
        raise ConfigError(f"--name {name!r} must be a plain name (one path component under RUN/finetune/)")
    return name


def finetune(run_path: str | Path, task: str, *, snapshot: int | None = None, inference: dict | None = None,
             finetune: dict | None = None, seed: int | None = None, name: str | None = None,
             resume: bool = False, overwrite: bool = False, progress: bool | None = None,
             device: str | None = None) -> RunDir:
    """Fine-tune a pre-trained run on ``task``; returns the fine-tuning run directory.

    As pre-training: options are checked and the directory's writability is tested before any
    work, one process writes a fine-tuning run at a time, SIGTERM/SIGINT checkpoint the current
    step and raise :class:`~dvfb.errors.RunInterrupted`, a failed resume changes no file and
    resuming a finished run is a no-op.
    """
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite contradict each other: pass one of them")
    run, config = open_pretrained_run(run_path)
    check_task_in_domain(task, config.domain)
    agent, snapshot = load_pretrained_agent(run, config, snapshot, device)
    run_config = finetune_run_config_class(config.agent)(
        pretrain_run=str(run.path), agent=config.agent, domain=config.domain, task=task, snapshot=snapshot,
        seed=config.seed if seed is None else seed, device=str(agent.device),
        inference=merge(config.inference, inference or {}, "inference."),
        finetune=merge(config.finetune, finetune or {}, "finetune."))
    finetuner_class(get_spec(config.agent).finetuner).check(agent, run_config.finetune)
    check_replay(run_config.finetune.replay_capacity, "--finetune.replay-capacity", agent.replay_needs(),
                 envs.TASKS[task].episode_length, config.domain)
    path = run.path / "finetune" / check_run_name(name or task)
    if resume:
        RunDir.open(path)  # names what is missing before anything else happens
    else:
        check_writable(path.parent)
    lock = RunLock(path)
    with lock:
        try:
            return _finetune_locked(run, config, agent, run_config, path, task, resume, overwrite, progress)
        except BaseException:
            lock.remove_if_created()
            raise


def _finetune_locked(run, config, agent, run_config, path, task, resume, overwrite, progress) -> RunDir:
    cfg = run_config.finetune
    state = None
    if resume:
        ft_run = RunDir.open(path)
        stored = to_dict(load_finetune_run_config(ft_run))
        requested = to_dict(run_config)
        for key in ("device",):
            stored.pop(key), requested.pop(key)
        stored["finetune"].pop("frames"), requested["finetune"].pop("frames")
        if stored != requested:
            diffs = sorted(k for k in stored if stored[k] != requested[k])
            raise ConfigError(f"--resume with a different configuration: {', '.join(diffs)} differ from {path}/config.json")
        summary = path / "finetune_summary.json"
        if summary.is_file():
            done = read_json(summary, RunDirError).get("frames")
            if isinstance(done, int) and done >= cfg.frames:
                notify(f"[finetune] {path} already finished at {done} frames; nothing to resume")
                return ft_run
        remove_orphaned_checkpoints(ft_run)
        try:
            state = load_checkpoint(ft_run, None, map_location=agent.device)
        except CheckpointError as exc:
            raise CheckpointError(f"cannot resume {path}: {exc}") from exc
        if state.get("kind") != RESUME_KIND:
            raise CheckpointError(f"{path}: the latest checkpoint is not a fine-tuning checkpoint")
        check_resume_format(state, path)
    else:
        ft_run = RunDir.create(path, run_config, overwrite=overwrite)

    rng = seed_everything(run_config.seed)
    env = envs.make(task, seed=run_config.seed)
    eval_env = envs.make(task, seed=run_config.seed)  # same seed as the training env, as in [C]
    max_len = envs.TASKS[task].episode_length
    # Batches are drawn the way the pre-training drew them (uniform, or the authors' loader shards).
    replay = ReplayBuffer(cfg.replay_capacity, agent.obs_dim, agent.action_dim, agent.skill_dim,
                          max_episode_length=max_len, device=agent.device, sampler=config.replay.sampler())
    finetuner_cls = finetuner_class(get_spec(config.agent).finetuner)
    # The run's own random stream: the protocol's and the fine-tuner's draws, noise and batches.
    generator = run_generator(run_config.seed, agent.device)
    agent.use_generator(generator)
    started = time.time()
    episode = EpisodeState()

    if state is not None:
        try:
            z = None if state["z"] is None else state["z"].to(agent.device)
            finetuner = finetuner_cls(agent, z, cfg)
            finetuner.load_training_state(state["finetuner"])
            replay.load_state_dict(state["replay"])
            restore_rng_state(state["rng"], rng)
            env.unwrapped.set_rng_state(state["env_rng"])
            eval_env.unwrapped.set_rng_state(state["eval_env_rng"])
            generator.set_state(state["generator"])
            step, curve, inference_info = state["step"], state["curve"], state["inference_info"]
            if state.get("episode_state") is not None:  # written mid-episode on a signal
                env.unwrapped.set_episode_state(state["episode_state"]["env"])
                episode.obs = np.asarray(state["episode_state"]["obs"], dtype=np.float32)
                skill = state["episode_state"].get("skill", z)
                episode.set_skill(None if skill is None else skill.to(agent.device))
                episode.episode_start = False
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise CheckpointError(f"cannot resume {path}: the checkpoint does not fit this run ({exc})") from exc
        ft_run.save_config(run_config)  # only now may the config change (a larger --finetune.frames)
        notify(f"[finetune] resuming {path} from step {step} (of {cfg.frames})")
        logger = MetricsLogger(ft_run, purge_step=step + 1)
    else:
        keep = finetuner_cls.keeps_inference_data(cfg)
        protocol = zero_shot_protocol(get_spec(config.agent).zero_shot)(run_config.inference)
        z, inference_info = task_skill(agent, run, config, task, protocol, rng, run_config.seed,
                                       keep_data=keep, env=env)
        if keep:
            _copy_transitions(inference_info.pop("buffer"), replay, z)
        # The inference data are discarded (§8.2 step 6) unless kept above.
        finetuner = finetuner_cls(agent, z, cfg)
        logger = MetricsLogger(ft_run)
        curve = [_curve_point(0, evaluate_policy(agent, eval_env, finetuner.skill, cfg.eval_episodes))]
        logger.log(0, _eval_metrics(curve[-1]), prefix="eval")
        step = 0
    _write_curve(ft_run, run_config, curve, inference_info, z)

    window = MetricWindow(agent.nonfinite_hint)
    needs = finetuner.replay_needs()
    finetuner.bind_replay(replay)
    bar = Progress(cfg.frames, step, f"finetune {task}", progress)
    collector = OnlineCollector(
        env, replay, agent, rng, lambda t, starting, current: finetuner.rollout_skill(t, starting, current, generator),
        lambda t: finetuner.uniform_seed_actions and t < cfg.seed_frames, state=episode)

    def save_resume(mid_episode: bool = False) -> None:
        checkpoint = {
            "kind": RESUME_KIND, "step": step, "z": None if z is None else z.cpu(), "curve": curve,
            "inference_info": inference_info, "finetuner": finetuner.training_state(),
            "replay": replay.state_dict(), "rng": rng_state(rng), "generator": generator.get_state(), "format": RESUME_FORMAT,
            "env_rng": env.unwrapped.get_rng_state(), "eval_env_rng": eval_env.unwrapped.get_rng_state()}
        if mid_episode:
            checkpoint["episode_state"] = {"env": env.unwrapped.get_episode_state(), "obs": torch.as_tensor(episode.obs),
                                           "skill": None if episode.skill is None else episode.skill.cpu()}
        save_checkpoint(ft_run, checkpoint, f"resume_{step}")

    def after_step(t: int) -> None:
        nonlocal step
        step = t  # what a checkpoint written at this step records
        if t % 1000 == 0 or t == cfg.frames:
            means = window.flush()
            if means:
                logger.log(t, means, prefix="train")
        if t % cfg.eval_every == 0 or t == cfg.frames:
            curve.append(_curve_point(t, evaluate_policy(agent, eval_env, finetuner.skill, cfg.eval_episodes)))
            logger.log(t, _eval_metrics(curve[-1]), prefix="eval")
            _write_curve(ft_run, run_config, curve, inference_info, z)

    checkpoints = ResumeCheckpoints(save_resume, window, cfg.checkpoint_every, cfg.frames, "fine-tuning",
                                    ft_run.path, last=step if state is not None else None)
    try:
        with checkpoints:
            step = loop.run(step, cfg.frames, collector, lambda: finetuner.update(needs.sample(replay, generator)),
                            cfg.seed_frames, cfg.update_every, window, checkpoints, bar, after_step)
    finally:
        bar.close()
        logger.close()
    write_json_atomic(ft_run.path / "finetune_summary.json", {
        "task": task, "frames": step, "wall_clock_s": time.time() - started,
        "zero_shot_return": curve[0]["mean_return"], "final_return": curve[-1]["mean_return"],
        **({"zero_shot_success_rate": curve[0]["success_rate"], "final_success_rate": curve[-1]["success_rate"]}
           if "success_rate" in curve[-1] else {})})
    return ft_run


def _curve_point(frames: int, evaluation: Evaluation) -> dict:
    return {"frames": frames, **evaluation.summary()}


def _eval_metrics(point: dict) -> dict:
    """What an evaluation logs: the mean return, and the success rate where the task has one."""
    return {"eval_return": point["mean_return"],
            **({"eval_success_rate": point["success_rate"]} if "success_rate" in point else {})}


def _write_curve(run: RunDir, config: FinetuneRunConfig, curve: list[dict], inference_info: dict,
                 z: torch.Tensor | None) -> None:
    write_json_atomic(run.path / "curve.json", {
        "task": config.task, "domain": config.domain, "agent": config.agent, "seed": config.seed,
        "snapshot": config.snapshot, "z": None if z is None else z.cpu().tolist(), "inference_info": inference_info,
        "curve": curve})


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
