"""Quadruped domain (docs/tasks.md §4.2): stock asset through the stock model builder.

walk and run are the stock dm_control tasks; stand and jump are custom rewards on the same
``Move`` task class, so initial states (random orientation, lowest non-contacting height) match.
"""

from __future__ import annotations

from dm_control.rl import control
from dm_control.suite import common
from dm_control.suite import quadruped as stock_quadruped
from dm_control.utils import rewards

from dvfb.envs._common import INF

TIME_LIMIT_S = 20  # 1000 steps of 0.02 s (docs/tasks.md §4.2)
CONTROL_DT = 0.02
WALK_SPEED = 0.5
RUN_SPEED = 5.0
JUMP_HEIGHT = 1.0  # centre-of-mass height above which the jump term is 1

# Floor half-size F given to the stock builder (time limit x speed, as the stock suite does).
# Planes are infinite for collision, so F only changes rendering (docs/tasks.md §4.2).
FLOOR_SIZE = {"stand": 10, "walk": 10, "jump": 10, "run": 100}


def upright_reward(physics) -> float:
    """upright = tol(zz; [1, inf), m=2, linear, v=0) = (1 + zz) / 2 (docs/tasks.md §4.2)."""
    return rewards.tolerance(
        physics.torso_upright(), bounds=(1.0, INF), sigmoid="linear", margin=2.0, value_at_margin=0
    )


class QuadrupedStand(stock_quadruped.Move):
    """Stand (docs/tasks.md §4.2): r = upright."""

    def __init__(self, random=None):
        super().__init__(desired_speed=0.0, random=random)

    def get_reward(self, physics) -> float:
        return upright_reward(physics)


class QuadrupedJump(stock_quadruped.Move):
    """Jump (docs/tasks.md §4.2): r = upright * clip(0.5 + c_z / 2), c_z = whole-body CoM height.

    c_z is the stock ``center_of_mass`` sensor (subtree CoM of the torso, world z).
    """

    def __init__(self, random=None):
        super().__init__(desired_speed=0.0, random=random)

    def get_reward(self, physics) -> float:
        com_height = physics.named.data.sensordata["center_of_mass"][2]
        jump = rewards.tolerance(
            com_height,
            bounds=(JUMP_HEIGHT, INF),
            margin=JUMP_HEIGHT,
            value_at_margin=0.5,
            sigmoid="linear",
        )
        return upright_reward(physics) * jump


def make_task(task: str, seed: int | None = None):
    """The dm_control task object for ``task`` (stock ``Move`` for walk/run, docs/tasks.md §3.1)."""
    if task == "stand":
        return QuadrupedStand(random=seed)
    if task == "jump":
        return QuadrupedJump(random=seed)
    speed = {"walk": WALK_SPEED, "run": RUN_SPEED}[task]
    return stock_quadruped.Move(desired_speed=speed, random=seed)


def build_environment(task: str, seed: int | None = None) -> control.Environment:
    """A dm_control environment for ``quadruped_<task>``: stock builder, floor F, 4 substeps."""
    xml = stock_quadruped.make_model(floor_size=FLOOR_SIZE[task])
    physics = stock_quadruped.Physics.from_xml_string(xml, common.ASSETS)
    return control.Environment(
        physics, make_task(task, seed), time_limit=TIME_LIMIT_S, control_timestep=CONTROL_DT
    )
