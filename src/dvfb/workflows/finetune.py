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

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.protocols import finetuner_class, zero_shot_protocol
from dvfb.config import merge, to_dict
from dvfb.errors import CheckpointError, ConfigError
from dvfb.data import ReplayBuffer
from dvfb.runs import (
    MetricsLogger,
    RunDir,
    RunLock,
    check_writable,
    load_checkpoint,
    remove_orphaned_checkpoints,
    save_checkpoint,
)
from dvfb.training import loop
from dvfb.training.loop import EpisodeState, OnlineCollector
from dvfb.training.checkpointing import ResumeCheckpoints
from dvfb.training.metrics import MetricWindow
from dvfb.training.progress import Progress, notify
from dvfb.runs.migrations import RESUME_FORMAT, check_resume_format
from dvfb.runs.records import Curve, FinetuneSummary, curve_point
from dvfb.training.seeding import restore_rng_state, rng_state, run_generator, seed_everything
from dvfb.workflows.resources import check_replay, check_task_in_domain
from dvfb.runs.layout import FinetuneRun
from dvfb.runs.run_config import FinetuneRunConfig, finetune_run_config_class
from dvfb.runs.snapshots import load_pretrained_agent
from dvfb.workflows.resources import open_run
from dvfb.nets.members import member_slice, stack_agents
from dvfb.workflows.evaluate import Evaluation, evaluate_group, evaluate_policy
from dvfb.workflows.groups import MemberGroup, check_one_method
from dvfb.workflows.zeroshot import task_skill

RESUME_KIND = "finetune_resume"


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
    member = _prepared(run_path, task, snapshot, inference, finetune, seed, name, resume, device)
    lock = RunLock(member.path)
    with lock:
        try:
            session = FinetuneSession(member, resume, overwrite)
            if not session.finished:
                _run(session, progress)
            return session.run
        except BaseException:
            lock.remove_if_created()
            raise


def finetune_group(run_paths: list[str | Path], task: str, *, snapshot: int | None = None,
                   inference: dict | None = None, finetune: dict | None = None, seed: int | None = None,
                   name: str | None = None, resume: bool = False, overwrite: bool = False,
                   progress: bool | None = None, device: str | None = None) -> list[RunDir]:
    """:func:`finetune` of every member of a group (docs/members.md) in lockstep, in this process.

    Member k is the fine-tuning run ``RUN_k/finetune/<name>`` that :func:`finetune` of ``run_paths[k]``
    writes: its own skill (its zero-shot protocol and random streams), environments, replay, logs,
    curve and resume checkpoints. The fine-tuners are stacked, so each update and each action is one
    batched pass for all members. The runs must be one method with one configuration (seeds aside)
    and have the snapshot. A member whose loss or action goes non-finite stops alone (its one line);
    the others finish, and the call then raises :class:`~dvfb.errors.NonFiniteLossError`.
    """
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite contradict each other: pass one of them")
    if not run_paths:
        raise ConfigError("a group fine-tuning needs at least one run")
    if len({Path(p).resolve() for p in run_paths}) != len(run_paths):
        raise ConfigError("a run is listed twice: the members of a group are distinct runs")
    members = [_prepared(p, task, snapshot, inference, finetune, seed, name, resume, device) for p in run_paths]
    check_one_method([(m.run, m.config) for m in members])
    first = members[0]
    finetuner_class(get_spec(first.config.agent).finetuner).check_group(first.run_config.finetune)
    if len({m.snapshot for m in members}) != 1:
        raise ConfigError("the members' snapshots are of different frames; pass --snapshot")
    for m in members[1:]:
        for section in ("inference", "finetune"):
            if to_dict(getattr(m.run_config, section)) != to_dict(getattr(first.run_config, section)):
                raise ConfigError(f"{m.run.path} and {first.run.path} have different {section} sections: a group "
                                  "fine-tunes its members with one protocol")
    locks = [RunLock(m.path) for m in members]
    with contextlib.ExitStack() as stack:
        try:
            for lock in locks:  # a member in use: the directories locked so far are removed again
                stack.enter_context(lock)
            sessions = [FinetuneSession(m, resume, overwrite) for m in members]
            if all(s.finished for s in sessions):
                return [s.run for s in sessions]
            if any(s.finished for s in sessions):
                raise ConfigError("some members of the group have finished and others not: resume the others alone")
            if len({s.step for s in sessions}) != 1:
                raise CheckpointError("the members' latest checkpoints are of different steps ("
                                      + ", ".join(f"{s.run.path}: {s.step}" for s in sessions)
                                      + "): a group resumes in lockstep; resume them alone")
            _run_group(sessions, task, progress)
            return [s.run for s in sessions]
        except BaseException:
            for lock in locks:
                lock.remove_if_created()
            raise


@dataclass
class _Member:
    """A fine-tuning run checked and ready to start: its pre-training run and agent, its config."""

    run: RunDir
    config: object
    agent: object
    snapshot: int
    run_config: FinetuneRunConfig
    path: Path
    task: str


def _prepared(run_path, task, snapshot, inference, finetune, seed, name, resume, device) -> _Member:
    """Everything :func:`finetune` checks before it takes the run's lock."""
    run = open_run(run_path)
    config = run.config
    check_task_in_domain(task, config.domain)
    agent, snapshot = load_pretrained_agent(run, snapshot, device)
    run_config = finetune_run_config_class(config.agent)(
        pretrain_run=str(run.path), agent=config.agent, domain=config.domain, task=task, snapshot=snapshot,
        seed=config.seed if seed is None else seed, device=str(agent.device),
        inference=merge(config.inference, inference or {}, "inference."),
        finetune=merge(config.finetune, finetune or {}, "finetune."))
    finetuner_class(get_spec(config.agent).finetuner).check(agent, run_config.finetune)
    check_replay(run_config.finetune.replay_capacity, "--finetune.replay-capacity", agent.replay_needs(),
                 envs.TASKS[task].episode_length, config.domain)
    path = run.finetune_path(name or task)
    if resume:
        RunDir.open(path)  # names what is missing before anything else happens
    else:
        check_writable(path.parent)
    return _Member(run, config, agent, snapshot, run_config, path, task)


class FinetuneSession:
    """One fine-tuning run directory's share of a fine-tuning: the run, its environments, replay,
    random streams, skill, fine-tuner, logs, curve and resume checkpoints. A run has one; a group
    (docs/members.md) one per member.

    Built inside the run's lock: it creates (or, resuming, opens and restores) the run, finds the
    task's skill and builds the fine-tuner on the member's ordinary agent (a group stacks them
    afterwards and calls :meth:`bind_member`). A fresh run's curve is empty until the caller
    records the zero-shot evaluation (:meth:`record`). ``finished``: a resumed run that had finished.
    """

    def __init__(self, member: _Member, resume: bool, overwrite: bool):
        run, config, agent, run_config, path, task = (member.run, member.config, member.agent, member.run_config,
                                                      member.path, member.task)
        self.run_config, self.cfg, self.seed = run_config, run_config.finetune, run_config.seed
        self.task, self.finished = task, False
        cfg = self.cfg
        state = None
        if resume:
            ft_run = FinetuneRun.open(path)
            stored = to_dict(ft_run.config)
            requested = to_dict(run_config)
            for key in ("device",):
                stored.pop(key), requested.pop(key)
            stored["finetune"].pop("frames"), requested["finetune"].pop("frames")
            if stored != requested:
                diffs = sorted(k for k in stored if stored[k] != requested[k])
                raise ConfigError(f"--resume with a different configuration: {', '.join(diffs)} differ from "
                                  f"{path}/config.json")
            done = ft_run.finished_frames()
            if done is not None:
                if done >= cfg.frames:
                    notify(f"[finetune] {path} already finished at {done} frames; nothing to resume")
                    self.run, self.finished = ft_run, True
                    return
            remove_orphaned_checkpoints(ft_run)
            try:
                state = load_checkpoint(ft_run, None, map_location=agent.device)
            except CheckpointError as exc:
                raise CheckpointError(f"cannot resume {path}: {exc}") from exc
            if state.get("kind") != RESUME_KIND:
                raise CheckpointError(f"{path}: the latest checkpoint is not a fine-tuning checkpoint")
            check_resume_format(state, path)
        else:
            ft_run = FinetuneRun.create(path, run_config, overwrite=overwrite)
        self.run = ft_run

        self.rng = rng = seed_everything(run_config.seed)
        self.env = env = envs.make(task, seed=run_config.seed)
        self.eval_env = eval_env = envs.make(task, seed=run_config.seed)  # same seed as the training env, as in [C]
        max_len = envs.TASKS[task].episode_length
        # Batches are drawn the way the pre-training drew them (uniform, or the authors' loader shards).
        self.replay = replay = ReplayBuffer(cfg.replay_capacity, agent.obs_dim, agent.action_dim, agent.skill_dim,
                                            max_episode_length=max_len, device=agent.device,
                                            sampler=config.replay.sampler())
        finetuner_cls = finetuner_class(get_spec(config.agent).finetuner)
        # The run's own random stream: the protocol's and the fine-tuner's draws, noise and batches.
        self.generator = generator = run_generator(run_config.seed, agent.device)
        agent.use_generator(generator)
        self.started = time.time()
        self.episode = episode = EpisodeState()

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
                self.step, self.curve, self.inference_info = state["step"], state["curve"], state["inference_info"]
                if state.get("episode_state") is not None:  # written mid-episode on a signal
                    env.unwrapped.set_episode_state(state["episode_state"]["env"])
                    episode.obs = np.asarray(state["episode_state"]["obs"], dtype=np.float32)
                    skill = state["episode_state"].get("skill", z)
                    episode.set_skill(None if skill is None else skill.to(agent.device))
                    episode.episode_start = False
            except (KeyError, TypeError, ValueError, RuntimeError) as exc:
                raise CheckpointError(f"cannot resume {path}: the checkpoint does not fit this run ({exc})") from exc
            ft_run.save_config(run_config)  # only now may the config change (a larger --finetune.frames)
            notify(f"[finetune] resuming {path} from step {self.step} (of {cfg.frames})")
            self.logger = MetricsLogger(ft_run, purge_step=self.step + 1)
            _write_curve(ft_run, run_config, self.curve, self.inference_info, z)
        else:
            keep = finetuner_cls.keeps_inference_data(cfg)
            protocol = zero_shot_protocol(get_spec(config.agent).zero_shot)(run_config.inference)
            z, self.inference_info = task_skill(agent, run, config, task, protocol, rng, run_config.seed,
                                                keep_data=keep, env=env)
            if keep:
                _copy_transitions(self.inference_info.pop("buffer"), replay, z)
            # The inference data are discarded (§8.2 step 6) unless kept above.
            finetuner = finetuner_cls(agent, z, cfg)
            self.logger = MetricsLogger(ft_run)
            self.curve, self.step = [], 0
        self.z = z
        self.last_checkpoint = self.step if state is not None else None
        self.window = MetricWindow(agent.nonfinite_hint)
        self.needs = finetuner.replay_needs()
        finetuner.bind_replay(replay)
        self.bind_member(finetuner, None)
        self.collector = OnlineCollector(
            env, replay, agent, rng, self.rollout_skill,
            lambda t: finetuner_cls.uniform_seed_actions and t < cfg.seed_frames, state=episode)

    def bind_member(self, finetuner, index: int | None) -> None:
        """Whose state this run saves: ``finetuner`` itself (``index`` None), or member ``index`` of
        a stacked group's (the index changes when a member before it stops)."""
        self.finetuner, self.index = finetuner, index
        self._skill_row = None

    def rollout_skill(self, t: int, episode_start: bool, current):
        skill = self.finetuner.rollout_skill(t, episode_start, current, self.generator)
        if self.index is None or skill is None or skill.dim() == 1:
            return skill
        # A group's fine-tuner holds its members' fixed skills stacked: this member's is its row
        # (the same tensor every step, so the replay's host copy is made once).
        if self._skill_row is None or self._skill_row[0] is not skill:
            self._skill_row = (skill, skill[self.index])
        return self._skill_row[1]

    def sample(self):
        return self.needs.sample(self.replay, self.generator)

    def training_state(self) -> dict:
        state = self.finetuner.training_state()
        return state if self.index is None else member_slice(state, self.index)

    def save_resume(self, mid_episode: bool = False) -> None:
        env, episode, z = self.env, self.episode, self.z
        checkpoint = {
            "kind": RESUME_KIND, "step": self.step, "z": None if z is None else z.cpu(), "curve": self.curve,
            "inference_info": self.inference_info, "finetuner": self.training_state(),
            "replay": self.replay.state_dict(), "rng": rng_state(self.rng), "generator": self.generator.get_state(),
            "format": RESUME_FORMAT, "env_rng": env.unwrapped.get_rng_state(),
            "eval_env_rng": self.eval_env.unwrapped.get_rng_state()}
        if mid_episode:
            checkpoint["episode_state"] = {"env": env.unwrapped.get_episode_state(), "obs": torch.as_tensor(episode.obs),
                                           "skill": None if episode.skill is None else episode.skill.cpu()}
        save_checkpoint(self.run, checkpoint, f"resume_{self.step}")
        self.last_checkpoint = self.step

    def after_step(self, t: int) -> None:
        self.step = t  # what a checkpoint written at this step records
        if t % 1000 == 0 or t == self.cfg.frames:
            means = self.window.flush()
            if means:
                self.logger.log(t, means, prefix="train")

    def evaluation_due(self, t: int) -> bool:
        return t % self.cfg.eval_every == 0 or t == self.cfg.frames

    def record(self, t: int, evaluation: Evaluation) -> None:
        """The evaluation at step ``t``: a curve point, its log record and the curve file."""
        self.curve.append(_curve_point(t, evaluation))
        self.logger.log(t, _eval_metrics(self.curve[-1]), prefix="eval")
        _write_curve(self.run, self.run_config, self.curve, self.inference_info, self.z)

    def finish(self) -> None:
        curve = self.curve
        self.run.write_summary(FinetuneSummary(
            task=self.task, frames=self.step, wall_clock_s=time.time() - self.started,
            zero_shot_return=curve[0]["mean_return"], final_return=curve[-1]["mean_return"],
            zero_shot_success_rate=curve[0].get("success_rate"), final_success_rate=curve[-1].get("success_rate")))


def _run(session: FinetuneSession, progress) -> None:
    cfg, agent = session.cfg, session.finetuner.agent

    def evaluate(t: int) -> None:
        session.record(t, evaluate_policy(agent, session.eval_env, session.finetuner.skill, cfg.eval_episodes))

    if not session.curve:
        evaluate(0)  # the zero-shot point of the curve

    def after_step(t: int) -> None:
        session.after_step(t)
        if session.evaluation_due(t):
            evaluate(t)

    bar = Progress(cfg.frames, session.step, f"finetune {session.task}", progress)
    checkpoints = ResumeCheckpoints(session.save_resume, session.window, cfg.checkpoint_every, cfg.frames,
                                    "fine-tuning", session.run.path, last=session.last_checkpoint)
    try:
        with checkpoints:
            loop.run(session.step, cfg.frames, session.collector, lambda: session.finetuner.update(session.sample()),
                     cfg.seed_frames, cfg.update_every, session.window, checkpoints, bar, after_step)
    finally:
        bar.close()
        session.logger.close()
    session.finish()


def _run_group(sessions: list[FinetuneSession], task: str, progress) -> None:
    cfg = sessions[0].cfg
    what = f"finetune {task} ({len(sessions)} members)"
    learner = stack_agents([s.finetuner for s in sessions])
    group = MemberGroup(sessions, learner, what, "fine-tuning",
                        lambda obs, skill: learner.agent.act_members(obs, skill, explore=True))

    def evaluate(t: int) -> None:
        live = list(group.live)
        for session, evaluation in zip(live, evaluate_group(learner.agent, [s.eval_env for s in live], learner.skill,
                                                            cfg.eval_episodes)):
            session.record(t, evaluation)

    if not sessions[0].curve:
        evaluate(0)  # the zero-shot point of every member's curve

    def after_step(t: int) -> None:
        for session in list(group.live):
            session.after_step(t)
        if sessions[0].evaluation_due(t):
            evaluate(t)

    bar = Progress(cfg.frames, sessions[0].step, what, progress)
    checkpoints = ResumeCheckpoints(group.save, group.window, cfg.checkpoint_every, cfg.frames, "fine-tuning",
                                    sessions[0].run.path, last=sessions[0].last_checkpoint)
    try:
        with checkpoints:
            loop.run(sessions[0].step, cfg.frames, group.source, group.update, cfg.seed_frames, cfg.update_every,
                     group.window, checkpoints, bar, after_step)
            group.window.flush()
    finally:
        bar.close()
        group.close_logs()
    for session in group.live:
        session.finish()
    group.raise_if_stopped()


def _curve_point(frames: int, evaluation: Evaluation) -> dict:
    return curve_point(frames, evaluation.summary())


def _eval_metrics(point: dict) -> dict:
    """What an evaluation logs: the mean return, and the success rate where the task has one."""
    return {"eval_return": point["mean_return"],
            **({"eval_success_rate": point["success_rate"]} if "success_rate" in point else {})}


def _write_curve(run: FinetuneRun, config: FinetuneRunConfig, curve: list[dict], inference_info: dict,
                 z: torch.Tensor | None) -> None:
    run.write_curve(Curve(task=config.task, domain=config.domain, agent=config.agent, seed=config.seed,
                          snapshot=config.snapshot, z=None if z is None else z.cpu().tolist(),
                          inference_info=inference_info, curve=curve))


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
