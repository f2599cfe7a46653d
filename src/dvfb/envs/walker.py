"""Walker domain (docs/tasks.md §4.1): stock asset and stock task class, plus a custom flip task.

stand, walk and run are the stock dm_control tasks. flip reuses the stock walker and its stand term
but rewards forward angular momentum instead of forward speed.
"""

from __future__ import annotations

from dm_control.rl import control
from dm_control.suite import walker as stock_walker
from dm_control.utils import rewards

from dvfb.envs._common import INF, torso_subtree_angular_momentum_y

TIME_LIMIT_S = 25  # 1000 steps of 0.025 s (docs/tasks.md §4.1)
CONTROL_DT = 0.025
STAND_HEIGHT = 1.2  # torso height above which `standing` is 1
WALK_SPEED = 1.0
RUN_SPEED = 8.0
FLIP_MOMENTUM = 5.0  # L_y above which the flip term is 1


class WalkerFlip(stock_walker.PlanarWalker):
    """Forward flip (docs/tasks.md §4.1): r = stand_r * (5 * clip(L_y / 5) + 1) / 6.

    The authors construct it with the run speed, which the flip reward then ignores.
    """

    def __init__(self, random=None):
        super().__init__(move_speed=RUN_SPEED, random=random)

    def get_reward(self, physics) -> float:
        standing = rewards.tolerance(
            physics.torso_height(), bounds=(STAND_HEIGHT, INF), margin=STAND_HEIGHT / 2
        )
        upright = (1 + physics.torso_upright()) / 2
        stand_reward = (3 * standing + upright) / 4
        flip = rewards.tolerance(
            torso_subtree_angular_momentum_y(physics),
            bounds=(FLIP_MOMENTUM, INF),
            margin=FLIP_MOMENTUM,
            value_at_margin=0,
            sigmoid="linear",
        )
        return stand_reward * (5 * flip + 1) / 6


def make_task(task: str, seed: int | None = None):
    """The dm_control task object for ``task`` (stock for stand/walk/run, docs/tasks.md §3.1)."""
    if task == "flip":
        return WalkerFlip(random=seed)
    move_speed = {"stand": 0.0, "walk": WALK_SPEED, "run": RUN_SPEED}[task]
    return stock_walker.PlanarWalker(move_speed=move_speed, random=seed)


def build_environment(task: str, seed: int | None = None) -> control.Environment:
    """A dm_control environment for ``walker_<task>``: stock walker, 10 substeps, 25 s."""
    physics = stock_walker.Physics.from_xml_string(*stock_walker.get_model_and_assets())
    return control.Environment(
        physics, make_task(task, seed), time_limit=TIME_LIMIT_S, control_timestep=CONTROL_DT
    )
