"""Hopper domain (docs/tasks.md §4.3): stock asset; hop is stock, the other three are custom rewards.

All four share the stock ``Hopper`` task's initial state and ``standing`` term; they differ only in
the motion term: forward/backward centre-of-mass speed, or forward/backward angular momentum.
"""

from __future__ import annotations

from dm_control.rl import control
from dm_control.suite import hopper as stock_hopper
from dm_control.utils import rewards

from dvfb.envs._common import INF, torso_subtree_angular_momentum_y

TIME_LIMIT_S = 20  # 1000 steps of 0.02 s (docs/tasks.md §4.3)
CONTROL_DT = 0.02
STAND_HEIGHT_RANGE = (0.6, 2.0)  # torso-over-foot height range where `standing` is 1
HOP_SPEED = 2.0
FLIP_MOMENTUM = 5.0


class _HopperCustomReward(stock_hopper.Hopper):
    """Stock hopper task (initial state, observation) with r = standing * motion_term."""

    def __init__(self, random=None):
        super().__init__(hopping=True, random=random)

    def motion_term(self, physics) -> float:
        raise NotImplementedError

    def get_reward(self, physics) -> float:
        standing = rewards.tolerance(physics.height(), STAND_HEIGHT_RANGE)
        return standing * self.motion_term(physics)


class HopperHopBackward(_HopperCustomReward):
    """hop_backward (docs/tasks.md §4.3): r = standing * clip(-v_x / 2)."""

    def motion_term(self, physics) -> float:
        return rewards.tolerance(
            -physics.speed(),
            bounds=(HOP_SPEED, INF),
            margin=HOP_SPEED / 2,
            value_at_margin=0.5,
            sigmoid="linear",
        )


class HopperFlip(_HopperCustomReward):
    """flip / flip_backward (docs/tasks.md §4.3): r = standing * clip(direction * L_y / 5).

    ``direction`` is +1 for a forward flip (positive L_y) and -1 for a backward flip.
    """

    def __init__(self, direction: float, random=None):
        super().__init__(random=random)
        self.direction = float(direction)

    def motion_term(self, physics) -> float:
        return rewards.tolerance(
            self.direction * torso_subtree_angular_momentum_y(physics),
            bounds=(FLIP_MOMENTUM, INF),
            margin=FLIP_MOMENTUM,
            value_at_margin=0,
            sigmoid="linear",
        )


def make_task(task: str, seed: int | None = None):
    """The dm_control task object for ``task`` (stock ``Hopper`` for hop, docs/tasks.md §3.1)."""
    if task == "hop":
        return stock_hopper.Hopper(hopping=True, random=seed)
    if task == "hop_backward":
        return HopperHopBackward(random=seed)
    direction = {"flip": 1.0, "flip_backward": -1.0}[task]
    return HopperFlip(direction=direction, random=seed)


def build_environment(task: str, seed: int | None = None) -> control.Environment:
    """A dm_control environment for ``hopper_<task>``: stock hopper, 4 substeps, 20 s.

    The authors' enlarged floor is rendering-only (docs/tasks.md §6) and is not applied.
    """
    physics = stock_hopper.Physics.from_xml_string(*stock_hopper.get_model_and_assets())
    return control.Environment(
        physics, make_task(task, seed), time_limit=TIME_LIMIT_S, control_timestep=CONTROL_DT
    )
