"""Gymnasium front end for a dm_control task: the URLB states-mode wrapper stack (docs/tasks.md §3).

What :class:`DMCGymEnv` does, per docs/tasks.md §3 (innermost first):

* §3.2/§3.4: actions are float32 in, float64 into MuJoCo; the observation dict is concatenated in
  key order into one float32 vector (a new array every step, safe to store).
* §3.3: action repeat 1 (states mode), i.e. one env step = one dm_control step.
* §3.5: affine action scaling from [-1, 1] to the actuator bounds, without clipping. It is the
  identity for every task except quadruped (lift 1.05a + 0.05, extend 0.8a).
* §3.6 and §2: the reset step has no reward; the 1000th step (dm_control's LAST step, discount 1)
  is a time-limit truncation, so ``terminated`` is always False and ``truncated`` is True there.
* §3 "Reward-free pre-training still computes a reward": the task reward is always computed and
  returned in ``info["task_reward"]``; with ``reward_free=True`` the returned reward is 0.0.
* Datasets (docs/methods.md, "Datasets"): :meth:`DMCGymEnv.physics_state` is the physics vector
  recorded with each observation, and :meth:`DMCGymEnv.rewards_from_physics` the task's reward of
  recorded states, computed as :meth:`DMCGymEnv.step` computes it.
"""

from __future__ import annotations

from typing import Any

import dm_env
import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded

from dvfb.envs._common import (mujoco_state, physics_layout, physics_setter, physics_vector, random_state_to_list,
                               set_mujoco_state, set_random_state)
from dvfb.envs.registry import TaskSpec

_FLOAT64 = np.float64
_FLOAT32 = np.float32
_LAST = dm_env.StepType.LAST


class DMCGymEnv(gym.Env):
    """A dm_control ``control.Environment`` behind the gymnasium API (docs/tasks.md §3).

    Attributes:
        task_spec: the :class:`TaskSpec` of the task being run.
        dmc_env: the underlying dm_control ``control.Environment``.
        physics: the dm_control ``Physics`` (same object as ``dmc_env.physics``).
        reward_free: if True, ``step`` returns reward 0.0 (the task reward stays in ``info``).
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        task_spec: TaskSpec,
        dmc_env,
        reward_free: bool = False,
        render_mode: str | None = None,
        render_size: tuple[int, int] = (240, 320),
    ):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode={render_mode!r} is not supported; use one of "
                f"{self.metadata['render_modes']} or None"
            )
        self.task_spec = task_spec
        self.dmc_env = dmc_env
        self.physics = dmc_env.physics
        self.reward_free = bool(reward_free)
        self.render_mode = render_mode
        self.render_size = render_size
        self.metadata = {**self.metadata, "render_fps": round(1.0 / task_spec.control_dt)}

        self.observation_space = spaces.Box(
            -np.inf, np.inf, shape=(task_spec.obs_dim,), dtype=_FLOAT32
        )
        self.action_space = spaces.Box(-1.0, 1.0, shape=(task_spec.action_dim,), dtype=_FLOAT32)
        self._action_shape = (task_spec.action_dim,)

        # Affine map a_env = low + (high - low) / 2 * (a + 1) (docs/tasks.md §3.5), written in URLB's
        # operation order. For [-1, 1] actuators it is the identity and is skipped entirely.
        bounds = dmc_env.action_spec()
        low = np.broadcast_to(np.asarray(bounds.minimum, _FLOAT64), self._action_shape).copy()
        high = np.broadcast_to(np.asarray(bounds.maximum, _FLOAT64), self._action_shape).copy()
        if np.all(low == -1.0) and np.all(high == 1.0):
            self._action_low = None
            self._action_half_range = None
        else:
            self._action_low = low
            self._action_half_range = (high - low) / 2.0
        self._scalar_positions: tuple[int, ...] | None = None
        self._needs_reset = True

    # ----------------------------------------------------------------------------------------
    # Gymnasium API

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode. A ``seed`` reseeds every RNG of the task (initial-state draws).

        Without a seed the task's RNG streams continue, so successive episodes differ; a given
        seed always reproduces the same initial state (docs/tasks.md §2 "Seeding").
        """
        super().reset(seed=seed)
        if seed is not None:
            reseed_task(self.dmc_env.task, seed)
        time_step = self.dmc_env.reset()
        self._needs_reset = False
        return self._flatten(time_step.observation), {}

    def step(self, action):
        """One control step: returns (obs, reward, terminated=False, truncated, info)."""
        if self._needs_reset:
            raise ResetNeeded("call reset() before step() (the episode ended or never started)")
        if type(action) is not np.ndarray:
            action = np.asarray(action, dtype=_FLOAT64)
        if action.shape != self._action_shape:
            raise ValueError(f"action has shape {action.shape}, expected {self._action_shape}")
        if self._action_low is not None:
            action = self._action_low + self._action_half_range * (action.astype(_FLOAT64) + 1.0)
        # Identity-scaled actions go in as they are: MuJoCo's float64 ctrl buffer receives them
        # through np.copyto, which widens float32 exactly (the URLB dtype cast of §3.2).
        time_step = self.dmc_env.step(action)
        task_reward = float(time_step.reward)
        truncated = time_step.step_type is _LAST
        if truncated:
            self._needs_reset = True
        return (
            self._flatten(time_step.observation),
            0.0 if self.reward_free else task_reward,
            False,
            truncated,
            {"task_reward": task_reward},
        )

    # ----------------------------------------------------------------------------------------
    # Exact resume

    def _task_random_states(self) -> dict[str, np.random.RandomState]:
        task = self.dmc_env.task
        return {name: value for name, value in vars(task).items()
                if isinstance(value, np.random.RandomState)} | {"random": task.random}

    def get_rng_state(self) -> dict:
        """Every RNG of the task (initial-state draws) as plain lists, for a resume checkpoint.

        Taken between episodes, it lets a rebuilt env continue with the same initial states as
        the uninterrupted one. (Physics state is not included: checkpoints are taken at episode
        ends, where the next reset overwrites it.)
        """
        return {name: random_state_to_list(random) for name, random in self._task_random_states().items()}

    def set_rng_state(self, state: dict) -> None:
        randoms = self._task_random_states()
        if set(state) != set(randoms):
            raise ValueError(f"RNG state has streams {sorted(state)}, this task has {sorted(randoms)}")
        for name, values in state.items():
            set_random_state(randoms[name], values)

    def get_episode_state(self) -> dict:
        """The state of the episode in progress, for a checkpoint taken mid-episode (a signal).

        MuJoCo's full integration state (time, positions, velocities, activations, controls,
        solver warm start, ...), the episode's step count and the task's RNG streams. Restored with
        :meth:`set_episode_state` into an env of the same task, the episode continues exactly as
        it would have (tests/test_envs.py).
        """
        return {"physics": mujoco_state(self.physics.model.ptr, self.physics.data.ptr),
                "step_count": int(self.dmc_env._step_count), "needs_reset": bool(self._needs_reset),
                "rng": self.get_rng_state()}

    def set_episode_state(self, state: dict) -> None:
        # dm_control steps Euler models as mj_step2 then mj_step1, so the derived quantities of
        # the current state (what mj_step1 computes) must be up to date before the next step.
        set_mujoco_state(self.physics.model.ptr, self.physics.data.ptr, state["physics"], recompute="step1")
        self.dmc_env._step_count = int(state["step_count"])
        self.dmc_env._reset_next_step = bool(state["needs_reset"])
        self._needs_reset = bool(state["needs_reset"])
        self.set_rng_state(state["rng"])

    # ----------------------------------------------------------------------------------------
    # Datasets: physics states and the rewards of recorded states

    @property
    def physics_layout(self) -> list[tuple[str, int]]:
        """(part, size) of :meth:`physics_state`: qpos, qvel, act, ctrl, ... (dvfb.envs._common.PHYSICS_PARTS)."""
        return physics_layout(self.physics.model.ptr)

    @property
    def physics_width(self) -> int:
        return sum(size for _, size in self.physics_layout)

    def physics_state(self) -> np.ndarray:
        """The physics vector (float64, :attr:`physics_width`) of the current state: after a
        :meth:`step`, the state its reward was computed from; after :meth:`reset`, the initial one."""
        return physics_vector(self.physics.model.ptr, self.physics.data.ptr)

    def rewards_from_physics(self, states: np.ndarray) -> np.ndarray:
        """This task's reward (float64, one per row) of each physics vector of ``states`` (N,
        :attr:`physics_width`), exactly as :meth:`step` returns it for a step that arrives there:
        the state is written into MuJoCo, ``mj_step1`` recomputes what a dm_control step leaves
        behind (positions, velocities, sensors), and the task's ``get_reward`` reads it. Overwrites
        the episode in progress: reset before stepping again."""
        states = np.ascontiguousarray(states, dtype=np.float64)
        if states.ndim != 2 or states.shape[1] != self.physics_width:
            raise ValueError(f"{self.task_spec.name}: physics states of shape {states.shape}, expected "
                             f"(N, {self.physics_width})")
        set_state = physics_setter(self.physics.model.ptr, self.physics.data.ptr, recompute="step1")
        task, physics = self.dmc_env.task, self.physics
        rewards = np.empty(len(states), dtype=np.float64)
        for i, state in enumerate(states):
            set_state(state)
            rewards[i] = task.get_reward(physics)
        self._needs_reset = True
        return rewards

    def render(self):
        """An RGB frame (H, W, 3) from camera 0 when ``render_mode == "rgb_array"``, else None."""
        if self.render_mode != "rgb_array":
            return None
        height, width = self.render_size
        return self.physics.render(height=height, width=width, camera_id=0)

    # ----------------------------------------------------------------------------------------

    def _flatten(self, observation) -> np.ndarray:
        """Concatenate the observation dict in key order into float32 (docs/tasks.md §2, §3.4).

        One ``np.concatenate`` straight into a new float32 array (no float64 intermediate).
        Scalar entries (e.g. the walker's height) are wrapped as 1-element sequences; which entries
        are scalars is worked out, and the total size checked, on the first observation.
        """
        if self._scalar_positions is None:
            self._scalar_positions = self._check_observation_layout(observation)
        if not self._scalar_positions:
            return np.concatenate(tuple(observation.values()), dtype=_FLOAT32)
        parts = list(observation.values())
        for position in self._scalar_positions:
            parts[position] = (parts[position],)
        return np.concatenate(parts, dtype=_FLOAT32)

    def _check_observation_layout(self, observation) -> tuple[int, ...]:
        """Positions of the 0-d entries; raises if an entry is not flat or the size is wrong."""
        scalar_positions, size = [], 0
        for position, (key, value) in enumerate(observation.items()):
            ndim = np.ndim(value)
            if ndim > 1:
                raise ValueError(f"observation {key!r} is not flat: shape {np.shape(value)}")
            if ndim == 0:
                scalar_positions.append(position)
            size += int(np.size(value))
        if size != self.task_spec.obs_dim:
            raise ValueError(
                f"{self.task_spec.name}: observation has {size} entries, "
                f"the task table says {self.task_spec.obs_dim}"
            )
        return tuple(scalar_positions)

    def __repr__(self) -> str:
        mode = ", reward_free" if self.reward_free else ""
        return f"<DMCGymEnv {self.task_spec.name}{mode}>"


def reseed_task(task, seed: int) -> None:
    """Reseed a dm_control task's RNGs in place (equivalent to building it with ``random=seed``).

    Tasks with extra RNGs (the maze start position) implement ``reseed(seed)`` themselves.
    """
    reseed = getattr(task, "reseed", None)
    if reseed is not None:
        reseed(seed)
    else:
        task.random.seed(seed)
