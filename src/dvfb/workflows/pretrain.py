"""Reward-free online pre-training (docs/methods.md §7.1) with snapshots and exact resume.

The loop (a rollout of the one loop, :mod:`dvfb.training.rollout`, with the training steps of
:class:`~dvfb.workflows.group.TrainingSteps`, as fine-tuning's), per environment step ``t``:

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
module adds the method's skill rule, the logging, the snapshots and what a checkpoint holds. One
implementation serves a run and a group of runs (docs/members.md): a run is a group of one.

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
import dataclasses
import time
from pathlib import Path
from typing import Sequence

from dvfb import envs
from dvfb.agents import get_spec, make_agent
from dvfb.core.config import replace, to_dict
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.data import ReplayBuffer, physics_columns, read_dataset, read_info
from dvfb.data.datasets import check_same_data
from dvfb.nets.execution import resolve_device
from dvfb.nets.members import member_slice
from dvfb.runs.machine import cores
from dvfb.runs import RunDir, RunLock, save_snapshot
from dvfb.runs.layout import PretrainRun, snapshot_name
from dvfb.runs.migrations import migrate_training_state
from dvfb.runs.records import PretrainSummary
from dvfb.runs.run_config import PretrainConfig, run_config_from_dict
from dvfb.runs.snapshots import snapshot_state
from dvfb.runs.wandb_sink import require_wandb
from dvfb.training.observers import ProgressCount, ReplayWriter
from dvfb.training.progress import Progress, notify, progress_bars
from dvfb.training.rollout import Lane, rollout
from dvfb.training.seeding import seed_everything
from dvfb.workflows.group import Group, TrainingSteps, check_lockstep
from dvfb.workflows.pretrain_evaluation import PretrainEvaluation
from dvfb.workflows.processes import group_schedule, run_in_processes, shares
from dvfb.workflows.resources import (check_memory, check_replay, check_task_in_domain, learner_state_bytes,
                                      resume_threads, setup_torch)
from dvfb.workflows.session import RunSession

RESUME_KIND = "pretrain_resume"


def pretrain(config: PretrainConfig, run_dir: str | Path | Sequence[str | Path], *, seeds: Sequence[int] | None = None,
             resume: bool = False, overwrite: bool = False, progress: bool | None = None,
             command: list[str] | None = None):
    """Pre-train ``config.agent`` on ``config.domain``: a run in ``run_dir``, or with a list of run
    directories and ``seeds``, a group (docs/members.md) of one member per seed in lockstep in this
    process, member k the run ``config`` with ``seed = seeds[k]`` in ``run_dir[k]``. Returns the run
    (:class:`~dvfb.runs.layout.PretrainRun`), or the list of the members' runs.

    Every option is checked before anything is built. One process writes a run at a time
    (``RUN/.lock``). Each member has its own environment, replay, random streams, episode, logs,
    snapshots and resume checkpoints (each one a separate run's, so a member may also be resumed
    alone); a group's networks are stacked, so an update and an action are one batched pass for all.
    SIGTERM/SIGINT write a checkpoint (mid-episode if need be) and raise
    :class:`~dvfb.core.errors.RunInterrupted`; ``resume`` continues exactly from it (all members of a
    group must stand at the same step). A failed resume changes no file; resuming a finished run is
    a no-op. Disk errors end the run with one line and leave the previous checkpoint intact. In a
    group, a member whose loss or action goes non-finite stops with the usual one line naming its
    run; the others finish, and the call then raises :class:`~dvfb.core.errors.NonFiniteLossError`.
    With ``config.processes`` > 1 a group's members are split over that many child processes, each
    training its share as a group (docs/members.md, "A group over several processes").
    """
    many = not isinstance(run_dir, (str, Path))
    paths = [Path(p) for p in run_dir] if many else [Path(run_dir)]
    seeds = list(seeds) if seeds is not None else [config.seed]
    if len(seeds) < 1 or len(seeds) != len(paths):
        raise ConfigError("a group needs one run directory per seed")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds lists a seed twice ({', '.join(map(str, seeds))}); members need distinct seeds")
    if len({p.resolve() for p in paths}) != len(paths):
        raise ConfigError("the members of a group need distinct run directories")
    if not resume:  # every member's directory is checked before any is created
        for path in paths:
            RunDir.check_new(path, overwrite)
    base, trained_task, dataset_info = _checked(replace(config, seed=seeds[0]) if many else config, paths, resume,
                                                overwrite)
    stored = PretrainRun.open(paths[0]) if resume else None
    if stored is not None:
        # A resume computes with the threads the run computed with, whatever the shell's
        # OMP_NUM_THREADS, and keeps its recorded setting unless --torch-threads asks otherwise.
        resume_threads(stored, base.torch_threads)
        asked_threads = base.torch_threads
        if not base.torch_threads:
            base = replace(base, torch_threads=stored.config.torch_threads)
        if not base.processes:  # not asked: the schedule the group ran with
            base = replace(base, processes=stored.config.processes)
        device = resolve_device(base.device)
    else:
        device = setup_torch(base)
    processes, child_threads = group_schedule(len(paths), base.processes, base.torch_threads, device.type == "cuda")
    if stored is not None and processes > 1:
        child_threads = _resumed_share_threads(stored, processes, child_threads, asked_threads)
    # config.json records the schedule the group runs with. The schedule is computed here, so the
    # config is not validated again: a config handed to pretrain() runs as it was given.
    base = dataclasses.replace(base, processes=processes)
    configs = [replace(base, seed=seed) for seed in seeds] if many else [base]
    what = f"pretrain {base.agent} {base.domain}" + (f" ({len(paths)} members)" if many else "")
    split = shares(len(paths), processes) if many else [range(1)]
    if len(split) > 1:  # the parent checks that the whole group fits, its children build the members
        _member_parts_checked(configs[:1], trained_task, device, dataset_info, what, len(paths), len(split))
        parts = dataset = None
    else:
        parts = _member_parts_checked(configs, trained_task, device, dataset_info, what, len(paths) if many else 1)
        dataset = _read_dataset(base, dataset_info, parts[0][2], device, progress)
    locks = [RunLock(p) for p in paths]
    with contextlib.ExitStack() as stack:
        try:
            for lock in locks:  # a member in use: the directories locked so far are removed again
                stack.enter_context(lock)
            if len(split) > 1:
                _run_split(configs, paths, split, trained_task, dataset_info, resume, overwrite, progress, command,
                           child_threads)
                runs = [PretrainRun(path, c) for path, c in zip(paths, configs)]
            else:
                runs = _run(configs, paths, parts, resume, overwrite, command, dataset, dataset_info, progress, what,
                            many)
        except BaseException:
            for lock in locks:
                lock.remove_if_created()
            raise
    return runs if many else runs[0]


def _member_parts_checked(configs, trained_task, device, dataset_info, what, members, processes=1, check=True):
    """Each config's random stream and :func:`_member_parts`, in order; after the first, unless
    ``check`` is off, the check that ``members`` runs like it fit in memory (``processes`` processes
    each hold a copy of a dataset)."""
    parts = []
    for k, member_config in enumerate(configs):
        rng = seed_everything(member_config.seed)
        parts.append((rng, *_member_parts(member_config, trained_task, device)))
        if k == 0 and check:  # refuse a group that cannot fit before building the other members
            _rng, env, agent, episode_length, columns = parts[0]
            check_memory(_memory_parts(configs[0], env, agent, episode_length, columns, dataset_info, members,
                                       processes), what, device)
    return parts


def _resumed_share_threads(stored: PretrainRun, processes: int, threads: int, asked: int) -> int:
    """The threads of each share of a resumed split group: those it computed with (its members'
    meta.json), unless ``--torch-threads`` asked otherwise; on a machine with fewer CPUs than the
    schedule takes, one line says what changes."""
    if not asked:
        threads = stored.computed_threads() or threads
    limit = cores()
    if processes * threads <= limit:
        return threads
    if threads > 1:
        fitted = max(1, limit // processes)
        notify(f"[threads] the group ran as {processes} processes of {threads} torch threads, but this process may "
               f"use {limit} CPU(s); resuming with {fitted} thread(s) each: its numbers may differ from an "
               "uninterrupted run's")
        return fitted
    notify(f"[threads] the group ran as {processes} single-thread processes, but this process may use {limit} CPU(s); "
           "resuming with the same schedule: the same numbers, more slowly")
    return threads


def _run_split(configs, paths, split, trained_task, dataset_info, resume, overwrite, progress, command, threads):
    """The group's members in ``len(split)`` child processes of ``threads`` torch threads, one share
    each (docs/members.md, "A group over several processes"); this process holds their locks."""
    base = configs[0]
    calls, names = [], []
    for k, share in enumerate(split):
        seeds = ",".join(str(configs[i].seed) for i in share)
        what = f"pretrain {base.agent} {base.domain} (seeds {seeds} of {len(paths)} members)"
        # configs travel as dicts: a method's config class is made at run time and does not pickle
        calls.append(([to_dict(configs[i]) for i in share], [paths[i] for i in share], trained_task, dataset_info, resume,
                      overwrite, progress if k == 0 else False, command, what))
        names.append(f"seeds {seeds}")
    run_in_processes(_run_share, calls, threads, names,
                     agree=lambda finished: _check_finished([f for share in finished for f in share]))


def _run_share(config_dicts, paths, trained_task, dataset_info, resume, overwrite, progress, command, what,
               ready) -> None:
    """In a child process: one share of a split group, as a group of its own (its parent holds the
    locks and has checked everything; ``ready`` waits for the other shares, see :func:`_run`)."""
    configs = [run_config_from_dict(d, what) for d in config_dicts]
    device = resolve_device(configs[0].device)  # the threads are this process's part, set by its parent
    parts = _member_parts_checked(configs, trained_task, device, dataset_info, what, len(configs), check=False)
    dataset = _read_dataset(configs[0], dataset_info, parts[0][2], device, progress)
    _run(configs, paths, parts, resume, overwrite, command, dataset, dataset_info, progress, what, True, ready)


def _check_finished(finished: list[bool]) -> None:
    if any(finished) and not all(finished):
        raise ConfigError("some members of the group have finished and others not: resume the others alone")


def _run(configs, paths, parts, resume, overwrite, command, dataset, dataset_info, progress, what, many,
         ready=None):
    """The group's training loop; ``ready``: a share of a split group says here, with its members'
    checkpoints read and nothing written yet, which of them have finished, and waits for the others."""
    sessions = [PretrainSession(c, p, resume, overwrite, command, rng, env, agent, length, columns, dataset,
                                dataset_info)
                for c, p, (rng, env, agent, length, columns) in zip(configs, paths, parts)]
    if ready is not None:
        ready([s.finished for s in sessions])
    if any(s.finished for s in sessions):
        _check_finished([s.finished for s in sessions])
        return [s.run for s in sessions]
    for session in sessions:
        session.begin()
    check_lockstep(sessions)
    base = configs[0]
    group = Group(sessions, [s.agent for s in sessions], what, "pre-training", lambda t: t < base.seed_frames)

    def after_step(t: int) -> None:
        for session in list(group.live):
            session.after_step(t)

    bar = Progress(base.frames, group.step, what, progress)
    checkpoints = group.checkpoints(base.checkpoint_every, base.frames)
    steps = TrainingSteps(group, base.seed_frames, base.update_every, checkpoints, after_step,
                          lambda session, t: session.after_episode(t))
    observers = [ProgressCount(bar), steps]
    if group.lanes:
        observers.insert(0, ReplayWriter(group.lanes, [s.replay for s in sessions],
                                         physics=[s.lane.env.unwrapped.physics_state if s.columns else None
                                                  for s in sessions]))
        if sessions[0].evaluation is not None and sessions[0].evaluation.window is not None:
            # The evaluations' own window of the newest transitions with their physics states.
            observers.insert(1, ReplayWriter(group.lanes, [s.evaluation.window for s in sessions], store_skill=False,
                                             physics=[s.evaluation.physics for s in sessions]))
    try:
        with checkpoints:
            step = rollout(group.lanes, group.policy if group.lanes else None, observers, start=group.step,
                           stop=base.frames)
            group.window.check()
            if parts[0][4]:  # a dataset's run: the final checkpoint holds every finished episode
                boundary = all(lane.state.episode_start for lane in group.lanes)
                checkpoints.ensure(step, mid_episode=not boundary)
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
    require_wandb(config.log)
    for run_path in run_paths:
        if resume:
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
        for run_path in run_paths if resume else ():
            # Cheap, before any work: the data each run recorded when it started (runs made before
            # dvfb recorded it are checked against their checkpoint's file names in begin()).
            recorded = PretrainRun(run_path, config).trained_on() if Path(run_path).is_dir() else None
            if recorded is not None:
                check_same_data(recorded, dataset_info, config.dataset, f"cannot resume {run_path}: it")
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


def _memory_parts(config, env, agent, episode_length, columns, dataset_info, members: int,
                  processes: int = 1) -> dict[str, int]:
    """What ``members`` runs like this one hold: their replays (offline, one dataset in each of the
    ``processes`` processes) and their networks."""
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    capacity = config.replay_capacity if dataset_info is None else dataset_info.transitions
    replay = ReplayBuffer.estimate_nbytes(capacity, obs_dim, action_dim, agent.skill_dim, episode_length, columns)
    if members == 1:
        return {"replay": replay, "networks": learner_state_bytes(agent)}
    copies = processes if dataset_info is not None else members
    label = (f"{copies} dataset{'s' if copies > 1 else ''}" if dataset_info is not None else f"{members} members")
    return {f"replay ({label})": replay * copies,
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


# Transitions a snapshot's data statistics are computed from (Cov(B) of FB, docs/methods.md,
# "Online task inference": at least 50k states).
STATISTICS_TRANSITIONS = 100_000


class PretrainSession(RunSession):
    """One run directory's share of a pre-training (:class:`RunSession`): its learner (unstacked; a
    group stacks its members' afterwards), replay (or the dataset, offline), environment, episode,
    snapshots and logs; the method's skill rule."""

    kind = RESUME_KIND
    phase = "pre-training"
    tag = "pretrain"
    budget_flag = "--frames"
    # log: where the metrics are sent besides the run directory (docs/methods.md, "Logging to Weights & Biases").
    # eval_*: the evaluations while pre-training (docs/health.md), which training never reads; not
    # eval_samples, the size of the window a checkpoint holds.
    resumable = ("frames", "device", "torch_threads", "processes", "log_every", "perf.compile", "perf.cuda_graphs", "log",
                 "eval_every", "eval_tasks", "eval_episodes", "eval_skill_steps")

    def __init__(self, config, run_path, resume, overwrite, command, rng, env, agent, episode_length, columns,
                 dataset=None, dataset_info=None):
        self.config, self.env, self.rng, self.columns, self.agent = config, env, rng, columns, agent
        self.seed = config.seed
        self.episode_length, self.dataset, self.dataset_info = episode_length, dataset, dataset_info
        self.resume = resume
        self.open(PretrainRun, run_path, resume, overwrite, command)

    @property
    def total(self) -> int:
        return self.config.frames

    @property
    def device(self):
        return self.agent.device

    def fits(self, state: dict) -> bool:
        return state.get("agent") == self.config.agent

    def lost_summary(self, state: dict) -> PretrainSummary | None:
        if self.total not in self.run.snapshot_frames():
            return None  # the final snapshot, what every later command reads, is gone too
        summary = self.run.recovered_summary()
        return None if summary is None else replace(summary, episodes=state.get("episode"), device=str(self.device))

    def describe_kind(self) -> str:
        return f"{self.config.agent} pre-training"

    def begin(self) -> None:
        """The run's data, random stream, environment lane and, resuming, its restored state."""
        config, agent, state = self.config, self.agent, self.state
        self.offline = offline = self.dataset is not None
        # What an offline checkpoint records instead of the replay: which data it trained on.
        info = self.dataset_info
        self.fingerprint = info.fingerprint(config.dataset) if offline else None
        if offline and state is not None:
            # Resuming on other data than the run trained on would continue another experiment.
            check_same_data(state.get("dataset", {}), info, config.dataset, f"cannot resume {self.run.path}: it")
        self.replay = self.dataset if offline else ReplayBuffer(
            config.replay_capacity, agent.obs_dim, agent.action_dim, agent.skill_dim,
            max_episode_length=self.episode_length, device=agent.device, sampler=config.replay.sampler(),
            columns=self.columns)
        self.needs = agent.replay_needs()
        self.make_generator()
        agent.use_generator(self.generator)
        self.lane = None if offline else Lane(self.env, self.rng, reset_seed=None if state is not None else config.seed,
                                              reward_key="task_reward")
        episode = self.lane.state if self.lane is not None else None
        self.evaluation = None
        if config.eval_every and offline:
            notify(f"[eval] {self.run.path}: an offline run is not evaluated while it trains (--eval-every is for online "
                   "runs); dvfb zeroshot evaluates its snapshots")
        elif config.eval_every:
            self.evaluation = PretrainEvaluation(config, agent.obs_dim, agent.action_dim, self.env, agent.device)
        if state is not None:
            try:
                agent.load_training_state(migrate_training_state(config.agent, state["agent_state"]))
                if not offline:
                    self.replay.load_state_dict(state["replay"])
                self.restore(state, episode)
                if self.evaluation is not None:
                    self.evaluation.load_state_dict(state.get("evaluation"))
                    if state.get("evaluation") is None and episode is not None and not episode.episode_start:
                        # Evaluations begin with this resume, mid-episode: the window starts here.
                        self.evaluation.start_window(episode.obs)
            except (KeyError, TypeError, ValueError, RuntimeError) as exc:
                raise CheckpointError(f"cannot resume {self.run.path}: the checkpoint does not fit this run ({exc})") \
                    from exc
            # Only now, with the checkpoint loaded, may the run's config change (a larger --frames).
            self.run.save_config(config)
            self.run.record_resume(self.command, self.step, processes=config.processes)
            notify(f"[pretrain] resuming {self.run.path} from step {self.step} (of {config.frames})")
        if state is None:
            # The schedule a group's member was made with (its threads: meta.json's machine record).
            self.run.update_meta(processes=config.processes)
        if offline:
            self.run.write_trained_on(self.fingerprint)  # what an offline zero-shot checks its data against
        self.start_logging(self.resume, agent.nonfinite_hint)
        self.snapshots = set(config.snapshot_frames) | {config.frames}

    def skill_rule(self, t: int, episode_start: bool, current):
        # The method's declared rule (docs/methods.md, "Skills"); its prior draws the new skill,
        # from this run's own stream (a group's learner draws for each member from the member's).
        learner = self.learner
        if not learner.skill.due(t, episode_start):
            return current
        return learner.explore_skill(self.lane.state.obs, self.generator, self.index)

    def extra_record(self) -> dict:
        config = self.config
        extra = {"agent": config.agent, "config": to_dict(config), "agent_state": self.learner_state()}
        if self.offline:
            extra["dataset"] = self.fingerprint
        else:
            extra["replay"] = self.replay.state_dict()
        if self.evaluation is not None:
            extra["evaluation"] = self.evaluation.state_dict()
        return extra

    def snapshot(self, t: int) -> dict:
        modules = {k: m.state_dict() for k, m in self.learner.pretrained_modules().items()}
        if self.index is not None:
            modules = member_slice(modules, self.index)
        model, statistics = self.learner.model, {}
        if model.has_statistics and len(self.replay):
            # The newest pre-training transitions (no random draw: the run's streams are untouched).
            data = self.replay.transitions(limit=STATISTICS_TRANSITIONS)
            statistics = model.data_statistics(data.obs, data.next_obs, self.index)
        return snapshot_state(self.learner, self.config, t, modules, statistics)

    def after_step(self, t: int) -> None:
        config = self.config
        self.step = t  # what a checkpoint written at this step records
        if t % config.log_every == 0 or t == config.frames:
            now = time.time()
            fps = (t - self.start_step) / max(now - self.started, 1e-9)
            # The rate since the previous record as well: what an ETA needs (README.md, "Threads and
            # progress"); fps, the average since the process started, hides a slowdown for hours.
            since, step = self.last_log
            self.last_log = (now, t)
            self.log_window(t, {"fps": fps, "fps_recent": (t - step) / max(now - since, 1e-9)})
        if t in self.snapshots:
            self.window.check()  # no snapshot of a non-finite learner
            save_snapshot(self.run, self.snapshot(t), snapshot_name(t))
        if self.evaluation is not None and self.evaluation.due(t):
            self.evaluate(t)

    def evaluate(self, t: int) -> None:
        """The zero-shot evaluation of the current networks at step ``t`` (docs/health.md): one record
        per task in metrics/eval.jsonl, TensorBoard and W&B, and one line."""
        modules = {k: m.state_dict() for k, m in self.learner.pretrained_modules().items()}
        if self.index is not None:
            modules = member_slice(modules, self.index)
        records = self.evaluation.run(t, modules, self.learner)
        for record in records:
            self.logger.log_row(t, record, {f"{record['task']}/return": record["return"]}, prefix="eval")
        if records:
            notify(f"[eval] {self.run.path} at {t} frames: "
                   + ", ".join(f"{r['task']} {r['return']:.1f}" for r in records)
                   + f" ({records[0]['episodes']} episodes each, {records[0]['seconds']:.1f} s)")

    def after_episode(self, t: int) -> None:
        ended = self.lane.state
        self.logger.log(t, {"episode": ended.episode, "episode_task_reward": ended.episode_return}, prefix="episode")

    def finish(self, resume: bool) -> None:
        config = self.config
        elapsed = time.time() - self.started
        episodes = self.lane.state.episode if self.lane is not None else 0
        self.run.write_summary(PretrainSummary(
            agent=config.agent, domain=config.domain, frames=self.step, episodes=episodes,
            wall_clock_s=elapsed, frames_per_s=(self.step - self.start_step) / max(elapsed, 1e-9),
            resumed_from=self.start_step if resume else None, device=str(self.device)))
