"""Cheetah domain (docs/tasks.md §4.4, paper Appendix G): stock asset; run is stock, the rest custom.

Every task rewards r = clip(direction * v_x / speed); there is no stand term.
"""

from __future__ import annotations

import contextlib
import logging

from dm_control.rl import control
from dm_control.suite import cheetah as stock_cheetah
from dm_control.utils import rewards

from dvfb.envs._common import INF

TIME_LIMIT_S = 10  # 1000 steps of 0.01 s, 1 substep (docs/tasks.md §4.4)
RUN_SPEED = 10.0
WALK_SPEED = 2.0


class _DropSettotalmassWarning(logging.Filter):
    """Drops MuJoCo's deprecation notice for the stock cheetah's ``settotalmass`` attribute.

    MuJoCo 3.17 still applies the attribute (the stock dynamics are unchanged); dm_control logs the
    notice through absl on every model compile, i.e. once per cheetah env built.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        return "'settotalmass' is deprecated" not in record.getMessage()


@contextlib.contextmanager
def _quiet_settotalmass_notice():
    logger = logging.getLogger("absl")
    notice_filter = _DropSettotalmassWarning()
    logger.addFilter(notice_filter)
    try:
        yield
    finally:
        logger.removeFilter(notice_filter)


class CheetahMove(stock_cheetah.Cheetah):
    """Cheetah moving at ``speed`` in ``direction`` (+1 forward, -1 backward), docs/tasks.md §4.4.

    r = tol(direction * v_x; [speed, inf), m=speed, linear, v=0) = clip(direction * v_x / speed).
    """

    def __init__(self, speed: float, direction: float, random=None):
        super().__init__(random=random)
        self.speed = float(speed)
        self.direction = float(direction)

    def get_reward(self, physics) -> float:
        return rewards.tolerance(
            self.direction * physics.speed(),
            bounds=(self.speed, INF),
            margin=self.speed,
            value_at_margin=0,
            sigmoid="linear",
        )


def make_task(task: str, seed: int | None = None):
    """The dm_control task object for ``task`` (stock ``Cheetah`` for run, docs/tasks.md §3.1)."""
    if task == "run":
        return stock_cheetah.Cheetah(random=seed)
    speed, direction = {
        "run_backward": (RUN_SPEED, -1.0),
        "walk": (WALK_SPEED, 1.0),
        "walk_backward": (WALK_SPEED, -1.0),
    }[task]
    return CheetahMove(speed=speed, direction=direction, random=seed)


def build_environment(task: str, seed: int | None = None) -> control.Environment:
    """A dm_control environment for ``cheetah_<task>``: stock cheetah, control dt = physics dt.

    The authors' enlarged ground is rendering-only (docs/tasks.md §6) and is not applied.
    """
    with _quiet_settotalmass_notice():
        physics = stock_cheetah.Physics.from_xml_string(*stock_cheetah.get_model_and_assets())
    return control.Environment(physics, make_task(task, seed), time_limit=TIME_LIMIT_S)
