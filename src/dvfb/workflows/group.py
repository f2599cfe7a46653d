"""A training loop's group of 1..N members (docs/members.md): the sessions, the learner they share,
their lanes and policy for the one rollout loop, their metric window, and the stopping of a member
that faults. A group of one is an ordinary run: its member keeps its own, unstacked learner, its
plain metric window, and a fault ends the run as it always has.

A *session* is one member's run directory and its state (:class:`~dvfb.workflows.session.RunSession`:
:class:`~dvfb.workflows.pretrain.PretrainSession`, :class:`~dvfb.workflows.finetune.FinetuneSession`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from dvfb.core.errors import CheckpointError, ConfigError, NonFiniteLossError
from dvfb.data import Batch
from dvfb.nets.learner import Learner
from dvfb.nets.members import drop_members, stack_agents
from dvfb.runs.run_config import agent_sections
from dvfb.training.checkpointing import ResumeCheckpoints, checkpoint_note
from dvfb.training.metric_windows import MetricWindow
from dvfb.training.progress import notify
from dvfb.training.rollout import Lane, Observer, Policy


def check_one_method(runs: list) -> None:
    """The pre-training runs ``[(run, config), ...]`` of a group are one method with one
    configuration on one domain: they differ only in their seeds."""
    first_run, first = runs[0]
    for run, config in runs[1:]:
        if config.agent != first.agent or agent_sections(config) != agent_sections(first) \
                or config.domain != first.domain:
            raise ConfigError(f"{run.path} is not the same method and configuration as {first_run.path}: "
                              "the members of a group differ only in their seeds")


def check_lockstep(sessions: list) -> None:
    """Members resumed together must stand at one step (their checkpoints are written together)."""
    if len({s.step for s in sessions}) != 1:
        raise CheckpointError("the members' latest checkpoints are of different steps ("
                              + ", ".join(f"{s.run.path}: {s.step}" for s in sessions)
                              + "): a group resumes in lockstep; resume them alone")


class Group:
    """The sessions of one training loop and their learner (member k of a stacked learner is
    ``live[k]``; a group of one holds its member's own learner).

    A member whose metrics or action go non-finite stops alone in a group of several: its one line
    names its run, its logs close, the learner drops its slice and the others go on;
    :meth:`raise_if_stopped` then ends the command non-zero. A group of one stops as a run does.
    """

    def __init__(self, sessions: list, learners: list[Learner], what: str, phase: str,
                 uniform: Callable[[int], bool] | None = None):
        self.sessions, self.what, self.phase = sessions, what, phase
        self.live = list(sessions)
        self.stopped: list[str] = []
        self.single = len(sessions) == 1
        self.learner: Learner = learners[0] if self.single else stack_agents(learners)
        self._bind()
        if self.single:
            self.window = sessions[0].window
        else:
            self.window = MetricWindow(self.learner.nonfinite_hint, lambda: list(self.live), self.stop)
            for session in sessions:
                session.window = self.window.member_window(session)
                session.window.load_state(session.window_state)
        self.lanes: list[Lane] = [s.lane for s in sessions if s.lane is not None]
        self.policy = GroupPolicy(self, uniform)

    def _bind(self) -> None:
        for i, session in enumerate(self.live):
            session.bind_member(self.learner, None if self.single else i)

    @property
    def step(self) -> int:
        return self.sessions[0].step

    def stop(self, session, message: str) -> None:
        """A member's fault: its one line, its logs closed; the group goes on without it."""
        line = (f"member seed {session.seed} ({session.run.path}): {message}; its {self.phase} stopped, "
                f"{checkpoint_note(session.last_checkpoint)}")
        notify(f"[{self.what}] {line}")
        self.stopped.append(line)
        session.logger.close()
        self.live.remove(session)
        if session.lane is not None and session.lane in self.lanes:
            self.lanes.remove(session.lane)
        if not self.live:
            raise NonFiniteLossError("; ".join(self.stopped))
        drop_members(self.learner, [s.index for s in self.live])
        self._bind()

    def update(self) -> dict:
        """One update of every live member, each on a batch from its own data and stream."""
        if self.single:
            return self.learner.update(self.live[0].sample())
        return self.learner.update(Batch.stack([s.sample() for s in self.live]))

    def session_of(self, lane: int):
        """The live session whose lane is ``lane`` of the rollout's lanes."""
        the_lane = self.lanes[lane]
        return next(s for s in self.live if s.lane is the_lane)

    def save(self, mid_episode: bool) -> None:
        for session in self.live:
            session.save_resume(mid_episode)

    def checkpoints(self, every: int, total: int) -> ResumeCheckpoints:
        """When the group writes its members' resume checkpoints (:class:`ResumeCheckpoints`); its
        messages name every member's run directory."""
        return ResumeCheckpoints(self.save, self.window, every, total, self.phase,
                                 [session.run.path for session in self.sessions],
                                 last=self.sessions[0].last_checkpoint)

    def close_logs(self) -> None:
        for session in self.live:
            session.logger.close()

    def raise_if_stopped(self) -> None:
        if self.stopped:
            raise NonFiniteLossError(f"{len(self.stopped)} of {len(self.sessions)} members stopped, the others "
                                     "finished: " + "; ".join(self.stopped))


class GroupPolicy(Policy):
    """The group's rollout policy: each live member's skill rule (``session.skill_rule``), the
    uniform phase, one batched act of the learner for all members, and the check of every
    member's action before the environments step (a non-finite one stops its member, or the run)."""

    def __init__(self, group: Group, uniform: Callable[[int], bool] | None):
        super().__init__(lambda obs, skills: group.learner.act(obs, skills, explore=True), None, uniform)
        self.group = group

    def choose_skills(self, step: int, lanes, starting) -> None:
        for session, start in zip(self.group.live, starting):
            session.lane.state.set_skill(session.skill_rule(step, start, session.lane.state.skill))

    def check(self, step: int, lanes: list[Lane], actions: list[np.ndarray]) -> list[np.ndarray]:
        bad = [k for k, action in enumerate(actions) if not np.isfinite(action).all()]
        if not bad:
            return actions
        message = f"the policy produced a non-finite action at step {step}"
        group = self.group
        acted = list(zip(lanes, actions))
        faulty = [lanes[k] for k in bad]
        group.window.flush()  # a loss that went non-finite first is named first (and stops its member)
        if group.single:
            raise NonFiniteLossError(message)
        for lane in faulty:
            session = next((s for s in group.live if s.lane is lane), None)
            if session is not None:
                group.stop(session, message)  # removes the lane
        return [action for lane, action in acted if lane in lanes]


class TrainingSteps(Observer):
    """A training loop's part of a rollout (docs/methods.md, "Training loop"): an update every
    ``update_every`` steps from ``learn_from`` on (before the environments step, as the authors' code
    does), the sessions' per-step work, their episode records, and the resume checkpoints at episode
    boundaries and on signals."""

    def __init__(self, group: Group, learn_from: int, update_every: int, checkpoints: ResumeCheckpoints,
                 after_step: Callable[[int], None], episode_ended: Callable | None = None):
        self.group, self.learn_from, self.update_every = group, learn_from, update_every
        self.checkpoints, self._after_step, self._episode_ended = checkpoints, after_step, episode_ended

    def before_env_step(self, step: int) -> None:
        if step >= self.learn_from and step % self.update_every == 0:
            self.group.window.add(step, self.group.update())

    def after_step(self, step: int) -> None:
        self._after_step(step)

    def episode_ended(self, lane: int, step: int) -> None:
        if self._episode_ended is not None:
            self._episode_ended(self.group.session_of(lane), step)

    def step_done(self, step: int, boundary: bool) -> None:
        if boundary:
            self.checkpoints.episode_end(step)
        self.checkpoints.after_step(step, mid_episode=not boundary)
