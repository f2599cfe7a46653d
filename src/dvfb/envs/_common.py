"""Pieces shared by several domains (docs/tasks.md §4 notation)."""

from __future__ import annotations

import numpy as np

INF = float("inf")


def torso_subtree_angular_momentum_y(physics) -> float:
    """L_y of docs/tasks.md §4: y component (world frame) of the torso subtree's angular momentum.

    MuJoCo's ``subtree_angmom`` is the angular momentum about the subtree's own centre of mass. It
    is up to date after every dm_control step because the walker and hopper models carry a subtree
    velocity sensor, which makes MuJoCo compute the subtree velocities (docs/tasks.md §4, notation).
    """
    return float(physics.named.data.subtree_angmom["torso", "y"])


def as_random_state(random) -> np.random.RandomState:
    """A ``RandomState`` from a seed, None (fresh entropy) or an existing ``RandomState``."""
    if isinstance(random, np.random.RandomState):
        return random
    return np.random.RandomState(random)
