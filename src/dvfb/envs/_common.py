"""Pieces shared by several domains (docs/tasks.md §4 notation)."""

from __future__ import annotations

import functools

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
    whose errors the rendering code reports with advice (dvfb.workflows.video)."""
    import mujoco  # late: its import reads MUJOCO_GL (see above)

    return mujoco, mujoco.mjtState.mjSTATE_INTEGRATION


def mujoco_state(model, data) -> list[float]:
    """MuJoCo's full integration state (time, positions, velocities, activations, controls, mocap,
    solver warm start, ...) of raw ``MjModel`` / ``MjData``, as a list."""
    mujoco, spec = _mujoco_state_api()
    state = np.empty(mujoco.mj_stateSize(model, spec), dtype=np.float64)
    mujoco.mj_getState(model, data, state, spec)
    return state.tolist()


# ------------------------------------------------------------------------------------------------
# Datasets: the physics state recorded with every observation (docs/methods.md, "Datasets")

# MuJoCo's state parts a dataset row holds, in MuJoCo's state order: its "physics" state (positions,
# velocities, actuator activations, actuator delay history), the controls (the point-mass reward
# reads them: physics.control()) and the mocap bodies' poses (Meta-World's hand target; none in
# DMC). Time, the solver's warm start and applied forces are left out: no reward reads them and the
# position and velocity stages that the rewards read do not depend on them.
PHYSICS_PARTS = ("qpos", "qvel", "act", "history", "ctrl", "mocap_pos", "mocap_quat")


@functools.cache
def _physics_bits() -> dict[str, int]:
    mujoco, _ = _mujoco_state_api()
    return {part: int(getattr(mujoco.mjtState, f"mjSTATE_{part.upper()}")) for part in PHYSICS_PARTS}


def _physics_spec() -> int:
    return sum(_physics_bits().values())


def physics_layout(model) -> list[tuple[str, int]]:
    """(part, size) of a dataset's physics vector for a raw ``MjModel``: the parts of
    :data:`PHYSICS_PARTS` that the model has (size > 0), in order."""
    mujoco, _ = _mujoco_state_api()
    sizes = [(part, int(mujoco.mj_stateSize(model, bit))) for part, bit in _physics_bits().items()]
    return [(part, size) for part, size in sizes if size]


def physics_vector(model, data) -> np.ndarray:
    """The physics vector (float64) of :func:`physics_layout` of raw ``MjModel`` / ``MjData``."""
    mujoco, _ = _mujoco_state_api()
    spec = _physics_spec()
    state = np.empty(mujoco.mj_stateSize(model, spec), dtype=np.float64)
    mujoco.mj_getState(model, data, state, spec)
    return state


def physics_setter(model, data, recompute: str):
    """``set(values)``: writes a physics vector of :func:`physics_vector` into ``data``, then
    recomputes the derived quantities as :func:`set_mujoco_state` does (``"step1"``: what a
    dm_control step leaves behind, positions and velocities of the new state; ``"forward"``: what
    Meta-World reads after each step). The other state parts of ``data`` are left as they are."""
    mujoco, _ = _mujoco_state_api()
    spec = _physics_spec()
    derive = {"step1": mujoco.mj_step1, "forward": mujoco.mj_forward}[recompute]

    def set_state(values: np.ndarray) -> None:
        mujoco.mj_setState(model, data, values, spec)
        derive(model, data)

    return set_state


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
