"""Zero-shot evaluation of a pre-trained run on a task (docs/methods.md §8).

The method's family chooses the strategy (its :class:`~dvfb.agents.registry.AgentSpec`):

* ``reward_inference`` (FB, DVFB): infer the task's skill from data, then evaluate ``pi(s, z_r)``;
* ``single_policy`` (methods without skills: RND, Disagreement, ICM-APT, Proto): evaluate the one
  pre-trained policy (the baselines' protocol; these methods have no task inference).

Three ways to obtain the task vector of the ``reward_inference`` family:

* ``rewards`` (the paper's protocol): collect ``inference.steps`` reward-labelled steps in the
  task, draw ``inference.samples`` of them, keep the top reward quantile, ``z_r = proj(mean r B)``;
* ``reward_fn``: a Python function ``f(next_obs: np.ndarray (N, O)) -> rewards (N,)`` applied to the
  states of the run's own pre-training replay buffer (no task interaction);
* ``goal``: ``z = proj(B(goal))`` for a goal observation.

The result (returns, z, inference details) is written to ``RUN/zeroshot/<task>.json``.
"""

from __future__ import annotations

import importlib
import importlib.util
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import Agent, get_spec
from dvfb.config import merge, to_dict
from dvfb.errors import CheckpointError, ConfigError, RunDirError
from dvfb.replay import ReplayBuffer
from dvfb.runs import RunDir, check_writable, load_checkpoint, write_json_atomic
from dvfb.workflows.common import (
    Progress,
    check_task_in_domain,
    load_pretrained_agent,
    open_pretrained_run,
    seed_everything,
)
from dvfb.workflows.config import InferenceConfig, PretrainConfig
from dvfb.workflows.evaluate import Evaluation, collect_inference_data, evaluate_policy, run_episodes

Z_SOURCES = ("rewards", "reward_fn", "goal")


def infer_task_vector(agent: Agent, buffer, config: InferenceConfig) -> tuple[torch.Tensor, dict]:
    """Draw the inference samples from ``buffer`` and let the agent infer the task's skill (§8.2)."""
    data = buffer.transitions()
    n = data.obs.shape[0]
    if n == 0:
        raise ConfigError("no reward-labelled transitions to infer z from (inference.steps is 0?)")
    if config.with_replacement:
        index = torch.randint(0, n, (config.samples,), device=data.obs.device)
    else:
        index = torch.randperm(n, device=data.obs.device)[: config.samples]
    return agent.infer_skill(data.obs[index], data.next_obs[index], data.reward[index], config)


def load_reward_fn(spec: str) -> Callable[[np.ndarray], np.ndarray]:
    """Import ``module:function`` (or ``path/to/file.py:function``)."""
    if ":" not in spec:
        raise ConfigError(f"reward function {spec!r} must look like 'module:function' or 'file.py:function'")
    module_name, func_name = spec.rsplit(":", 1)
    try:
        if module_name.endswith(".py"):
            loader = importlib.util.spec_from_file_location("dvfb_user_reward", module_name)
            if loader is None:
                raise ImportError(module_name)
            module = importlib.util.module_from_spec(loader)
            loader.loader.exec_module(module)
        else:
            module = importlib.import_module(module_name)
        return getattr(module, func_name)
    except (ImportError, AttributeError, FileNotFoundError) as exc:
        raise ConfigError(f"cannot load reward function {spec!r}: {exc}") from exc


def infer_from_reward_fn(agent: Agent, run: RunDir, config: PretrainConfig, reward_fn: Callable,
                         inference: InferenceConfig) -> tuple[torch.Tensor, dict]:
    """Apply ``reward_fn`` to the pre-training replay states and infer z from those rewards."""
    try:
        state = load_checkpoint(run, None, map_location="cpu")
    except CheckpointError as exc:
        raise CheckpointError(f"reward_fn inference needs the run's replay buffer (a resume checkpoint): {exc}") from exc
    buffer = ReplayBuffer(config.replay_capacity, agent.obs_dim, agent.action_dim, agent.skill_dim,
                          envs.TASKS[envs.pretrain_task(config.domain)].episode_length, device=agent.device)
    buffer.load_state_dict(state["replay"])
    data = buffer.transitions()
    rewards = np.asarray(reward_fn(data.next_obs.cpu().numpy()), dtype=np.float32).reshape(-1)
    if rewards.shape[0] != data.next_obs.shape[0]:
        raise ConfigError(f"reward function returned {rewards.shape[0]} rewards for {data.next_obs.shape[0]} states")
    reward_t = torch.as_tensor(rewards, device=agent.device)
    index = torch.randperm(reward_t.shape[0], device=agent.device)[: inference.samples]
    return agent.infer_skill(data.obs[index], data.next_obs[index], reward_t[index], inference)


def result_path(run: RunDir, task: str, snapshot: int, final_snapshot: int) -> Path:
    name = task if snapshot == final_snapshot else f"{task}@{snapshot}"
    return run.path / "zeroshot" / f"{name}.json"


def zeroshot(run_path: str | Path, task: str, *, snapshot: int | None = None, inference: dict | None = None,
             seed: int | None = None, z_source: str = "rewards", reward_fn: str | Callable | None = None,
             goal: np.ndarray | None = None, overwrite: bool = False, device: str | None = None,
             progress: bool | None = None) -> dict:
    """Infer z for ``task`` from a pre-trained run and evaluate ``pi(., z)``; returns the result.

    ``progress``: True shows a bar, False nothing, None a bar on a terminal and otherwise a line
    every ``DVFB_PROGRESS_SECONDS`` seconds.
    """
    if z_source not in Z_SOURCES:
        raise ConfigError(f"z_source must be one of {Z_SOURCES}, got {z_source!r}")
    run, config = open_pretrained_run(run_path)
    if z_source != "rewards" and get_spec(config.agent).zero_shot != "reward_inference":
        raise ConfigError(f"--z-source {z_source} needs a method that infers skills; {config.agent!r} has a single "
                          "policy (use the default)")
    check_task_in_domain(task, config.domain)
    cfg = merge(config.inference, inference or {}, "inference.")
    agent, snapshot = load_pretrained_agent(run, config, snapshot, device)
    final = max(config.frames, snapshot)
    out = result_path(run, task, snapshot, final)
    if out.exists() and not overwrite:
        raise RunDirError(f"{out} exists; pass --overwrite to replace it")
    if goal is not None and z_source == "goal":
        check_goal(goal, agent.obs_dim, config.domain)
    # The result is written at the end: fail now, not after the work, if it cannot be.
    check_writable(out.parent if out.parent.exists() else run.path)
    seed = config.seed if seed is None else seed
    rng = seed_everything(seed)
    started = time.time()
    episode_length = envs.TASKS[task].episode_length
    collected = cfg.steps if (z_source == "rewards" and get_spec(config.agent).zero_shot == "reward_inference") else 0
    bar = Progress(collected + cfg.eval_episodes * episode_length, 0, f"zeroshot {task}", progress, unit="step")
    try:
        z, info = task_skill(agent, run, config, task, cfg, rng, seed, z_source, reward_fn, goal, progress=bar)
        eval_env = envs.make(task, seed=seed)
        evaluation = evaluate_policy(agent, eval_env, z, cfg.eval_episodes, progress=bar)
    finally:
        bar.close()
    result = {
        "task": task, "domain": config.domain, "agent": config.agent, "preset": config.preset,
        "pretrain_seed": config.seed, "seed": seed, "snapshot_frames": snapshot,
        "z_source": z_source if get_spec(config.agent).zero_shot == "reward_inference" else "none",
        "inference": to_dict(cfg), "inference_info": info, "z": None if z is None else z.cpu().tolist(),
        **evaluation.summary(), "eval_episodes": len(evaluation.returns), "wall_clock_s": time.time() - started,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out, result)
    return result


def task_skill(agent: Agent, run: RunDir, config: PretrainConfig, task: str, cfg, rng: np.random.Generator,
               seed: int, z_source: str = "rewards", reward_fn: str | Callable | None = None,
               goal: np.ndarray | None = None, keep_data: bool = False, env=None,
               progress=None) -> tuple[torch.Tensor | None, dict]:
    """The skill the policy is evaluated with, by the method family's zero-shot strategy.

    ``reward_inference``: collected reward-labelled steps (or a reward function, or a goal);
    ``single_policy``: no skill (None) and no task interaction. With ``keep_data`` the collected
    buffer is returned in ``info["buffer"]`` (fine-tuning's D12 option). ``env``: the task
    environment to collect in (fine-tuning goes on in the same one); by default a new one.
    """
    strategy = get_spec(config.agent).zero_shot
    if strategy == "single_policy":
        return None, {"strategy": "single_policy"}
    if z_source == "rewards":
        env = env if env is not None else envs.make(task, seed=seed)
        buffer = collect_inference_data(agent, env, cfg.steps, cfg.random_action_steps, rng,
                                        envs.TASKS[task].episode_length, progress=progress)
        z, info = infer_task_vector(agent, buffer, cfg)
        if keep_data:
            info["buffer"] = buffer
        return z, info
    if z_source == "reward_fn":
        if reward_fn is None:
            raise ConfigError("z_source 'reward_fn' needs a reward function")
        fn = load_reward_fn(reward_fn) if isinstance(reward_fn, str) else reward_fn
        return infer_from_reward_fn(agent, run, config, fn, cfg)
    if goal is None:
        raise ConfigError("z_source 'goal' needs a goal observation")
    z = agent.skill_from_goal(torch.as_tensor(goal, dtype=torch.float32))
    return z, {"goal": np.asarray(goal, dtype=float).tolist()}


def check_goal(goal: np.ndarray, obs_dim: int, domain: str) -> None:
    """A goal is one observation of the domain (or an (s, s') pair for B's pair inputs)."""
    size = int(np.asarray(goal).size)
    if size not in (obs_dim, 2 * obs_dim):
        raise ConfigError(f"--goal has {size} values but {domain} observations have {obs_dim}")
    if not np.all(np.isfinite(np.asarray(goal, dtype=float))):
        raise ConfigError("--goal holds a non-finite value")


def random_policy_evaluation(task: str, episodes: int, seed: int = 0) -> Evaluation:
    """Uniform-random actions: the floor every zero-shot table should show (returns, and success
    rates where the task has them)."""
    env = envs.make(task, seed=seed)
    rng = np.random.default_rng(seed)
    shape = env.action_space.shape
    return run_episodes(env, lambda obs: rng.uniform(-1, 1, shape).astype(np.float32), episodes)


def random_policy_return(task: str, episodes: int, seed: int = 0) -> list[float]:
    """Returns of a uniform-random policy (:func:`random_policy_evaluation`)."""
    return random_policy_evaluation(task, episodes, seed).returns


__all__ = ["PretrainConfig", "Z_SOURCES", "infer_task_vector", "random_policy_evaluation", "random_policy_return",
           "zeroshot"]
