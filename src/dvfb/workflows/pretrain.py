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

import contextlib
import logging
import time
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec, make_agent
from dvfb.config import replace, to_dict
from dvfb.data import read_dataset, read_info
from dvfb.errors import CheckpointError, ConfigError
from dvfb.data import ReplayBuffer, physics_columns
from dvfb.runs import (
    PRETRAIN_RESUME_KIND,
    MetricsLogger,
    RunDir,
    RunLock,
    load_checkpoint,
    remove_orphaned_checkpoints,
    save_checkpoint,
    save_snapshot,
)
from dvfb.training import loop
from dvfb.training.loop import DatasetSource, EpisodeState, OnlineCollector
from dvfb.training.checkpointing import ResumeCheckpoints
from dvfb.training.metrics import MetricWindow
from dvfb.training.progress import Progress, notify, progress_bars
from dvfb.runs.layout import PretrainRun, snapshot_name
from dvfb.runs.migrations import RESUME_FORMAT, check_resume_format
from dvfb.runs.records import PretrainSummary
from dvfb.runs.run_config import PretrainConfig
from dvfb.runs.snapshots import snapshot_state
from dvfb.training.seeding import restore_rng_state, rng_state, run_generator, seed_everything
from dvfb.workflows.resources import check_memory, check_replay, check_task_in_domain, learner_state_bytes, setup_torch
from dvfb.nets.members import member_slice, member_training_state, stack_agents
from dvfb.workflows.groups import MemberGroup

log = logging.getLogger(__name__)

RESUME_KIND = PRETRAIN_RESUME_KIND
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
    config, trained_task, dataset_info = _checked(config, [run_path], resume, overwrite)
    device = setup_torch(config)
    rng = seed_everything(config.seed)
    env, agent, episode_length, columns = _member_parts(config, trained_task, device)
    check_memory(_memory_parts(config, env, agent, episode_length, columns, dataset_info, 1),
                 f"pretrain {config.agent} {config.domain}", device)
    dataset = _read_dataset(config, dataset_info, agent, device, progress)
    lock = RunLock(run_path)
    with lock:
        try:
            session = PretrainSession(config, run_path, resume, overwrite, command, device, rng, env, agent,
                                      episode_length, columns, dataset, dataset_info)
            if session.finished:
                return session.run
            bar = Progress(config.frames, session.step, f"pretrain {config.agent} {config.domain}", progress)
            checkpoints = ResumeCheckpoints(session.save_resume, session.window, config.checkpoint_every,
                                            config.frames, "pre-training", session.run.path, last=session.last_checkpoint)
            try:
                with checkpoints:
                    step = loop.run(session.step, config.frames, session.collector,
                                    lambda: agent.update(session.sample()), config.seed_frames, config.update_every,
                                    session.window, checkpoints, bar, session.after_step,
                                    None if session.offline else session.after_episode)
                    if columns:  # a dataset's run: the final checkpoint holds every finished episode
                        checkpoints.ensure(step, mid_episode=not session.episode.episode_start)
            finally:
                bar.close()
                session.logger.close()
            session.finish(resume)
            return session.run
        except BaseException:
            lock.remove_if_created()
            raise


def pretrain_group(config: PretrainConfig, seeds: list[int], run_paths: list[str | Path], *, resume: bool = False,
                   overwrite: bool = False, progress: bool | None = None,
                   command: list[str] | None = None) -> list[RunDir]:
    """Pre-train one member per seed in lockstep in this process (docs/members.md): member k is
    the run ``config`` with ``seed = seeds[k]`` in ``run_paths[k]``, an ordinary run directory.

    Each member has its own environment, replay, random streams, episode, logs, snapshots and
    resume checkpoints (each one a separate run's, so a member may also be resumed alone); the
    networks of all members are stacked, so an update and an action are one batched pass for all.
    A member whose loss or action goes non-finite stops with the usual one line naming its run;
    the others finish, and the call then raises :class:`~dvfb.errors.NonFiniteLossError` naming the stopped
    members. ``resume`` continues every member (all must stand at the same step).
    """
    if len(seeds) < 1 or len(seeds) != len(run_paths):
        raise ConfigError("a group needs one run directory per seed")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds lists a seed twice ({', '.join(map(str, seeds))}); members need distinct seeds")
    paths = [Path(p) for p in run_paths]
    if len({p.resolve() for p in paths}) != len(paths):
        raise ConfigError("the members of a group need distinct run directories")
    if not resume:  # every member's directory is checked before any is created
        for path in paths:
            RunDir.check_new(path, overwrite)
    configs = [replace(config, seed=seed) for seed in seeds]
    base, trained_task, dataset_info = _checked(configs[0], paths, resume, overwrite)
    configs = [replace(base, seed=seed) for seed in seeds]
    device = setup_torch(base)
    what = f"pretrain {base.agent} {base.domain} ({len(seeds)} members)"
    parts = []
    for k, member_config in enumerate(configs):
        rng = seed_everything(member_config.seed)
        parts.append((rng, *_member_parts(member_config, trained_task, device)))
        if k == 0:  # refuse a group that cannot fit before building the other members
            _rng, env, agent, episode_length, columns = parts[0]
            check_memory(_memory_parts(base, env, agent, episode_length, columns, dataset_info, len(seeds)),
                         what, device)
    dataset = _read_dataset(base, dataset_info, parts[0][2], device, progress)
    locks = [RunLock(p) for p in paths]
    with contextlib.ExitStack() as stack:
        try:
            for lock in locks:  # a member in use: the directories locked so far are removed again
                stack.enter_context(lock)
            return _run_group(configs, paths, parts, resume, overwrite, command, device, dataset, dataset_info,
                              progress, what)
        except BaseException:
            for lock in locks:
                lock.remove_if_created()
            raise


def _run_group(configs, paths, parts, resume, overwrite, command, device, dataset, dataset_info, progress,
               what) -> list[RunDir]:
    sessions = [PretrainSession(c, p, resume, overwrite, command, device, rng, env, agent, length, columns,
                                dataset, dataset_info)
                for c, p, (rng, env, agent, length, columns) in zip(configs, paths, parts)]
    if any(s.finished for s in sessions):
        if all(s.finished for s in sessions):
            return [s.run for s in sessions]
        raise ConfigError("some members of the group have finished and others not: resume the others alone")
    steps = {s.step for s in sessions}
    if len(steps) != 1:
        raise CheckpointError("the members' latest checkpoints are of different steps ("
                              + ", ".join(f"{s.run.path}: {s.step}" for s in sessions)
                              + "): a group resumes in lockstep; resume them alone")
    base = configs[0]
    group = MemberGroup(sessions, stack_agents([agent for _rng, _env, agent, _length, _columns in parts]), what,
                        "pre-training", lambda obs, skill: group.learner.act_members(obs, skill, explore=True),
                        log_episodes=True)

    def after_step(t: int) -> None:
        for session in list(group.live):
            session.after_step(t)
        for session in group.ended_episodes():
            session.after_episode(t, session.collector.state)

    bar = Progress(base.frames, sessions[0].step, what, progress)
    checkpoints = ResumeCheckpoints(group.save, group.window, base.checkpoint_every, base.frames, "pre-training",
                                    paths[0].parent, last=sessions[0].last_checkpoint)
    columns = parts[0][4]
    try:
        with checkpoints:
            step = loop.run(sessions[0].step, base.frames, group.source, group.update, base.seed_frames,
                            base.update_every, group.window, checkpoints, bar, after_step, None)
            group.window.flush()
            if columns:
                checkpoints.ensure(step, mid_episode=not group.source.state.episode_start)
    finally:
        bar.close()
        group.close_logs()
    for session in group.live:
        session.finish(resume)
    group.raise_if_stopped()
    return [s.run for s in sessions]


def _checked(config: PretrainConfig, run_paths: list[Path], resume: bool, overwrite: bool):
    """The checks of a pre-training before anything is built; returns the config as it runs (an
    offline run updates every step), the trained task (the supervised reference) and the dataset's
    info."""
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite contradict each other: --resume continues the run in "
                          f"{run_paths[0]}, --overwrite deletes it; pass one of them")
    envs.check_domain(config.domain)
    for run_path in run_paths:
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
    return config, trained_task, dataset_info


def _member_parts(config: PretrainConfig, trained_task: str | None, device):
    """The environment and the agent of one run (after its seeding), the episode length and the
    replay's extra columns."""
    env = envs.make(trained_task or config.domain, seed=config.seed, reward_free=True)
    obs_dim = env.observation_space.shape[0]
    action_dim = env.action_space.shape[0]
    agent = make_agent(config.agent, obs_dim, action_dim, config, device)
    episode_length = envs.TASKS[trained_task or envs.pretrain_task(config.domain)].episode_length
    check_replay(config.replay_capacity, "--replay-capacity", agent.replay_needs(), episode_length, config.domain)
    columns = physics_columns(env.unwrapped.physics_width) if config.replay.record_physics else None
    return env, agent, episode_length, columns


def _memory_parts(config, env, agent, episode_length, columns, dataset_info, members: int) -> dict[str, int]:
    """What ``members`` runs like this one hold: their replays (one dataset, shared, offline) and
    their networks."""
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    capacity = config.replay_capacity if dataset_info is None else dataset_info.transitions
    replay = ReplayBuffer.estimate_nbytes(capacity, obs_dim, action_dim, agent.skill_dim, episode_length, columns)
    if members == 1:
        return {"replay": replay, "networks": learner_state_bytes(agent)}
    return {f"replay ({'1 dataset' if dataset_info is not None else f'{members} members'})":
            replay * (1 if dataset_info is not None else members),
            f"networks ({members} members)": learner_state_bytes(agent) * members}


def _read_dataset(config, dataset_info, agent, device, progress):
    if dataset_info is None:
        return None
    obs_dim, action_dim = agent.obs_dim, agent.action_dim
    if (dataset_info.obs_dim, dataset_info.action_dim) != (obs_dim, action_dim):
        raise ConfigError(f"--dataset {config.dataset} has observations of {dataset_info.obs_dim} and actions of "
                          f"{dataset_info.action_dim} values; {config.domain} has {obs_dim} and {action_dim}")
    # Read whole before the run directory exists: a bad file creates nothing.
    dataset, _ = read_dataset(config.dataset, device, agent.skill_dim, progress=progress_bars(progress))
    return dataset


class PretrainSession:
    """One run directory's share of a pre-training: the run, its replay, random streams, episode,
    logs, snapshots and resume checkpoints. A run has one; a group (docs/members.md) one per member.

    Built inside the run's lock: it creates (or, resuming, opens and restores) the run, and loads
    the checkpoint into ``agent`` (an ordinary agent; a group stacks its members' afterwards and
    calls :meth:`bind_member`). ``finished``: a resumed run that had already finished.
    """

    def __init__(self, config, run_path, resume, overwrite, command, device, rng, env, agent, episode_length,
                 columns, dataset=None, dataset_info=None):
        self.config, self.env, self.rng, self.columns, self.device = config, env, rng, columns, device
        self.seed = config.seed
        self.finished = False
        obs_dim, action_dim = agent.obs_dim, agent.action_dim
        state = None
        if resume:
            run = PretrainRun.open(run_path)
            _check_resume_config(run.config, config)
            finished = run.finished_frames()
            if finished is not None and finished >= config.frames:
                notify(f"[pretrain] {run.path} already finished at {finished} frames (>= --frames {config.frames}); "
                       "nothing to resume")
                self.run, self.finished = run, True
                return
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
            run = PretrainRun.create(run_path, config, overwrite=overwrite, command=command)
        self.run = run
        self.offline = offline = dataset is not None
        # What an offline checkpoint records instead of the replay: which data it trained on.
        self.fingerprint = None if not offline else {
            "path": str(Path(config.dataset).resolve()), "episodes": dataset_info.episodes,
            "transitions": dataset_info.transitions, "files": list(dataset_info.files)}
        self.replay = replay = dataset if offline else ReplayBuffer(
            config.replay_capacity, obs_dim, action_dim, agent.skill_dim, max_episode_length=episode_length,
            device=device, sampler=config.replay.sampler(), columns=columns)
        self.needs = agent.replay_needs()
        self.step = 0
        self.episode = episode = EpisodeState()
        # The run's own random stream: skill draws, policy noise, the agent's modules and its batches.
        self.generator = generator = run_generator(config.seed, device)
        agent.use_generator(generator)
        if state is not None:
            try:
                agent.load_training_state(state["agent_state"])
                generator.set_state(state["generator"])
                if offline:
                    if state.get("dataset", {}).get("files") != self.fingerprint["files"]:
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
            self.step, episode.episode = state["step"], state["episode"]
            # Only now, with the checkpoint loaded, may the run's config change (a larger --frames).
            run.save_config(config)
            notify(f"[pretrain] resuming {run.path} from step {self.step} (of {config.frames})")
        self.last_checkpoint = self.step if state is not None else None

        # Records up to the checkpointed step belong to the restored state; later ones are redone.
        self.logger = MetricsLogger(run, purge_step=self.step + 1 if resume else None)
        self.window = MetricWindow(agent.nonfinite_hint)
        self.snapshots = set(config.snapshot_frames) | {config.frames}
        self.started = time.time()
        self.start_step = self.step
        self.bind_member(agent, None)
        self.collector = DatasetSource() if offline else OnlineCollector(
            env, replay, agent, rng, self.next_skill, lambda t: t < config.seed_frames, reward_key="task_reward",
            first_reset_seed=None if state is not None else config.seed, state=episode,
            physics=env.unwrapped.physics_state if columns else None)

    def bind_member(self, agent, index: int | None) -> None:
        """Whose state this run saves: ``agent`` itself (``index`` None), or member ``index`` of a
        stacked group (the index changes when a member before it stops)."""
        self.agent, self.index = agent, index

    def next_skill(self, t: int, episode_start: bool, current):
        # The method's declared rule (docs/methods.md, "Skills"); its prior draws the new skill,
        # from this run's own stream (a group's agent draws for each member from the member's).
        agent = self.agent
        return agent.sample_skill(1, generator=self.generator)[0] if agent.skill.due(t, episode_start) else current

    def sample(self):
        return self.needs.sample(self.replay, self.generator)

    def training_state(self) -> dict:
        if self.index is None:
            return self.agent.training_state()
        return member_training_state(self.agent, self.index)

    def snapshot(self, t: int) -> dict:
        modules = {k: m.state_dict() for k, m in self.agent.pretrained_modules().items()}
        if self.index is not None:
            modules = member_slice(modules, self.index)
        return snapshot_state(self.agent, self.config, t, modules)

    def save_resume(self, mid_episode: bool = False) -> None:
        config, episode, env = self.config, self.episode, self.env
        checkpoint = {
            "kind": RESUME_KIND, "format": RESUME_FORMAT, "agent": config.agent, "config": to_dict(config),
            "step": self.step, "generator": self.generator.get_state(),
            "episode": episode.episode, "agent_state": self.training_state(),
            **({"dataset": self.fingerprint} if self.offline else {"replay": self.replay.state_dict()}),
            "rng": rng_state(self.rng), "env_rng": env.unwrapped.get_rng_state()}
        if mid_episode:
            checkpoint["episode_state"] = {
                "env": env.unwrapped.get_episode_state(), "obs": torch.as_tensor(episode.obs),
                "skill": None if episode.skill is None else episode.skill.cpu(),
                "episode_return": episode.episode_return}
        save_checkpoint(self.run, checkpoint, f"resume_{self.step}")
        self.last_checkpoint = self.step

    def after_step(self, t: int) -> None:
        config = self.config
        self.step = t  # what a checkpoint written at this step records
        if t % config.log_every == 0 or t == config.frames:
            means = self.window.flush()
            if means:
                means["fps"] = (t - self.start_step) / max(time.time() - self.started, 1e-9)
                self.logger.log(t, means, prefix="train")
        if t in self.snapshots:
            self.window.flush()
            save_snapshot(self.run, self.snapshot(t), snapshot_name(t))

    def after_episode(self, t: int, ended: EpisodeState) -> None:
        self.logger.log(t, {"episode": ended.episode, "episode_task_reward": ended.episode_return}, prefix="episode")

    def finish(self, resume: bool) -> None:
        config = self.config
        elapsed = time.time() - self.started
        self.run.write_summary(PretrainSummary(
            agent=config.agent, domain=config.domain, frames=self.step, episodes=self.episode.episode,
            wall_clock_s=elapsed, frames_per_s=(self.step - self.start_step) / max(elapsed, 1e-9),
            resumed_from=self.start_step if resume else None, device=str(self.device)))
