"""One run directory being written by a training loop: the session core that pre-training and
fine-tuning share (docs/architecture.md, "Sessions").

A :class:`RunSession` creates its run directory, or opens it to resume: the resume rules (which
options may change), the finished check, the resume checkpoint (kind, format version, random
streams, environment state, episode state) and its metrics log are the same for every kind of run.
A session of pre-training or fine-tuning adds only what differs: its learner, replay or dataset,
skill rule, snapshots or curve (:mod:`dvfb.workflows.pretrain`, :mod:`dvfb.workflows.finetune`).

A run has one session; a group (docs/members.md) one per member, which the
:class:`~dvfb.workflows.group.Group` steps together.
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
import torch

from dvfb.core.config import to_dict
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.nets.learner import Learner
from dvfb.nets.members import member_slice
from dvfb.runs import MetricsLogger, load_checkpoint, remove_orphaned_checkpoints, save_checkpoint
from dvfb.runs.migrations import RESUME_FORMAT, check_resume_format
from dvfb.runs.wandb_sink import WandbSink, stored_wandb_id
from dvfb.training.metric_windows import MetricWindow
from dvfb.training.progress import notify
from dvfb.training.rollout import EpisodeState, Lane
from dvfb.training.seeding import restore_rng_state, rng_state, run_generator


def config_changes(stored: Any, requested: Any, resumable: tuple[str, ...]) -> list[str]:
    """The top-level fields in which two configs differ, leaving out the dotted fields that may
    change on a resume (``frames``, ``perf.compile``, ...)."""
    a, b = to_dict(stored), to_dict(requested)
    for path in resumable:
        *parents, key = path.split(".")
        for d in (a, b):
            for parent in parents:
                d = d.get(parent, {})
            d.pop(key, None)
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


class RunSession:
    """One run's share of a training loop (module docstring). Subclasses set the class fields and
    call :meth:`open` from their constructor, then (in the order a group needs them, member after
    member) :meth:`begin` to build their random streams and restore or start their state."""

    kind: ClassVar[str] = ""  # of its resume checkpoints
    phase: ClassVar[str] = ""  # "pre-training", "fine-tuning": what one-line messages call it
    tag: ClassVar[str] = ""  # "pretrain", "finetune": the prefix of its status lines
    budget_flag: ClassVar[str] = ""  # the option of its steps: "--frames", "--finetune.frames"
    # Config fields (dotted) a resume may change: they change how much is run or how it executes,
    # not what is computed.
    resumable: ClassVar[tuple[str, ...]] = ()

    run: Any
    command: list[str] | None = None  # this call's command line: meta.json records it, and each resume's
    config: Any  # the config the run is written with (the run directory's config.json)
    seed: int
    finished = False
    step = 0
    last_checkpoint: int | None = None
    state: dict | None = None  # the checkpoint a resume continues from
    lane: Lane | None = None  # its environment (None offline)
    rng: np.random.Generator
    generator: torch.Generator
    index: int | None = None  # its member index in a group's stacked learner (None: its own learner)
    learner: Learner | None = None  # its group's (bind_member): an agent or a fine-tuner
    logger: MetricsLogger
    window: Any
    window_state: dict | None = None  # the metric rows a resumed checkpoint carried (restore)

    # Creating or opening -------------------------------------------------------------------------
    def open(self, run_cls, path, resume: bool, overwrite: bool, command=None) -> None:
        """Create the run directory, or open it to resume: its config must equal this session's but
        for :attr:`resumable` fields; a finished run sets :attr:`finished`; otherwise the latest
        checkpoint is read (``state``). Nothing is written on a resume until the state is restored."""
        self.command = command
        if not resume:
            self.run = run_cls.create(path, self.config, overwrite=overwrite, command=command)
            return
        run = run_cls.open(path)
        changes = config_changes(run.config, self.config, self.resumable)
        if changes:
            raise ConfigError(f"--resume with a different configuration: {', '.join(changes)} differ from "
                              f"{run.config_path}; resume with the original options")
        self.run = run
        done = run.finished_frames()
        if done is not None and done >= self.total:
            notify(f"[{self.tag}] {run.path} already finished at {done} frames (>= {self.budget_flag} {self.total}); "
                   "nothing to resume")
            self.finished = True
            return
        remove_orphaned_checkpoints(run)
        try:
            state = load_checkpoint(run, None, map_location=self.device)
        except CheckpointError as exc:
            raise CheckpointError(f"cannot resume {run.path}: {exc}") from exc
        if state.get("kind") != self.kind or not self.fits(state):
            raise CheckpointError(f"{run.path}: the latest checkpoint is not a {self.describe_kind()} checkpoint")
        check_resume_format(state, run.path)
        if state["step"] >= self.total:
            summary = self.lost_summary(state) if state["step"] == self.total else None
            if summary is not None:  # it finished, then lost its summary (deleted by hand, a half-copied run)
                run.write_summary(summary)
                notify(f"[{self.tag}] {run.path} had finished at {self.total} frames but had lost its "
                       f"{run.summary_path.name}; rebuilt it from the last checkpoint (without wall-clock figures); "
                       "nothing to resume")
                self.finished = True
                return
            raise ConfigError(f"{self.budget_flag} {self.total} is not beyond the checkpoint's step {state['step']}; "
                              f"pass a larger {self.budget_flag} to extend the run")
        log = getattr(self.config, "log", None)
        if log is not None and log.wandb:
            stored_wandb_id(run)  # a damaged id refuses the resume here, before begin() rewrites config.json
        self.state = state

    @property
    def total(self) -> int:
        """The steps the run ends at."""
        raise NotImplementedError

    @property
    def device(self) -> torch.device:
        raise NotImplementedError

    def fits(self, state: dict) -> bool:
        """Whether a checkpoint of the right kind is this run's (pre-training: of its method)."""
        return True

    def lost_summary(self, state: dict):
        """The summary of a run whose last checkpoint ``state`` is at its final step but whose summary
        file is gone, rebuilt from that checkpoint; None when the run's results are not all there
        (then the resume is refused as one beyond the budget)."""
        return None

    def describe_kind(self) -> str:
        return self.phase

    # Random streams and the checkpoint record ----------------------------------------------------
    def make_generator(self) -> None:
        """The run's own torch stream: every skill draw, policy noise, module sample and batch."""
        self.generator = run_generator(self.seed, self.device)

    def restore(self, state: dict, episode: EpisodeState | None, skill: torch.Tensor | None = None) -> None:
        """What every resume restores: the step and episode counters, the random streams, the
        environment's random state and, for a checkpoint written mid-episode, the episode (``skill``:
        its skill when the checkpoint has none). ``episode`` is the lane's (None offline)."""
        self.generator.set_state(state["generator"])
        restore_rng_state(state["rng"], self.rng)
        if self.lane is not None:
            self.lane.env.unwrapped.set_rng_state(state["env_rng"])
            episode_state = state.get("episode_state")
            if episode_state is not None:  # a checkpoint written mid-episode (on a signal)
                self.lane.env.unwrapped.set_episode_state(episode_state["env"])
                episode.obs = np.asarray(episode_state["obs"], dtype=np.float32)
                skill = episode_state.get("skill", skill)
                episode.set_skill(None if skill is None else skill.to(self.device))
                episode.episode_return = float(episode_state.get("episode_return", 0.0))
                episode.episode_start = False
            episode.episode = state.get("episode", 0)
        self.step = state["step"]
        self.last_checkpoint = self.step
        # The metric rows of the window the checkpoint cut (loaded by start_logging, or by a group
        # into its member window), so that the next record equals an uninterrupted run's.
        self.window_state = state.get("metric_window")

    def checkpoint_record(self, mid_episode: bool) -> dict:
        """The part of a resume checkpoint every run writes (see :meth:`restore`); the kind of run adds
        :meth:`extra_record`."""
        record = {"kind": self.kind, "format": RESUME_FORMAT, "step": self.step, "generator": self.generator.get_state(),
                  "rng": rng_state(self.rng), "episode": 0 if self.lane is None else self.lane.state.episode,
                  "metric_window": self.window.state()}
        if self.lane is not None:
            episode = self.lane.state
            record["env_rng"] = self.lane.env.unwrapped.get_rng_state()
            if mid_episode:
                record["episode_state"] = {
                    "env": self.lane.env.unwrapped.get_episode_state(), "obs": torch.as_tensor(episode.obs),
                    "skill": None if episode.skill is None else episode.skill.cpu(),
                    "episode_return": episode.episode_return}
        return record

    def extra_record(self) -> dict:
        """What the kind of run adds to its checkpoints (the learner's state, the replay, ...)."""
        return {}

    def save_resume(self, mid_episode: bool = False) -> None:
        save_checkpoint(self.run, {**self.checkpoint_record(mid_episode), **self.extra_record()}, f"resume_{self.step}")
        self.last_checkpoint = self.step

    # The learner ---------------------------------------------------------------------------------
    def bind_member(self, learner: Learner, index: int | None) -> None:
        """Whose state this run saves: ``learner`` itself (``index`` None), or member ``index`` of a
        stacked group's (the index changes when a member before it stops)."""
        self.learner, self.index = learner, index

    def learner_state(self) -> dict:
        state = self.learner.training_state()
        return state if self.index is None else member_slice(state, self.index)

    def sample(self):
        return self.needs.sample(self.replay, self.generator)

    # Logging -------------------------------------------------------------------------------------
    def start_logging(self, resumed: bool, hint=None) -> None:
        # Records up to the checkpointed step belong to the restored state; later ones are redone.
        self.logger = MetricsLogger(self.run, purge_step=self.step + 1 if resumed else None, sink=self.wandb_sink())
        self.window = MetricWindow(hint)
        if resumed:
            self.window.load_state(self.window_state)
        self.started = time.time()
        self.start_step = self.step
        self.last_log = (self.started, self.step)  # (time, step) of the newest record's rate

    def wandb_sink(self) -> WandbSink | None:
        """The run's W&B run when its config asks for one (``--log.wandb``; docs/methods.md, "Logging to
        Weights & Biases"): named :meth:`wandb_name`, with the run config as its config."""
        log = getattr(self.config, "log", None)
        if log is None or not log.wandb:
            return None
        return WandbSink(self.run, log, to_dict(self.config), name=self.wandb_name(), job_type=self.tag)

    def wandb_name(self) -> str:
        """The W&B run's name: the run directory's."""
        return self.run.path.resolve().name

    def log_window(self, step: int, extra: dict | None = None) -> None:
        """The window's means as a ``train`` record at ``step`` (nothing when it is empty)."""
        means = self.window.flush()
        if means:
            self.logger.log(step, {**means, **(extra or {})}, prefix="train")
