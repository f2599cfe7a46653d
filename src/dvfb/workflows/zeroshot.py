"""Zero-shot evaluation of a pre-trained run on a task (docs/methods.md §8, "Protocols").

The method's registered zero-shot protocol (:mod:`dvfb.protocols.zeroshot`) finds the skill the
policy is evaluated with: reward inference (FB family), the single policy (exploration baselines)
or skill selection (skill discovery). Protocols that infer skills from data also take

* ``reward_fn``: a Python function ``f(next_obs: np.ndarray (N, O)) -> rewards (N,)`` applied to the
  states of the run's own pre-training replay buffer (no task interaction);
* ``dataset``: the transitions of a dataset (``dvfb dataset export``; by default the one an offline
  run trained on) with the task's rewards relabelled from their physics states;
* ``goal``: a goal observation.

An exported model (docs/sharing.md, "Evaluate") is evaluated in a run directory made from it, with
its ``inference_data.npz`` (``inference_data``): the states a reward function is applied to, and,
relabelled from their physics states, the samples of ``skill_source="dataset"`` without a dataset.

The result (returns, the skill, the protocol's details) is written to ``RUN/zeroshot/<task>.json``
(:class:`~dvfb.runs.records.ZeroShotResult`). One implementation serves a run and a group of runs
(docs/members.md): a run is a group of one.
"""

from __future__ import annotations

import importlib
import importlib.util
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import Model, get_spec
from dvfb.core.config import merge, to_dict
from dvfb.core.errors import CheckpointError, ConfigError, RunDirError
from dvfb.data import PHYSICS_COLUMN, ReplayBuffer, read_dataset, read_info
from dvfb.data.datasets import check_same_data
from dvfb.nets.members import stack_agents
from dvfb.protocols import SKILL_SOURCES, ZeroShotProtocol, zero_shot_protocol
from dvfb.protocols.zeroshot import collect_inference_data, infer_task_vector
from dvfb.runs import check_writable
from dvfb.runs.layout import PretrainRun
from dvfb.runs.records import ZeroShotResult
from dvfb.runs.run_config import PretrainConfig
from dvfb.runs.snapshots import load_model
from dvfb.training.evaluation import Evaluation, evaluate, run_episodes
from dvfb.training.progress import Progress
from dvfb.training.rollout import Lane, Policy
from dvfb.training.seeding import run_generator, seed_everything
from dvfb.workflows.group import check_one_method
from dvfb.workflows.resources import evaluation_tasks, open_run


def run_protocol(config: PretrainConfig, overrides: dict | None = None, source: str | None = None) -> ZeroShotProtocol:
    """The run's zero-shot protocol with its ``inference`` config (plus ``--inference.*`` overrides);
    with ``source``, the skill source is checked first (a method without that inference is named as
    such, not by the options its protocol does not have)."""
    cls = zero_shot_protocol(get_spec(config.agent).zero_shot)
    if source is not None:
        cls.check_source(source, config.agent)
    return cls(merge(config.inference, overrides or {}, "inference."))


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


def infer_from_reward_fn(model: Model, run: PretrainRun | None, reward_fn: Callable, protocol: ZeroShotProtocol,
                         rng: np.random.Generator | None = None, config: PretrainConfig | None = None,
                         states: tuple[torch.Tensor, torch.Tensor, str] | None = None) -> tuple[torch.Tensor, dict]:
    """Apply ``reward_fn`` to states and infer the skill from those rewards.

    The states are ``states`` (observations, next observations, where they come from) when given
    (an exported model's inference data), else those of the run's pre-training replay (its newest
    resume checkpoint). Without either (a shipped snapshot such as the bundled demo model, or an
    exported model without inference data: ``run`` None and its ``config``), they are collected in
    the domain's reward-free environment with the protocol's data-collection rule and budget
    (``inference.steps``, uniform actions first). ``info["states"]`` says which was used.
    """
    config = run.config if run is not None else config
    if states is not None:
        obs, next_obs, source = states
    else:
        obs, next_obs, source = _inference_states(model, run, config, protocol, rng)
    rewards = np.asarray(reward_fn(next_obs.cpu().numpy()), dtype=np.float32).reshape(-1)
    if rewards.shape[0] != next_obs.shape[0]:
        raise ConfigError(f"reward function returned {rewards.shape[0]} rewards for {next_obs.shape[0]} states")
    reward_t = torch.as_tensor(rewards, device=model.device)
    skill, info = protocol.skill_from_samples(model, obs, next_obs, reward_t)
    return skill, {**info, "states": source}


def _inference_states(model: Model, run: PretrainRun | None, config: PretrainConfig, protocol: ZeroShotProtocol,
                      rng: np.random.Generator | None) -> tuple[torch.Tensor, torch.Tensor, str]:
    episode_length = envs.TASKS[envs.pretrain_task(config.domain)].episode_length
    state = None
    if run is not None:
        try:
            state = run.resume_state()
        except CheckpointError:
            state = None
    if run is not None and config.dataset:  # an offline run: its dataset's states
        buffer, _ = read_dataset(config.dataset, model.device, model.skill_dim)
        source = f"the run's dataset {config.dataset}"
    elif state is not None:
        buffer = ReplayBuffer.from_state(state["replay"], model.device)
        source = "the run's pre-training replay"
    else:
        c = protocol.config
        env = envs.make(envs.pretrain_task(config.domain), seed=config.seed, reward_free=True)
        rng = rng if rng is not None else np.random.default_rng(config.seed)
        buffer = collect_inference_data(model, env, c.steps, c.random_action_steps, rng, episode_length)
        what = "the run has no replay" if run is not None else "no inference data"
        source = f"{c.steps} steps collected in {envs.pretrain_task(config.domain)} ({what})"
    data = buffer.transitions()
    return data.obs, data.next_obs, source


def exported_states(data: dict[str, np.ndarray], device) -> tuple[torch.Tensor, torch.Tensor, str]:
    """The observations and next observations of an exported model's inference data, and what they are."""
    return (torch.as_tensor(data["obs"], dtype=torch.float32, device=device),
            torch.as_tensor(data["next_obs"], dtype=torch.float32, device=device),
            f"the exported model's inference data ({len(data['obs'])} transitions)")


def infer_from_exported_data(model: Model, config: PretrainConfig, task: str, protocol: ZeroShotProtocol,
                             data: dict[str, np.ndarray]) -> tuple[torch.Tensor, dict]:
    """The skill from an exported model's inference samples with ``task``'s rewards recomputed from
    the physics states of their next observations (docs/sharing.md, "Evaluate"), as a dataset's."""
    next_physics = data.get(f"next_{PHYSICS_COLUMN}")
    if next_physics is None:
        raise ConfigError("--skill-source dataset relabels the exported model's inference data from their physics "
                          "states, but its inference_data.npz has none of the next observations (the run did not "
                          "record physics, or an older dvfb exported it); use --skill-source rewards or reward_fn, "
                          "or give --dataset DIR")
    env = envs.make(task, seed=config.seed)
    rewards = env.unwrapped.rewards_from_physics(next_physics)
    obs, next_obs, source = exported_states(data, model.device)
    reward_t = torch.as_tensor(rewards, dtype=torch.float32, device=model.device).reshape(-1, 1)
    skill, info = protocol.skill_from_samples(model, obs, next_obs, reward_t)
    return skill, {**info, "states": f"{source}, rewards of {task} relabelled from physics"}


def infer_from_dataset(model: Model, run: PretrainRun, task: str, protocol: ZeroShotProtocol,
                       dataset: str | Path | None) -> tuple[torch.Tensor, dict]:
    """The skill from a dataset's transitions with ``task``'s rewards recomputed from their physics
    states (docs/methods.md, "Datasets"): ``dataset``, or the one the run trained on offline, which
    must still hold the data the run recorded."""
    config = run.config
    path = dataset or config.dataset
    if not path:
        raise ConfigError("--skill-source dataset needs --dataset DIR (a dataset of the run's domain; an offline "
                          "run defaults to its own)")
    info = read_info(path)
    if info.domain != config.domain:
        raise ConfigError(f"dataset {path} holds {info.domain} data; the run is on {config.domain}")
    recorded = run.trained_on()
    if recorded is not None and Path(path).resolve() == Path(recorded.get("path", "")).resolve():
        check_same_data(recorded, info, path, f"run {run.path}")
    buffer, _ = read_dataset(path, model.device, columns=(PHYSICS_COLUMN,))
    data = buffer.transitions()
    env = envs.make(task, seed=config.seed)
    rewards = env.unwrapped.rewards_from_physics(data.columns["next_" + PHYSICS_COLUMN].cpu().numpy())
    reward_t = torch.as_tensor(rewards, dtype=torch.float32, device=model.device).reshape(-1, 1)
    skill, info_ = protocol.skill_from_samples(model, data.obs, data.next_obs, reward_t)
    return skill, {**info_, "states": f"dataset {path} ({info.transitions} transitions, rewards of {task} "
                                      "relabelled from physics)"}


def zeroshot(run_dir: str | Path | Sequence[str | Path], task: str, *, snapshot: int | None = None,
             inference: dict | None = None, seed: int | None = None, skill_source: str = "rewards",
             reward_fn: str | Callable | None = None, goal: np.ndarray | None = None, overwrite: bool = False,
             device: str | None = None, progress: bool | None = None, dataset: str | Path | None = None,
             skip_existing: bool = False, torch_threads: int | None = None,
             inference_data: dict[str, np.ndarray] | None = None):
    """Find the task's skill by the run's zero-shot protocol and evaluate ``pi(., skill)``; returns
    the result (a dict of the result file's fields).

    Given a list of runs, a group (docs/members.md) in one pass: each member's skill by its own
    protocol and random streams, as its separate zero-shot finds it; then the evaluation episodes of
    all members in lockstep, their actions from one batched forward of the stacked actors. Each
    member's result goes to its own run; the list of results is returned. The runs must be one method
    with one configuration (seeds aside) and have the snapshot. With ``skip_existing``, the runs
    that already have the task's result are left out (their entry is None) instead of being an error.

    ``progress``: True shows a bar, False nothing, None a bar on a terminal and otherwise a line
    every ``DVFB_PROGRESS_SECONDS`` seconds. ``torch_threads``: the command's ``--torch-threads``
    (:func:`~dvfb.workflows.resources.use_threads`; None: the run's own setting or the default).
    ``inference_data``: an exported model's inference samples (module docstring), for one run.
    """
    for option, value, source in (("--dataset", dataset, "dataset"), ("--reward-fn", reward_fn, "reward_fn"),
                                  ("--goal", goal, "goal")):
        if value is not None and skill_source != source:
            # It would be ignored: say so rather than infer the skill from something else.
            raise ConfigError(f"{option} is used only with --skill-source {source} (this command's source is "
                              f"{skill_source!r}): add --skill-source {source} or leave out {option}")
    many = not isinstance(run_dir, (str, Path))
    run_paths = list(run_dir) if many else [run_dir]
    if not run_paths:
        raise ConfigError("a group zero-shot needs at least one run")
    if inference_data is not None and many:
        raise ConfigError("an exported model's inference data belong to one model: evaluate exported models one at "
                          "a time")
    if len({Path(p).resolve() for p in run_paths}) != len(run_paths):
        raise ConfigError("a run is listed twice: the members of a group are distinct runs")
    members = []
    for run_path in run_paths:
        run = open_run(run_path, torch_threads)
        protocol = run_protocol(run.config, inference, skill_source)
        evaluation_tasks(run.config, [task])
        members.append((run, protocol))
    if many:
        check_one_method([(run, run.config) for run, _protocol in members])
    loaded = []
    for run, protocol in members:
        model, snap = load_model(run, snapshot, device)
        out = run.zeroshot_result(task, snap)
        if out.exists() and not overwrite:
            if skip_existing:
                loaded.append(None)
                continue
            raise RunDirError(f"{out} exists; pass --overwrite to replace it")
        if goal is not None and skill_source == "goal":
            check_goal(goal, model.goal_widths(), run.config.domain)
        # The result is written at the end: fail now, not after the work, if it cannot be.
        check_writable(out.parent if out.parent.exists() else run.path)
        loaded.append((model, snap))
    todo = [(run, protocol, *load) for (run, protocol), load in zip(members, loaded) if load is not None]
    if not todo:
        return [None] * len(members) if many else None
    if len({snap for *_rest, snap in todo}) != 1:
        raise ConfigError("the members' snapshots are of different frames; pass --snapshot")
    started = time.time()
    episode_length = envs.TASKS[task].episode_length
    first = todo[0][1]
    bar = Progress(len(todo) * (first.task_steps(skill_source) + first.eval_episodes * episode_length), 0,
                   f"zeroshot {task}" + (f" ({len(todo)} members)" if many else ""), progress, unit="step")
    skills, infos, seeds, eval_envs = [], [], [], []
    try:
        for run, protocol, model, _snap in todo:
            member_seed = run.config.seed if seed is None else seed
            rng = seed_everything(member_seed)
            model.use_generator(run_generator(member_seed, model.device))  # the evaluation's own random stream
            z, info = task_skill(model, run, task, protocol, rng, member_seed, skill_source, reward_fn, goal,
                                 progress=bar, dataset=dataset, inference_data=inference_data)
            skills.append(z)
            infos.append(info)
            seeds.append(member_seed)
            eval_envs.append(envs.make(task, seed=member_seed))
        models = [model for _run, _protocol, model, _snap in todo]
        acting = models[0] if len(models) == 1 else stack_agents(models)
        evaluations = evaluate(acting.act, eval_envs, skills, first.eval_episodes, progress=bar)
    finally:
        bar.close()
    group = [str(run.path) for run, *_rest in todo] if many else None
    results = []
    for (run, protocol, model, snap), z, info, member_seed, evaluation in zip(todo, skills, infos, seeds, evaluations):
        config = run.config
        result = ZeroShotResult(
            task=task, domain=config.domain, agent=config.agent, preset=config.preset, pretrain_seed=config.seed,
            seed=member_seed, snapshot_frames=snap, protocol=protocol.name,
            skill_source=skill_source if model.skill.has_skill else "none", inference=to_dict(protocol.config),
            inference_info=info, z=None if z is None else z.cpu().tolist(), **evaluation.summary(),
            eval_episodes=len(evaluation.returns), wall_clock_s=time.time() - started, group=group)
        run.write_zeroshot_result(result)
        results.append(result.to_json())
    by_run = dict(zip([id(run) for run, *_rest in todo], results))
    answers = [by_run.get(id(run)) for run, _protocol in members]
    return answers if many else answers[0]


def task_skill(model: Model, run: PretrainRun, task: str, protocol: ZeroShotProtocol,
               rng: np.random.Generator, seed: int, skill_source: str = "rewards", reward_fn: str | Callable | None = None,
               goal: np.ndarray | None = None, keep_data: bool = False, env=None,
               progress=None, dataset: str | Path | None = None,
               inference_data: dict[str, np.ndarray] | None = None) -> tuple[torch.Tensor | None, dict]:
    """The skill the policy is evaluated with, by the run's zero-shot protocol.

    ``skill_source``: interaction with the task (``rewards``), a reward function over the run's replay
    states, or a goal, where the protocol supports them. With ``keep_data`` the collected buffer is
    returned in ``info["buffer"]`` (fine-tuning's D12 option). ``env``: the task environment to
    collect in (fine-tuning goes on in the same one); by default a new one. ``inference_data``: an
    exported model's samples (module docstring), used instead of the run's replay.
    """
    config = run.config
    protocol.check_source(skill_source, config.agent)
    if skill_source == "rewards":
        env = env if env is not None else envs.make(task, seed=seed)
        return protocol.task_skill(model, env, rng, envs.TASKS[task].episode_length, progress=progress,
                                   keep_data=keep_data)
    if skill_source == "reward_fn":
        if reward_fn is None:
            raise ConfigError("skill_source 'reward_fn' needs a reward function")
        fn = load_reward_fn(reward_fn) if isinstance(reward_fn, str) else reward_fn
        states = exported_states(inference_data, model.device) if inference_data is not None else None
        return infer_from_reward_fn(model, run, fn, protocol, rng, states=states)
    if skill_source == "dataset":
        if dataset is None and inference_data is not None:
            return infer_from_exported_data(model, config, task, protocol, inference_data)
        return infer_from_dataset(model, run, task, protocol, dataset)
    if goal is None:
        raise ConfigError("skill_source 'goal' needs a goal observation")
    return protocol.skill_from_goal(model, goal)


def check_goal(goal, widths: tuple[int, ...], domain: str, name: str = "--goal") -> None:
    """A goal is numbers of one of the widths the model accepts (an observation of the domain, or
    what else its skill-from-goal map reads), all finite; ``name`` is what the error calls it."""
    try:
        values = np.asarray(goal, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name} must be numbers (one {domain} observation): {exc}") from exc
    if values.size not in widths or values.ndim > 1 and values.shape[0] != 1:
        raise ConfigError(f"{name} has shape {values.shape} ({values.size} values) but {domain} observations have "
                          f"{widths[0]}" if values.ndim > 1 else
                          f"{name} has {values.size} values but {domain} observations have {widths[0]}")
    if not np.all(np.isfinite(values)):
        raise ConfigError(f"{name} holds a non-finite value")


def random_policy_evaluation(task: str, episodes: int, seed: int = 0) -> Evaluation:
    """Uniform-random actions: the floor every zero-shot table should show (returns, and success
    rates where the task has them)."""
    lanes = [Lane(envs.make(task, seed=seed), np.random.default_rng(seed))]
    return run_episodes(lanes, Policy(None, uniform=lambda step: True), episodes)[0]


def random_policy_return(task: str, episodes: int, seed: int = 0) -> list[float]:
    """Returns of a uniform-random policy (:func:`random_policy_evaluation`)."""
    return random_policy_evaluation(task, episodes, seed).returns


__all__ = ["SKILL_SOURCES", "infer_task_vector", "run_protocol", "random_policy_evaluation", "random_policy_return",
           "zeroshot"]
