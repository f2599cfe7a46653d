"""Meta-World faucet-open and faucet-close (docs/tasks.md §4.6), behind the same gymnasium API.

Needs the optional extra ``pip install -e '.[metaworld]'`` (metaworld 3.0.0). Importing this module
checks the installed version and, on MuJoCo builds whose weld constraint has 12 parameters
(3.17 has; the MuJoCo that metaworld was written for had 11), fixes Meta-World's mocap-weld reset,
which otherwise fails when a faucet env is built (docs/tasks.md §7). The fix writes the same 11
values as Meta-World and leaves the new 12th one at the model's value. Nothing of dm_control is
touched, so the DMC tasks' physics do not change when the extra is installed.

What :class:`MetaWorldGymEnv` does (docs/tasks.md §4.6):

* The task set is ML1's 50 **test** tasks of the faucet env, built with the env's seed. Every reset
  picks one uniformly at random and applies it (the faucet position), then resets.
* Observations: 39 float32 values, the goal coordinates zeroed (ML1 is partially observable).
* Episodes are truncated after 250 steps (never terminated); Meta-World's own limit (500) is never
  reached.
* The reward is Meta-World's default "v2" reward in [0, 10]; ``info["task_reward"]`` always holds it
  and ``info["success"]`` the task's success flag (handle within 7 cm of the target) at this step.
  The protocol reads success at the final step of an episode (docs/tasks.md §4.6).
* Datasets (docs/methods.md, "Datasets"): the faucet reward reads, after each step's forward
  pass, the handle's and the gripper's site positions (from MuJoCo's positions) and the episode's
  task constants (the faucet position drawn for the task, Meta-World's ``rand_vec``, from which its
  reset derives the target, the initial handle and gripper positions); not the action, nor the
  previous observation frame. So :meth:`MetaWorldGymEnv.physics_state` is MuJoCo's physics vector
  followed by the task's ``rand_vec``, and :meth:`MetaWorldGymEnv.rewards_from_physics` recomputes
  the reward exactly, for either faucet task.
"""

from __future__ import annotations

import functools
import importlib.metadata
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded

from dvfb.core.errors import ConfigError
from dvfb.envs._common import (mujoco_state, physics_layout, physics_setter, physics_vector, random_state_to_list,
                               set_mujoco_state, set_random_state)
from dvfb.envs.registry import TaskSpec

SUPPORTED_VERSION = "3.0.0"
INSTALL_HINT = "pip install -e '.[metaworld]'  (or: pip install metaworld==3.0.0)"
# Meta-World's env names of the two tasks (docs/tasks.md §4.6: the "-v3" envs, v2 reward by default).
ENV_NAMES = {"faucet_open": "faucet-open-v3", "faucet_close": "faucet-close-v3"}
RENDER_CAMERA = "corner2"  # the camera of the authors' wrapper (docs/tasks.md §4.6)
# Meta-World's corner cameras were set up for mujoco-py, whose images came bottom row first; MuJoCo's
# renderer gives the top row first, so their images are flipped back to look the same.
_FLIPPED_CAMERAS = ("corner", "corner2", "corner3")
_FLOAT32 = np.float32


def _import_metaworld():
    """``metaworld``, after checking its version and fixing its weld reset for this MuJoCo."""
    try:
        version = importlib.metadata.version("metaworld")
    except importlib.metadata.PackageNotFoundError:
        raise ConfigError(f"the Meta-World tasks need the optional extra, which is not installed: {INSTALL_HINT}") from None
    if version != SUPPORTED_VERSION:
        raise ConfigError(f"metaworld {version} is installed, but dvfb's Meta-World tasks are checked against "
                          f"metaworld {SUPPORTED_VERSION} only: {INSTALL_HINT}")
    # metaworld is the optional extra, checked just above (~0.5 s to import); mujoco, late as in
    # dvfb.envs._common: its import reads MUJOCO_GL
    import mujoco
    import metaworld
    from metaworld import sawyer_xyz_env

    _fix_weld_reset(sawyer_xyz_env.SawyerMocapBase, mujoco)
    return metaworld


# Meta-World's weld reset: anchor (3), relative position (3), relative quaternion (4), torque scale.
_WELD_RESET = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 5.0])


def _fix_weld_reset(mocap_base: type, mujoco) -> None:
    """Make ``reset_mocap_welds`` write only the 11 parameters it knows (docs/tasks.md §7).

    Applied once, and only where MuJoCo's weld rows are longer than 11 (``mjNEQDATA``); on the
    MuJoCo that metaworld was written for the original method runs unchanged.
    """
    if mujoco.mjNEQDATA <= _WELD_RESET.size or getattr(mocap_base, "_dvfb_weld_fix", False):
        return

    def reset_mocap_welds(self) -> None:
        if self.model.nmocap > 0 and self.model.eq_data is not None:
            for i in range(self.model.eq_data.shape[0]):
                if self.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD:
                    self.model.eq_data[i, : _WELD_RESET.size] = _WELD_RESET

    mocap_base.reset_mocap_welds = reset_mocap_welds
    mocap_base._dvfb_weld_fix = True


metaworld = _import_metaworld()


@functools.lru_cache(maxsize=16)
def ml1_test_tasks(task: str, seed: int) -> tuple:
    """ML1's 50 test tasks of ``task`` built with ``seed`` (cached: ML1 takes ~2 s to build)."""
    return tuple(metaworld.ML1(ENV_NAMES[task], seed=seed).test_tasks)


class MetaWorldGymEnv(gym.Env):
    """A Meta-World faucet env as an ML1 test-task distribution (docs/tasks.md §4.6).

    Attributes:
        task_spec: the :class:`TaskSpec` of the task being run.
        mw_env: the underlying Meta-World env (one instance; tasks are switched at every reset).
        tasks: ML1's 50 test tasks for this env's seed.
        task_index: index into ``tasks`` of the episode in progress (None before the first reset).
        reward_free: if True, ``step`` returns reward 0.0 (the task reward stays in ``info``).
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, task_spec: TaskSpec, seed: int | None = None, reward_free: bool = False,
                 render_mode: str | None = None, render_size: tuple[int, int] = (240, 320)):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} is not supported; use one of "
                             f"{self.metadata['render_modes']} or None")
        self.task_spec = task_spec
        self.reward_free = bool(reward_free)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": round(1.0 / task_spec.control_dt)}
        env_cls = metaworld.env_dict.ALL_V3_ENVIRONMENTS[ENV_NAMES[task_spec.task]]
        self.render_size = render_size
        self.mw_env = env_cls()
        self._renderers: dict[tuple[int, int], Any] = {}
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(task_spec.obs_dim,), dtype=_FLOAT32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(task_spec.action_dim,), dtype=_FLOAT32)
        self._action_shape = (task_spec.action_dim,)
        self._reseed(np.random.SeedSequence().entropy % 2**31 if seed is None else int(seed))
        self.task_index: int | None = None
        self._step_count = 0
        self._needs_reset = True

    def _reseed(self, seed: int) -> None:
        """Everything that depends on the seed: the test-task set and the stream that picks tasks."""
        self.seed = seed
        self.tasks = ml1_test_tasks(self.task_spec.task, seed)
        self._task_random = np.random.RandomState(seed)

    # ----------------------------------------------------------------------------------------
    # Gymnasium API

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode on a test task drawn uniformly at random. A ``seed`` rebuilds the task
        set and the draws exactly as an env made with that seed would have them."""
        super().reset(seed=seed)
        if seed is not None:
            self._reseed(seed)
        obs = self._start(int(self._task_random.randint(len(self.tasks))))
        return obs.astype(_FLOAT32), {}

    def _start(self, task_index: int) -> np.ndarray:
        self.task_index = task_index
        self.mw_env.set_task(self.tasks[task_index])
        obs, _ = self.mw_env.reset()
        self._step_count = 0
        self._needs_reset = False
        return obs

    def step(self, action):
        """One control step: returns (obs, reward, terminated=False, truncated, info)."""
        if self._needs_reset:
            raise ResetNeeded("call reset() before step() (the episode ended or never started)")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self._action_shape:
            raise ValueError(f"action has shape {action.shape}, expected {self._action_shape}")
        obs, reward, _, _, info = self.mw_env.step(action)
        self._step_count += 1
        truncated = self._step_count >= self.task_spec.episode_length
        if truncated:
            self._needs_reset = True
        task_reward = float(reward)
        return (obs.astype(_FLOAT32), 0.0 if self.reward_free else task_reward, False, truncated,
                {"task_reward": task_reward, "success": bool(info["success"])})

    # ----------------------------------------------------------------------------------------
    # Datasets: physics states and the rewards of recorded states (module docstring)

    @property
    def physics_layout(self) -> list[tuple[str, int]]:
        """(part, size) of :meth:`physics_state`: MuJoCo's parts (qpos, qvel, ctrl, mocap_pos,
        mocap_quat; dvfb.envs._common.PHYSICS_PARTS), then the task's ``rand_vec``."""
        return physics_layout(self.mw_env.model) + [("rand_vec", int(self.mw_env._random_reset_space.shape[0]))]

    @property
    def physics_width(self) -> int:
        return sum(size for _, size in self.physics_layout)

    def physics_state(self) -> np.ndarray:
        """The physics vector (float64, :attr:`physics_width`) of the current state: after a
        :meth:`step`, the state its reward was computed from; after :meth:`reset`, the initial one."""
        return np.concatenate([physics_vector(self.mw_env.model, self.mw_env.data),
                               np.asarray(self.mw_env._last_rand_vec, dtype=np.float64)])

    def rewards_from_physics(self, states: np.ndarray) -> np.ndarray:
        """This task's reward (float64, one per row) of the physics vectors of one episode (N,
        :attr:`physics_width`; one task ``rand_vec``), exactly as :meth:`step` returns it for a step
        that arrives there: Meta-World's reset for that ``rand_vec`` sets the episode's constants,
        then per row MuJoCo's state is written, its forward pass run, and the observation (clipped
        as Meta-World's step clips it) scored by the env's own ``evaluate_state``. Overwrites the
        episode in progress: reset before stepping again."""
        states = np.ascontiguousarray(states, dtype=np.float64)
        if states.ndim != 2 or states.shape[1] != self.physics_width:
            raise ValueError(f"{self.task_spec.name}: physics states of shape {states.shape}, expected "
                             f"(N, {self.physics_width})")
        mw = self.mw_env
        width = int(mw._random_reset_space.shape[0])
        rand_vec = states[0, -width:]
        if not (states[:, -width:] == rand_vec).all():
            raise ValueError(f"{self.task_spec.name}: the physics states come from several episodes (their task "
                             "rand_vec differs); give one episode at a time")
        if not getattr(mw, "_set_task_called", False):
            mw.set_task(self.tasks[0])
        mw._last_rand_vec, mw._freeze_rand_vec = rand_vec.copy(), True
        mw.reset()
        set_state = physics_setter(mw.model, mw.data, recompute="forward")
        space = mw.sawyer_observation_space
        action = np.zeros(self._action_shape)  # the faucet rewards do not read it
        rewards = np.empty(len(states), dtype=np.float64)
        for i, state in enumerate(states):
            set_state(state[:-width])
            obs = np.clip(mw._get_obs(), a_max=space.high, a_min=space.low, dtype=np.float64)
            rewards[i] = float(mw.evaluate_state(obs, action)[0])
        self._needs_reset = True
        return rewards

    def render(self):
        """An RGB frame (H, W, 3) from the authors' camera when ``render_mode == "rgb_array"``."""
        if self.render_mode != "rgb_array":
            return None
        return self.render_frame(*self.render_size, RENDER_CAMERA)

    @property
    def camera_names(self) -> list[str]:
        model = self.mw_env.model
        return [model.camera(i).name for i in range(model.ncam)]

    def render_frame(self, height: int, width: int, camera: str | int = RENDER_CAMERA) -> np.ndarray:
        """An RGB frame (H, W, 3) of the current state from a named camera (or an id; -1 = free)."""
        import mujoco  # late, as in dvfb.envs._common: its import reads MUJOCO_GL

        renderer = self._renderers.get((height, width))
        if renderer is None:
            renderer = self._renderers[(height, width)] = mujoco.Renderer(self.mw_env.model, height, width)
        renderer.update_scene(self.mw_env.data, camera=camera)
        frame = renderer.render()
        name = camera if isinstance(camera, str) else (self.camera_names[camera] if camera >= 0 else "")
        return np.ascontiguousarray(frame[::-1]) if name in _FLIPPED_CAMERAS else frame

    def close(self):
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
        self.mw_env.close()

    # ----------------------------------------------------------------------------------------
    # Exact resume (same contract as the DMC envs: dvfb.envs.gym_env)

    def get_rng_state(self) -> dict:
        """The seed of the task set and the task-drawing stream as plain lists, for a resume checkpoint."""
        return {"seed": self.seed, "tasks": random_state_to_list(self._task_random)}

    def set_rng_state(self, state: dict) -> None:
        if set(state) != {"seed", "tasks"}:
            raise ValueError(f"RNG state has streams {sorted(state)}, this task has ['seed', 'tasks']")
        if int(state["seed"]) != self.seed:
            self._reseed(int(state["seed"]))
        set_random_state(self._task_random, state["tasks"])

    def get_episode_state(self) -> dict:
        """The episode in progress, for a checkpoint taken mid-episode (a signal).

        A task's reset is deterministic, so the episode is the task index plus MuJoCo's integration
        state, the step count and the previous observation frame that Meta-World stacks.
        """
        return {"task_index": self.task_index, "physics": mujoco_state(self.mw_env.model, self.mw_env.data),
                "step_count": self._step_count, "needs_reset": self._needs_reset, "rng": self.get_rng_state(),
                "prev_frame": np.asarray(self.mw_env._prev_obs, dtype=np.float64).tolist()}

    def set_episode_state(self, state: dict) -> None:
        self.set_rng_state(state["rng"])  # first: it rebuilds the task set of the state's seed
        if state["task_index"] is not None:
            self._start(int(state["task_index"]))
            set_mujoco_state(self.mw_env.model, self.mw_env.data, state["physics"], recompute="forward")
            self.mw_env._prev_obs = np.asarray(state["prev_frame"], dtype=np.float64)
            self.mw_env.curr_path_length = self._step_count = int(state["step_count"])
        self._needs_reset = bool(state["needs_reset"])

    def __repr__(self) -> str:
        mode = ", reward_free" if self.reward_free else ""
        return f"<MetaWorldGymEnv {self.task_spec.name}{mode}>"


def make_gym_env(task_spec: TaskSpec, seed: int | None, reward_free: bool, render_mode: str | None):
    """The factory's entry point for this domain (dvfb.envs.make)."""
    return MetaWorldGymEnv(task_spec, seed=seed, reward_free=reward_free, render_mode=render_mode)
