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


# ------------------------------------------------------------------------------------------------
# Exact resume: what every environment's checkpoint state is made of


def random_state_to_list(random: np.random.RandomState) -> list:
    """A ``RandomState``'s state as plain lists (JSON- and checkpoint-safe)."""
    kind, keys, pos, has_gauss, cached = random.get_state()
    return [kind, keys.tolist(), int(pos), int(has_gauss), float(cached)]


def set_random_state(random: np.random.RandomState, state: list) -> None:
    """Restore what :func:`random_state_to_list` gave."""
    kind, keys, pos, has_gauss, cached = state
    random.set_state((kind, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))


def _mujoco_state_api():
    """``mujoco`` and the state spec of a mid-episode checkpoint: everything MuJoCo needs to
    continue an episode bit for bit. Imported here, not at the top: mujoco's import reads MUJOCO_GL,
    whose errors the rendering code reports with advice (dvfb.analysis.video)."""
    import mujoco

    return mujoco, mujoco.mjtState.mjSTATE_INTEGRATION


def mujoco_state(model, data) -> list[float]:
    """MuJoCo's full integration state (time, positions, velocities, activations, controls, mocap,
    solver warm start, ...) of raw ``MjModel`` / ``MjData``, as a list."""
    mujoco, spec = _mujoco_state_api()
    state = np.empty(mujoco.mj_stateSize(model, spec), dtype=np.float64)
    mujoco.mj_getState(model, data, state, spec)
    return state.tolist()


def set_mujoco_state(model, data, values: list[float], recompute: str) -> None:
    """Restore what :func:`mujoco_state` gave (ValueError if it has the wrong size for ``model``),
    then recompute the derived quantities the environment's next step reads: ``"step1"`` for
    dm_control, which steps as mj_step2 then mj_step1, ``"forward"`` for Meta-World, which reads
    positions after each step's forward pass."""
    mujoco, spec = _mujoco_state_api()
    state = np.asarray(values, dtype=np.float64)
    size = mujoco.mj_stateSize(model, spec)
    if state.shape != (size,):
        raise ValueError(f"episode state has {state.shape[0]} physics values, this task needs {size}")
    mujoco.mj_setState(model, data, state, spec)
    {"step1": mujoco.mj_step1, "forward": mujoco.mj_forward}[recompute](model, data)
