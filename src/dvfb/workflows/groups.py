"""What every group of members shares, pre-training or fine-tuning (docs/members.md): the live
members, the stacked learner they bind to, their metric window, their lockstep data source and
the stopping of a member that faults.

A *session* is one member's run directory and its state (:class:`~dvfb.workflows.pretrain.PretrainSession`,
:class:`~dvfb.workflows.finetune.FinetuneSession`). It has ``run``, ``seed``, ``last_checkpoint``,
``logger``, ``collector``, ``window``, :meth:`bind_member`, :meth:`sample` and :meth:`save_resume`.
"""

from __future__ import annotations

from typing import Callable

from dvfb.errors import ConfigError, NonFiniteLossError
from dvfb.nets.members import drop_members
from dvfb.data import Batch
from dvfb.training.loop import GroupSource
from dvfb.training.checkpointing import checkpoint_note
from dvfb.training.metrics import GroupWindow
from dvfb.training.progress import notify
from dvfb.runs.run_config import agent_sections


def check_one_method(runs: list) -> None:
    """The pre-training runs ``[(run, config), ...]`` of a group are one method with one
    configuration on one domain: they differ only in their seeds."""
    first_run, first = runs[0]
    for run, config in runs[1:]:
        if config.agent != first.agent or agent_sections(config) != agent_sections(first) \
                or config.domain != first.domain:
            raise ConfigError(f"{run.path} is not the same method and configuration as {first_run.path}: "
                              "the members of a group differ only in their seeds")


class MemberGroup:
    """The sessions of a group and the learner that stacks them (its member k is ``live[k]``).

    ``act(obs (M, O), skills) -> (M, U)`` gives the live members' policy actions in one batched
    pass. A member whose metrics or action go non-finite stops alone: its one line names its run,
    its logs close, the learner drops its slice and the others go on; :meth:`raise_if_stopped`
    then ends the command non-zero.
    """

    def __init__(self, sessions: list, learner, what: str, phase: str, act: Callable, log_episodes: bool = False):
        self.sessions, self.learner, self.what, self.phase = sessions, learner, what, phase
        self.live = list(sessions)
        self.stopped: list[str] = []
        self._bind()
        self.window = GroupWindow(lambda: list(self.live), self.stop, learner.nonfinite_hint)
        for session in sessions:
            session.window = self.window.member_window(session)
        # With log_episodes: the members whose episode ended this step (:meth:`ended_episodes`).
        self.ended: list = []
        self.source = GroupSource(lambda: [s.collector for s in self.live], act, self._action_fault,
                                  self.ended.append if log_episodes else None)

    def _bind(self) -> None:
        for i, session in enumerate(self.live):
            session.bind_member(self.learner, i)

    def stop(self, session, message: str) -> None:
        """A member's fault: its one line, its logs closed; the group goes on without it."""
        line = (f"member seed {session.seed} ({session.run.path}): {message}; its {self.phase} stopped, "
                f"{checkpoint_note(session.last_checkpoint)}")
        notify(f"[{self.what}] {line}")
        self.stopped.append(line)
        session.logger.close()
        self.live.remove(session)
        if not self.live:
            raise NonFiniteLossError("; ".join(self.stopped))
        drop_members(self.learner, [s.index for s in self.live])
        self._bind()

    def _action_fault(self, collector, message: str) -> None:
        self.window.flush()  # a loss that went non-finite first is named first
        session = next((s for s in self.live if s.collector is collector), None)
        if session is not None:
            self.stop(session, message)

    def update(self) -> dict:
        """One update of every live member, each on a batch from its own replay and stream."""
        return self.learner.update(Batch.stack([s.sample() for s in self.live]))

    def ended_episodes(self) -> list:
        """The live sessions whose episode ended at this step (then forgotten)."""
        ended = [s for s in self.live if s.collector in self.ended]
        self.ended.clear()
        return ended

    def save(self, mid_episode: bool) -> None:
        for session in self.live:
            session.save_resume(mid_episode)

    def close_logs(self) -> None:
        for session in self.live:
            session.logger.close()

    def raise_if_stopped(self) -> None:
        if self.stopped:
            raise NonFiniteLossError(f"{len(self.stopped)} of {len(self.sessions)} members stopped, the others "
                                     "finished: " + "; ".join(self.stopped))
