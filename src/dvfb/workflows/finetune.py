"""Fine-tuning of a pre-trained run on a task (docs/methods.md §9; docs/methods.md, "Protocols").

Protocol: load the snapshot; obtain the task's skill by the method's registered zero-shot protocol
(FB family: collect the inference steps and infer z_r, §8.1-8.2; skill discovery: select the best
prior skill; methods without skills: none); evaluate zero-shot (the curve's point at 0 frames);
build the method's registered fine-tuner (dual-value for the FB family, URLB's for the DDPG
agents); then ``finetune.frames`` steps of rollouts with ``pi(s, skill)`` (the skill of every step
from the fine-tuner; uniform actions during ``seed_frames`` where it asks for them), one
fine-tuner update every ``update_every`` steps after ``seed_frames`` (or the later first update a
fine-tuner asks for), and an evaluation every ``eval_every`` steps.

``protocol`` chooses another fine-tuner the method may use (docs/methods.md, "Protocols"): test-time
search over z (``latent_search``) or task inference from interaction alone (``online_inference``,
which starts from no labelled data: no zero-shot protocol runs first).

Each fine-tuning run has its own directory ``RUN/finetune/<name>/`` (default name: the task, and
``<task>.<protocol>`` for a chosen protocol) with
its config, metrics, resume checkpoints and ``curve.json`` (frames, mean and std return). One
implementation serves a run and a group of runs (docs/members.md): a run is a group of one.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.core.config import merge, to_dict
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.data import ReplayBuffer
from dvfb.nets.learner import Learner
from dvfb.protocols import Finetuner, check_finetune_options, finetuner_class, resolve_finetuner, zero_shot_protocol
from dvfb.runs import RunDir, RunLock, check_writable
from dvfb.runs.layout import FinetuneRun, PretrainRun
from dvfb.runs.records import Curve, FinetuneSummary, curve_point
from dvfb.runs.run_config import FinetuneRunConfig
from dvfb.runs.snapshots import load_model
from dvfb.runs.wandb_sink import require_wandb
from dvfb.training.evaluation import Evaluation, evaluate
from dvfb.training.observers import ProgressCount, ReplayWriter
from dvfb.training.progress import Progress, notify
from dvfb.training.rollout import Lane, rollout
from dvfb.training.seeding import seed_everything
from dvfb.workflows.group import Group, TrainingSteps, check_lockstep, check_one_method
from dvfb.workflows.resources import check_replay, check_task_in_domain, open_run, resume_threads
from dvfb.workflows.session import RunSession

RESUME_KIND = "finetune_resume"


def finetune(run_dir: str | Path | Sequence[str | Path], task: str, *, snapshot: int | None = None,
             inference: dict | None = None, finetune: dict | None = None, seed: int | None = None,
             name: str | None = None, resume: bool = False, overwrite: bool = False, progress: bool | None = None,
             device: str | None = None, log: dict | None = None, protocol: str | None = None,
             torch_threads: int | None = None):
    """Fine-tune the pre-trained run ``run_dir`` on ``task`` (returns its fine-tuning run,
    :class:`~dvfb.runs.layout.FinetuneRun`), or, given a list of runs, a group (docs/members.md) in
    lockstep in this process (returns the list of their fine-tuning runs).

    Member k is the fine-tuning run ``RUN_k/finetune/<name>`` that a separate ``finetune`` of
    ``run_dir[k]`` writes: its own skill (its zero-shot protocol and random streams), environments,
    replay, logs, curve and resume checkpoints. A group's fine-tuners are stacked, so each update and
    each action is one batched pass for all members. The runs must be one method with one
    configuration (seeds aside) and have the snapshot. As pre-training: options are checked and the
    directories' writability is tested before any work, one process writes a fine-tuning run at a
    time, SIGTERM/SIGINT checkpoint the current step and raise :class:`~dvfb.core.errors.RunInterrupted`,
    a failed resume changes no file and resuming a finished run is a no-op. In a group, a member
    whose loss or action goes non-finite stops alone (its one line); the others finish, and the call
    then raises :class:`~dvfb.core.errors.NonFiniteLossError`.

    ``log``: overrides of the pre-training run's ``log`` section (``{"wandb": True}``: also log to
    Weights & Biases, docs/methods.md, "Logging to Weights & Biases"). ``torch_threads``: the
    command's ``--torch-threads`` (:func:`~dvfb.workflows.resources.use_threads`).
    """
    if resume and overwrite:
        raise ConfigError("--resume and --overwrite contradict each other: pass one of them")
    many = not isinstance(run_dir, (str, Path))
    run_paths = list(run_dir) if many else [run_dir]
    if not run_paths:
        raise ConfigError("a group fine-tuning needs at least one run")
    if len({Path(p).resolve() for p in run_paths}) != len(run_paths):
        raise ConfigError("a run is listed twice: the members of a group are distinct runs")
    members = [_prepared(p, task, snapshot, inference, finetune, seed, name, resume, device, log, protocol,
                         torch_threads) for p in run_paths]
    if many:
        _check_group(members)
    locks = [RunLock(m.path) for m in members]
    with contextlib.ExitStack() as stack:
        try:
            for lock in locks:  # a member in use: the directories locked so far are removed again
                stack.enter_context(lock)
            runs = _run(members, task, resume, overwrite, progress, many)
        except BaseException:
            for lock in locks:
                lock.remove_if_created()
            raise
    return runs if many else runs[0]


@dataclass
class _Member:
    """A fine-tuning run checked and ready to start: its pre-training run and model, its config and
    its fine-tuner's class (the one ``run_config.protocol`` names)."""

    run: PretrainRun
    config: object
    model: object
    snapshot: int
    run_config: FinetuneRunConfig
    finetuner_cls: type[Finetuner]
    path: Path
    task: str


def _prepared(run_path, task, snapshot, inference, finetune, seed, name, resume, device, log=None,
              protocol=None, torch_threads=None) -> _Member:
    """Everything :func:`finetune` checks before it takes the run's lock."""
    run = open_run(run_path, torch_threads)
    config = run.config
    check_task_in_domain(task, config.domain)
    if resume:
        previous = FinetuneRun.open(run.finetune_path(name or task))
        # A resume computes with the threads the fine-tuning computed with (the shell's
        # OMP_NUM_THREADS aside), unless --torch-threads asks otherwise.
        resume_threads(previous, torch_threads)
        if protocol is None:  # a resumed run keeps the fine-tuner it was started with
            protocol = previous.config.protocol
    protocol = resolve_finetuner(config.agent, protocol)
    finetuner_cls = finetuner_class(protocol)
    check_finetune_options(protocol, finetune or {})
    own = protocol == get_spec(config.agent).finetuner
    model, snapshot = load_model(run, snapshot, device)
    # The run config's finetune section is the method's own fine-tuner's; another starts from its defaults.
    base = config.finetune if own else finetuner_cls.config_cls()
    run_config = FinetuneRunConfig(
        pretrain_run=str(run.path), agent=config.agent, domain=config.domain, task=task, snapshot=snapshot,
        seed=config.seed if seed is None else seed, device=str(model.device), protocol=protocol,
        inference=merge(config.inference, inference or {}, "inference."),
        finetune=merge(base, finetune or {}, "finetune."), log=merge(config.log, log or {}, "log."))
    require_wandb(run_config.log)
    finetuner_cls.check(model, run_config.finetune)
    check_replay(run_config.finetune.replay_capacity, "--finetune.replay-capacity", finetuner_cls.needs_of(model),
                 envs.TASKS[task].episode_length, config.domain)
    path = run.finetune_path(name or (task if own else f"{task}.{protocol}"))
    if resume:
        RunDir.open(path)  # names what is missing before anything else happens
    else:
        check_writable(path.parent)
    return _Member(run, config, model, snapshot, run_config, finetuner_cls, path, task)


def _check_group(members: list[_Member]) -> None:
    """What a group fine-tunes in lockstep: one method and configuration, one snapshot, one protocol."""
    check_one_method([(m.run, m.config) for m in members])
    first = members[0]
    first.finetuner_cls.check_group(first.run_config.finetune)
    if len({m.snapshot for m in members}) != 1:
        raise ConfigError("the members' snapshots are of different frames; pass --snapshot")
    for m in members[1:]:
        for section in ("inference", "finetune"):
            if to_dict(getattr(m.run_config, section)) != to_dict(getattr(first.run_config, section)):
                raise ConfigError(f"{m.run.path} and {first.run.path} have different {section} sections: a group "
                                  "fine-tunes its members with one protocol")


def _run(members: list[_Member], task: str, resume: bool, overwrite: bool, progress, many: bool) -> list:
    sessions = [FinetuneSession(m, resume, overwrite) for m in members]
    if all(s.finished for s in sessions):
        return [s.run for s in sessions]
    if any(s.finished for s in sessions):
        raise ConfigError("some members of the group have finished and others not: resume the others alone")
    for session in sessions:
        session.begin()
    check_lockstep(sessions)
    cfg = sessions[0].cfg
    finetuner_cls = sessions[0].finetuner_cls
    what = f"finetune {task}" + (f" ({len(sessions)} members)" if many else "")
    group = Group(sessions, [s.finetuner for s in sessions], what, "fine-tuning",
                  lambda t: finetuner_cls.uniform_seed_actions and t < cfg.seed_frames)
    learner = group.learner

    def evaluate_all(t: int) -> None:
        live = list(group.live)
        skills = [s.evaluation_skill() for s in live]
        for session, evaluation in zip(live, evaluate(learner.act, [s.eval_env for s in live], skills,
                                                      cfg.eval_episodes)):
            session.record_evaluation(t, evaluation)

    if not sessions[0].curve:
        evaluate_all(0)  # the zero-shot point of every member's curve

    def after_step(t: int) -> None:
        for session in list(group.live):
            session.after_step(t)
        if sessions[0].evaluation_due(t):
            evaluate_all(t)

    bar = Progress(cfg.frames, group.step, what, progress)
    checkpoints = group.checkpoints(cfg.checkpoint_every, cfg.frames)
    observers = [ReplayWriter(group.lanes, [s.replay for s in sessions]), ProgressCount(bar),
                 TrainingSteps(group, cfg.first_update(), cfg.update_every, checkpoints, after_step,
                               lambda session, t: session.after_episode(t))]
    try:
        with checkpoints:
            rollout(group.lanes, group.policy, observers, start=group.step, stop=cfg.frames)
            group.window.check()
    finally:
        bar.close()
        group.close_logs()
    for session in group.live:
        session.finish()
    group.raise_if_stopped()
    return [s.run for s in sessions]


class FinetuneSession(RunSession):
    """One fine-tuning run directory's share of a fine-tuning (:class:`RunSession`): its environments,
    replay, skill, fine-tuner (unstacked; a group stacks its members' afterwards), logs and curve.

    The constructor creates (or, resuming, opens and reads) the run directory; :meth:`begin` seeds
    the run's streams and builds its state: resuming, from the checkpoint; fresh, by finding the
    task's skill with the method's zero-shot protocol (in the fine-tuning environment, whose
    episodes go on from there) and building the fine-tuner on the member's model. A fresh run's
    curve is empty until the caller records the zero-shot evaluation (:meth:`record_evaluation`).
    """

    kind = RESUME_KIND
    phase = "fine-tuning"
    tag = "finetune"
    budget_flag = "--finetune.frames"
    # pretrain_run: where the pre-training run is, which changes when its directory moves.
    # log: where the metrics are sent besides the run directory (docs/methods.md, "Logging to Weights & Biases").
    resumable = ("device", "finetune.frames", "pretrain_run", "log")

    def __init__(self, member: _Member, resume: bool, overwrite: bool):
        self.member, self.model = member, member.model
        self.run_config = self.config = member.run_config
        self.cfg, self.seed, self.task = member.run_config.finetune, member.run_config.seed, member.task
        self.finetuner_cls = member.finetuner_cls
        self.resume = resume
        self.open(FinetuneRun, member.path, resume, overwrite)

    @property
    def total(self) -> int:
        return self.cfg.frames

    @property
    def device(self):
        return self.model.device

    def wandb_name(self) -> str:
        """The W&B run's name: the pre-training run's directory and this run's name under it."""
        return f"{self.member.run.path.resolve().name}/finetune/{self.run.path.name}"

    def begin(self) -> None:
        member, model, cfg, state = self.member, self.model, self.cfg, self.state
        self.rng = rng = seed_everything(self.seed)
        env = envs.make(self.task, seed=self.seed)
        self.eval_env = envs.make(self.task, seed=self.seed)  # same seed as the training env, as in [C]
        max_len = envs.TASKS[self.task].episode_length
        # Batches are drawn the way the pre-training drew them (uniform, or the authors' loader shards).
        self.replay = ReplayBuffer(cfg.replay_capacity, model.obs_dim, model.action_dim, model.skill_dim,
                                   max_episode_length=max_len, device=model.device,
                                   sampler=member.config.replay.sampler())
        self.make_generator()
        model.use_generator(self.generator)
        self.lane = Lane(env, rng)
        if state is not None:
            try:
                z = None if state["z"] is None else state["z"].to(model.device)
                self.finetuner = self.finetuner_cls(model, z, cfg)
                self.finetuner.load_training_state(state["finetuner"])
                self.replay.load_state_dict(state["replay"])
                self.eval_env.unwrapped.set_rng_state(state["eval_env_rng"])
                self.curve, self.inference_info = state["curve"], state["inference_info"]
                self.episodes = state.get("episodes", [])
                self.restore(state, self.lane.state, z)
            except (KeyError, TypeError, ValueError, RuntimeError) as exc:
                raise CheckpointError(f"cannot resume {self.run.path}: the checkpoint does not fit this run ({exc})") \
                    from exc
            self.run.save_config(self.run_config)  # only now may the config change (a larger --finetune.frames)
            self.run.record_resume(self.command, self.step)
            notify(f"[finetune] resuming {self.run.path} from step {self.step} (of {cfg.frames})")
        else:
            held = None  # inference data the fine-tuner reads apart from its replay
            if self.finetuner_cls.infers_skill:
                keep = self.finetuner_cls.keeps_inference_data(cfg)
                protocol = zero_shot_protocol(get_spec(member.config.agent).zero_shot)(self.run_config.inference)
                z, self.inference_info = protocol.task_skill(model, env, rng, max_len, keep_data=keep)
                if keep and self.finetuner_cls.replays_inference_data(cfg):
                    # the inference episodes, as collected, with z = z_r (D12 option)
                    _copy_episodes(self.inference_info.pop("buffer"), self.replay, z)
                elif keep:
                    held = self.inference_info.pop("buffer")
                # The inference data are discarded (§8.2 step 6) unless kept above.
            else:  # no labelled data: the fine-tuner finds the skill from the interaction itself
                z, self.inference_info = None, {"protocol": self.finetuner_cls.name, "labelled_steps": 0}
            self.finetuner = self.finetuner_cls(model, z, cfg)
            if held is not None:
                self.finetuner.bind_inference_data(held)
            self.curve, self.episodes = [], []
        self.finetuner.compile()
        self.z = z
        self.needs = self.finetuner.replay_needs()
        self.finetuner.bind_replay(self.replay)
        self.start_logging(state is not None, model.nonfinite_hint)
        if state is not None:
            self._write_curve()

    def bind_member(self, learner: Learner, index: int | None) -> None:
        super().bind_member(learner, index)
        self._skill_row = None

    def skill_rule(self, t: int, episode_start: bool, current):
        skill = self.learner.rollout_skill(t, episode_start, current, self.generator, obs=self.lane.state.obs)
        return self._row(skill)

    def evaluation_skill(self):
        return self._row(self.learner.skill)

    def _row(self, skill):
        if self.index is None or skill is None or skill.dim() == 1:
            return skill
        # A group's fine-tuner holds its members' fixed skills stacked: this member's is its row
        # (the same tensor every step, so the replay's host copy is made once).
        if self._skill_row is None or self._skill_row[0] is not skill:
            self._skill_row = (skill, skill[self.index])
        return self._skill_row[1]

    def extra_record(self) -> dict:
        return {"z": None if self.z is None else self.z.cpu(), "curve": self.curve,
                "inference_info": self.inference_info, "finetuner": self.learner_state(), "episodes": self.episodes,
                "replay": self.replay.state_dict(), "eval_env_rng": self.eval_env.unwrapped.get_rng_state()}

    def after_step(self, t: int) -> None:
        self.step = t  # what a checkpoint written at this step records
        if t % 1000 == 0 or t == self.cfg.frames:
            self.log_window(t)

    def after_episode(self, t: int) -> None:
        """A training episode ended at step ``t``: its return joins the per-episode curve of the
        protocols that record one (:attr:`~dvfb.protocols.base.Finetuner.records_episodes`)."""
        if self.finetuner_cls.records_episodes:
            self.episodes.append({"frames": t, "return": float(self.lane.state.episode_return)})

    def evaluation_due(self, t: int) -> bool:
        return t % self.cfg.eval_every == 0 or t == self.cfg.frames

    def record_evaluation(self, t: int, evaluation: Evaluation) -> None:
        """The evaluation at step ``t``: a curve point, its log record and the curve file."""
        self.curve.append(curve_point(t, evaluation.summary()))
        point = self.curve[-1]
        self.logger.log(t, {"eval_return": point["mean_return"],
                            **({"eval_success_rate": point["success_rate"]} if "success_rate" in point else {})},
                        prefix="eval")
        self._write_curve()

    def _write_curve(self) -> None:
        c = self.run_config
        # A protocol that finds the skill itself (online inference): the one it evaluates now.
        z = self.z if self.finetuner_cls.infers_skill else self.finetuner.skill
        self.run.write_curve(Curve(task=c.task, domain=c.domain, agent=c.agent, seed=c.seed, snapshot=c.snapshot,
                                   z=None if z is None else z.cpu().tolist(),
                                   inference_info=self.inference_info, curve=self.curve,
                                   protocol=None if c.own_protocol else c.protocol,
                                   episodes=self.episodes if self.finetuner_cls.records_episodes else None))

    def finish(self) -> None:
        if self.finetuner_cls.records_episodes:
            self._write_curve()  # the episodes that ended after the last evaluation
        self.run.write_summary(_summary(self.task, self.step, self.curve, wall_clock_s=time.time() - self.started))

    def lost_summary(self, state: dict) -> FinetuneSummary | None:
        curve = state.get("curve")
        if not curve or not self.run.curve_path.is_file():
            return None
        return _summary(self.task, state["step"], curve, rebuilt=True)


def _summary(task: str, frames: int, curve: list[dict], **fields) -> FinetuneSummary:
    """A finished fine-tuning's summary: its first (zero-shot) and last evaluations."""
    return FinetuneSummary(
        task=task, frames=frames, zero_shot_return=curve[0]["mean_return"], final_return=curve[-1]["mean_return"],
        zero_shot_success_rate=curve[0].get("success_rate"), final_success_rate=curve[-1].get("success_rate"),
        **fields)


def _copy_episodes(source: ReplayBuffer, target: ReplayBuffer, z: torch.Tensor | None) -> None:
    """The zero-shot protocol's episodes into the fine-tuning replay as they were collected (their
    boundaries and discounts), each step with the skill ``z``."""
    z_np = None if z is None else z.cpu().numpy()
    for obs, action, reward, discount in source.episodes():
        skills = None if z_np is None else np.repeat(z_np[None], len(action), axis=0)
        target.add_episode(obs, action, reward, discount, skills)
