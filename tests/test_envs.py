"""Tests of dvfb.envs against the environment spec (docs/tasks.md), on real MuJoCo physics.

Reward checks set a physics state by hand, then compare the task's reward with a value computed
here, directly from the spec formula and MuJoCo's state arrays, without calling dvfb's helpers.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys

# dvfb.envs first: it picks a headless MUJOCO_GL default before dm_control is imported.
import dvfb.envs as envs  # isort: skip

import gymnasium
import mujoco
import numpy as np
import pytest
from dm_control import suite
from dm_control.suite.wrappers import action_scale
from gymnasium.error import ResetNeeded

from dvfb.core.errors import ConfigError

# ------------------------------------------------------------------------------------------------
# Spec constants, written out independently of the package (docs/tasks.md §0, §4, §5).

SPEC_TASKS = {
    "walker": ["stand", "walk", "run", "flip"],
    "quadruped": ["stand", "walk", "jump", "run"],
    "hopper": ["hop", "flip", "hop_backward", "flip_backward"],
    "cheetah": ["run", "run_backward", "walk", "walk_backward"],
    "point_mass_maze": [
        "reach_top_left",
        "reach_top_right",
        "reach_bottom_left",
        "reach_bottom_right",
    ],
}
ALL_TASKS = [f"{d}_{t}" for d, tasks in SPEC_TASKS.items() for t in tasks]  # the DMC tasks
# Meta-World (docs/tasks.md §4.6): registered after the DMC tasks, tested in tests/test_metaworld.py.
METAWORLD_TASKS = ["metaworld_faucet_open", "metaworld_faucet_close"]
# domain -> (obs dim, action dim, control dt, physics dt)
SPEC_DIMS = {
    "metaworld": (39, 4, 0.0125, 0.0025),
    "walker": (24, 6, 0.025, 0.0025),
    "quadruped": (78, 12, 0.02, 0.005),
    "hopper": (15, 4, 0.02, 0.005),
    "cheetah": (17, 6, 0.01, 0.01),
    "point_mass_maze": (4, 2, 0.02, 0.02),
}
SPEC_PRETRAIN = {
    "walker": "walker_walk",
    "quadruped": "quadruped_walk",
    "hopper": "hopper_hop",
    "cheetah": "cheetah_walk",
    "point_mass_maze": "point_mass_maze_reach_top_left",
}
MAZE_TARGETS = {
    "reach_top_left": (-0.15, 0.15),
    "reach_top_right": (0.15, 0.15),
    "reach_bottom_left": (-0.15, -0.15),
    "reach_bottom_right": (0.15, -0.15),
}
# One task per domain, preferring custom rewards, for the longer checks.
ONE_PER_DOMAIN = [
    "walker_flip",
    "quadruped_jump",
    "hopper_flip_backward",
    "cheetah_walk_backward",
    "point_mass_maze_reach_bottom_right",
]


def clip01(x: float) -> float:
    return min(max(x, 0.0), 1.0)


def random_actions(n: int, dim: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n, dim)).astype(np.float32)


def set_state(physics, qpos: dict | None = None, qvel: dict | None = None) -> None:
    """Reset the physics, write named joint positions/velocities, run a forward pass."""
    with physics.reset_context():
        for joint, value in (qpos or {}).items():
            physics.named.data.qpos[joint] = value
        for joint, value in (qvel or {}).items():
            physics.named.data.qvel[joint] = value


def task_reward(env) -> float:
    return float(env.unwrapped.dmc_env.task.get_reward(env.unwrapped.physics))


# ------------------------------------------------------------------------------------------------
# Registry


def test_registry_lists_every_spec_task_with_its_dims():
    assert list(envs.TASKS) == ALL_TASKS + METAWORLD_TASKS
    for name, spec in envs.TASKS.items():
        obs_dim, action_dim, control_dt, _ = SPEC_DIMS[spec.domain]
        episode_length = 250 if spec.domain == "metaworld" else 1000
        assert spec.name == name == f"{spec.domain}_{spec.task}"
        assert (spec.obs_dim, spec.action_dim, spec.episode_length) == (obs_dim, action_dim, episode_length)
        assert spec.control_dt == pytest.approx(control_dt)
    with pytest.raises(dataclasses.FrozenInstanceError):
        envs.TASKS["walker_walk"].obs_dim = 3


def test_domains_and_helpers():
    assert envs.DOMAINS == {**SPEC_PRETRAIN, "metaworld": "metaworld_faucet_open"}
    for domain, tasks in SPEC_TASKS.items():
        assert envs.tasks_of_domain(domain) == [f"{domain}_{t}" for t in tasks]
        assert envs.pretrain_task(domain) == SPEC_PRETRAIN[domain]
    with pytest.raises(ConfigError):
        envs.tasks_of_domain("jaco")
    table = envs.format_task_table()
    for name in ALL_TASKS:
        assert name in table
    assert "obs dim" in table and "action dim" in table and "episode length" in table


def test_unknown_name_raises_config_error_listing_valid_names():
    with pytest.raises(ConfigError) as info:
        envs.make("walker_moonwalk")
    message = str(info.value)
    assert isinstance(info.value, ValueError)
    for name in ("walker_flip", "hopper_hop_backward", "point_mass_maze_reach_top_left"):
        assert name in message
    assert "quadruped" in message and "cheetah" in message


def test_bare_domain_only_in_reward_free_mode():
    with pytest.raises(ConfigError, match="walker_walk"):
        envs.make("walker")
    for domain, pretrain_name in SPEC_PRETRAIN.items():
        if domain == "quadruped":
            continue  # covered elsewhere; keep the test fast
        env = envs.make(domain, seed=0, reward_free=True)
        assert env.unwrapped.task_spec.name == pretrain_name


# ------------------------------------------------------------------------------------------------
# Every task: builds, steps, spec dims, float32 finite observations, rewards in [0, 1]


@pytest.mark.parametrize("name", ALL_TASKS)
def test_task_builds_and_steps(name):
    domain = envs.TASKS[name].domain
    obs_dim, action_dim, control_dt, physics_dt = SPEC_DIMS[domain]
    env = envs.make(name, seed=1)
    assert env.observation_space.shape == (obs_dim,)
    assert env.observation_space.dtype == np.float32
    assert env.action_space.shape == (action_dim,)
    assert env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    dmc_env = env.unwrapped.dmc_env
    assert dmc_env.control_timestep() == pytest.approx(control_dt)
    assert env.unwrapped.physics.timestep() == pytest.approx(physics_dt)
    assert env.unwrapped.physics is dmc_env.physics

    obs, info = env.reset()
    assert isinstance(info, dict)
    assert obs.shape == (obs_dim,) and obs.dtype == np.float32 and np.all(np.isfinite(obs))
    for action in random_actions(40, action_dim):
        obs, reward, terminated, truncated, info = env.step(action)
        assert obs.shape == (obs_dim,) and obs.dtype == np.float32
        assert np.all(np.isfinite(obs))
        assert type(reward) is float and 0.0 <= reward <= 1.0
        assert info["task_reward"] == reward
        assert terminated is False and truncated is False
    # The observation is the task's observation dict concatenated in key order (docs/tasks.md §2).
    expected = np.concatenate(
        [np.ravel(v) for v in dmc_env.task.get_observation(dmc_env.physics).values()]
    ).astype(np.float32)
    np.testing.assert_array_equal(obs, expected)


@pytest.mark.parametrize("name", ONE_PER_DOMAIN)
def test_full_episode_truncates_at_step_1000(name):
    env = envs.make(name, seed=2)
    actions = random_actions(1000, env.action_space.shape[0], seed=3)
    env.reset()
    rewards = []
    for step, action in enumerate(actions, start=1):
        obs, reward, terminated, truncated, info = env.step(action)
        rewards.append(reward)
        assert terminated is False
        assert truncated is (step == 1000), f"truncated={truncated} at step {step}"
        assert np.all(np.isfinite(obs))
    assert min(rewards) >= 0.0 and max(rewards) <= 1.0
    assert env.unwrapped.physics.time() == pytest.approx(1000 * envs.TASKS[name].control_dt)
    with pytest.raises(ResetNeeded):
        env.step(actions[0])
    obs, _ = env.reset()
    assert env.step(actions[0])[3] is False


def test_step_before_reset_raises():
    env = envs.make("point_mass_maze_reach_top_left", seed=0)
    with pytest.raises(ResetNeeded):
        env.step(np.zeros(2, np.float32))


# ------------------------------------------------------------------------------------------------
# Determinism


def rollout(env, actions, seed=None):
    obs, _ = env.reset(seed=seed)
    observations, rewards = [obs], []
    for action in actions:
        obs, reward, _, _, _ = env.step(action)
        observations.append(obs)
        rewards.append(reward)
    return np.stack(observations), np.array(rewards)


@pytest.mark.parametrize("name", ONE_PER_DOMAIN)
def test_same_seed_and_actions_give_bit_identical_trajectories(name):
    actions = random_actions(120, envs.TASKS[name].action_dim, seed=4)
    env_a, env_b = envs.make(name, seed=123), envs.make(name, seed=123)
    obs_a, rew_a = rollout(env_a, actions)
    obs_b, rew_b = rollout(env_b, actions)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(rew_a, rew_b)
    # A second episode without reseeding continues both RNG streams identically ...
    obs_a2, _ = rollout(env_a, actions[:5])
    obs_b2, _ = rollout(env_b, actions[:5])
    np.testing.assert_array_equal(obs_a2, obs_b2)
    assert not np.array_equal(obs_a2[0], obs_a[0])
    # ... and reset(seed=...) on a used env reproduces a fresh env with that seed.
    obs_c, rew_c = rollout(env_a, actions, seed=123)
    np.testing.assert_array_equal(obs_c, obs_a)
    np.testing.assert_array_equal(rew_c, rew_a)
    other, _ = envs.make(name, seed=124).reset()
    assert not np.array_equal(other, obs_a[0])


STOCK_PAIRS = [("walker", "walk"), ("quadruped", "walk"), ("hopper", "hop"), ("cheetah", "run")]


@pytest.mark.parametrize("domain, task", STOCK_PAIRS)
def test_stock_tasks_match_dm_control_suite_with_urlb_action_scaling(domain, task):
    """Stock pairs equal suite.load + dm_control's action_scale wrapper, as URLB uses (§3)."""
    seed = 11
    env = envs.make(f"{domain}_{task}", seed=seed)
    reference = action_scale.Wrapper(
        suite.load(domain, task, task_kwargs={"random": seed}), minimum=-1.0, maximum=1.0
    )
    obs, _ = env.reset()
    time_step = reference.reset()
    for action in random_actions(60, env.action_space.shape[0], seed=5):
        obs, reward, *_ = env.step(action)
        time_step = reference.step(action)
        ref_obs = np.concatenate([np.ravel(v) for v in time_step.observation.values()])
        np.testing.assert_array_equal(obs, ref_obs.astype(np.float32))
        assert reward == time_step.reward


# ------------------------------------------------------------------------------------------------
# Action mapping (docs/tasks.md §3.5)


def test_quadruped_action_scaling_is_affine_and_not_clipped():
    env = envs.make("quadruped_walk", seed=0)
    env.reset()
    action = np.tile(np.array([1.5, 1.5, 1.5], np.float32), 4)
    action[3:6] = [-0.5, -2.0, 0.25]
    env.step(action)
    ctrl = env.unwrapped.physics.data.ctrl
    a = action.astype(np.float64)
    expected = a.copy()
    expected[1::3] = 1.05 * a[1::3] + 0.05  # lift
    expected[2::3] = 0.8 * a[2::3]  # extend
    np.testing.assert_allclose(ctrl, expected, rtol=0, atol=1e-12)
    assert ctrl[1] == pytest.approx(1.625) and ctrl[1] > 1.1  # beyond lift's ctrlrange: no clip


def test_other_domains_pass_actions_through_unchanged():
    env = envs.make("walker_walk", seed=0)
    env.reset()
    action = np.array([1.7, -1.3, 0.5, 0.0, -0.25, 1.0], np.float32)
    env.step(action)
    np.testing.assert_array_equal(env.unwrapped.physics.data.ctrl, action.astype(np.float64))


# ------------------------------------------------------------------------------------------------
# Reward formulas (docs/tasks.md §4), checked on hand-set states


def independent_subtree_angular_momentum(physics) -> np.ndarray:
    """Angular momentum of the whole robot about its CoM, summed body by body."""
    model, data = physics.model, physics.data
    bodies = range(1, model.nbody)
    masses = np.array([model.body_mass[b] for b in bodies])
    com = sum(masses[i] * data.xipos[b] for i, b in enumerate(bodies)) / masses.sum()
    velocities = []
    for b in bodies:
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(model.ptr, data.ptr, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)
        velocities.append(vel)
    com_vel = sum(masses[i] * velocities[i][3:] for i in range(len(masses))) / masses.sum()
    momentum = np.zeros(3)
    for i, b in enumerate(bodies):
        rotation = data.ximat[b].reshape(3, 3)
        inertia = rotation @ np.diag(model.body_inertia[b]) @ rotation.T
        momentum += masses[i] * np.cross(data.xipos[b] - com, velocities[i][3:] - com_vel)
        momentum += inertia @ velocities[i][:3]
    return momentum


WALKER_STATES = [
    # (qpos, qvel): upright & tall / crouched & tilted / spinning fast / spinning backwards
    ({}, {"rooty": 0.3}),
    ({"rootz": -0.5, "rooty": 0.7, "right_knee": -1.0}, {"rooty": 0.4, "left_hip": 2.0}),
    ({"rooty": 2.5}, {"rooty": 12.0, "rootx": 1.0}),
    ({"rootz": -0.2}, {"rooty": -4.0}),
]


@pytest.mark.parametrize("qpos, qvel", WALKER_STATES)
def test_walker_flip_reward_uses_subtree_angular_momentum(qpos, qvel):
    env = envs.make("walker_flip", seed=0)
    env.reset()
    physics = env.unwrapped.physics
    set_state(physics, qpos, qvel)
    momentum_y = physics.named.data.subtree_angmom["torso"][1]
    # The momentum MuJoCo reports is the spec's L_y: about the subtree CoM, world frame.
    np.testing.assert_allclose(
        physics.named.data.subtree_angmom["torso"],
        independent_subtree_angular_momentum(physics),
        rtol=1e-9,
        atol=1e-9,
    )
    height = physics.named.data.xpos["torso"][2]
    zz = physics.named.data.xmat["torso"][8]
    standing = 1.0 if height >= 1.2 else 0.1 ** (((1.2 - height) / 0.6) ** 2)
    stand_r = (3 * standing + (1 + zz) / 2) / 4
    expected = stand_r * (5 * clip01(momentum_y / 5) + 1) / 6
    assert task_reward(env) == pytest.approx(expected, rel=1e-12, abs=1e-12)


def test_walker_flip_states_cover_all_regimes():
    env = envs.make("walker_flip", seed=0)
    env.reset()
    physics = env.unwrapped.physics
    momenta = []
    for qpos, qvel in WALKER_STATES:
        set_state(physics, qpos, qvel)
        momenta.append(physics.named.data.subtree_angmom["torso"][1])
    assert any(0 < m < 5 for m in momenta)  # linear part
    assert any(m > 5 for m in momenta)  # saturated
    assert any(m < 0 for m in momenta)  # backwards: flip term 0


def hopper_standing(physics) -> float:
    height = physics.named.data.xipos["torso"][2] - physics.named.data.xipos["foot"][2]
    return 1.0 if 0.6 <= height <= 2.0 else 0.0


@pytest.mark.parametrize("root_vx", [-5.0, -1.0, -0.3, 0.0, 1.5])
def test_hopper_hop_backward_reward(root_vx):
    env = envs.make("hopper_hop_backward", seed=0)
    env.reset()
    physics = env.unwrapped.physics
    set_state(physics, {"knee": 0.3}, {"rootx": root_vx, "waist": 0.5})
    assert hopper_standing(physics) == 1.0
    v_x = physics.named.data.subtree_linvel["torso"][0]
    assert task_reward(env) == pytest.approx(clip01(-v_x / 2), abs=1e-12)
    # Lying down: the standing factor is 0.
    set_state(physics, {"rooty": math.pi / 2, "rootz": -0.9}, {"rootx": root_vx})
    assert hopper_standing(physics) == 0.0
    assert task_reward(env) == 0.0


@pytest.mark.parametrize("spin", [-30.0, -4.0, -1.0, 2.0, 25.0])
def test_hopper_flip_and_flip_backward_rewards(spin):
    forward, backward = envs.make("hopper_flip", seed=0), envs.make("hopper_flip_backward", seed=0)
    for env in (forward, backward):
        env.reset()
        set_state(env.unwrapped.physics, {"hip": -0.3}, {"rooty": spin, "ankle": 1.0})
    physics = backward.unwrapped.physics
    momentum_y = physics.named.data.subtree_angmom["torso"][1]
    standing = hopper_standing(physics)
    assert standing == 1.0
    assert np.sign(momentum_y) == np.sign(spin)
    assert task_reward(backward) == pytest.approx(standing * clip01(-momentum_y / 5), abs=1e-12)
    assert task_reward(forward) == pytest.approx(standing * clip01(momentum_y / 5), abs=1e-12)


def quaternion_about_x(angle: float) -> list[float]:
    return [math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]


@pytest.mark.parametrize(
    "height, tilt", [(0.4, 0.0), (0.9, 0.0), (1.6, 0.0), (3.0, 0.0), (1.2, math.pi / 3), (2.0, 2.5)]
)
def test_quadruped_jump_and_stand_rewards(height, tilt):
    jump, stand = envs.make("quadruped_jump", seed=0), envs.make("quadruped_stand", seed=0)
    for env in (jump, stand):
        env.reset()
        set_state(env.unwrapped.physics, {"root": [0.3, -0.2, height, *quaternion_about_x(tilt)]})
    physics = jump.unwrapped.physics
    masses = physics.model.body_mass[1:]
    com_z = float(masses @ physics.data.xipos[1:, 2] / masses.sum())  # whole-body CoM height
    zz = physics.named.data.xmat["torso"][8]
    assert zz == pytest.approx(math.cos(tilt))
    upright = (1 + zz) / 2
    assert task_reward(jump) == pytest.approx(upright * clip01(0.5 + com_z / 2), abs=1e-12)
    assert task_reward(stand) == pytest.approx(upright, abs=1e-12)


@pytest.mark.parametrize("root_vx", [-25.0, -6.0, -1.0, 0.5, 4.0, 12.0])
def test_cheetah_rewards_forward_and_backward(root_vx):
    names = ["cheetah_run", "cheetah_run_backward", "cheetah_walk", "cheetah_walk_backward"]
    scales = {"cheetah_run": (10, 1), "cheetah_run_backward": (10, -1)}
    scales.update({"cheetah_walk": (2, 1), "cheetah_walk_backward": (2, -1)})
    for name in names:
        env = envs.make(name, seed=0)
        env.reset()
        physics = env.unwrapped.physics
        set_state(physics, {"bthigh": 0.2}, {"rootx": root_vx, "fshin": -1.0})
        v_x = physics.named.data.subtree_linvel["torso"][0]
        speed, sign = scales[name]
        assert task_reward(env) == pytest.approx(clip01(sign * v_x / speed), abs=1e-12), name


def maze_reward_by_hand(xy, target, control) -> float:
    dist = math.dist(xy, target)
    near = 1.0 if dist <= 0.015 else 0.1 ** (((dist - 0.015) / 0.015) ** 2)
    per_actuator = [max(0.0, 1.0 - u * u) for u in control]  # tol(u; [0,0], m=1, quadratic, 0)
    small_control = (sum(per_actuator) / len(per_actuator) + 4) / 5
    return near * small_control


@pytest.mark.parametrize("task", list(MAZE_TARGETS))
def test_maze_reward_distance_and_small_control(task):
    env = envs.make(f"point_mass_maze_{task}", seed=0)
    env.reset()
    physics = env.unwrapped.physics
    target = MAZE_TARGETS[task]
    offsets = [(0.0, 0.0), (0.01, 0.0), (0.0, -0.02), (0.015, 0.02), (0.1, 0.1)]
    controls = [(0.0, 0.0), (0.5, -0.3), (1.0, 0.2), (-1.4, 0.0)]
    for dx, dy in offsets:
        for control in controls:
            xy = (target[0] + dx, target[1] + dy)
            set_state(physics, {"root_x": xy[0], "root_y": xy[1]})
            physics.data.ctrl[:] = control  # the raw applied control, unclamped
            expected = maze_reward_by_hand(xy, target, control)
            assert task_reward(env) == pytest.approx(expected, rel=1e-12, abs=1e-300)


def test_maze_step_reward_uses_the_raw_unclipped_control():
    env = envs.make("point_mass_maze_reach_top_left", seed=0)
    env.reset()
    physics = env.unwrapped.physics
    set_state(physics, {"root_x": -0.15, "root_y": 0.152})
    action = np.array([1.5, -0.5], np.float32)
    _, reward, _, _, _ = env.step(action)
    np.testing.assert_array_equal(physics.data.ctrl, [1.5, -0.5])
    xy = (physics.named.data.qpos["root_x"][0], physics.named.data.qpos["root_y"][0])
    expected = maze_reward_by_hand(xy, (-0.15, 0.15), (1.5, -0.5))
    assert reward == pytest.approx(expected, rel=1e-12)
    assert reward == pytest.approx((0.5 * 0.75 + 4) / 5)  # near = 1, |u_x| > 1 contributes 0


# ------------------------------------------------------------------------------------------------
# Maze layout and start state (docs/tasks.md §4.5, §6)


def push_mass(env, start_xy, action, steps=300) -> np.ndarray:
    env.reset()
    set_state(env.unwrapped.physics, {"root_x": start_xy[0], "root_y": start_xy[1]})
    action = np.asarray(action, np.float32)
    for _ in range(steps):
        obs, *_ = env.step(action)
    return obs


def test_maze_walls_block_and_gaps_connect_rooms():
    env = envs.make("point_mass_maze_reach_top_left", seed=0)
    # Pushing +x at y = 0.10 stops at the interior wall face (-0.02) minus the radius (0.01).
    assert push_mass(env, (-0.2, 0.10), [1, 0])[0] == pytest.approx(-0.03, abs=2e-3)
    # At y = 0.25 the mass passes through the gap to the joint limit.
    assert push_mass(env, (-0.2, 0.25), [1, 0])[0] == pytest.approx(0.29, abs=2e-3)
    # The other wall arm blocks -y motion from the top-right room.
    assert push_mass(env, (0.1, 0.2), [0, -1])[1] == pytest.approx(0.03, abs=2e-3)
    physics = env.unwrapped.physics
    assert not physics.model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT


@pytest.mark.parametrize("task", list(MAZE_TARGETS))
def test_maze_target_is_placed_and_non_colliding(task):
    physics = envs.make(f"point_mass_maze_{task}", seed=0).unwrapped.physics
    np.testing.assert_allclose(
        physics.named.model.geom_pos["target"], [*MAZE_TARGETS[task], 0.01], atol=1e-12
    )
    assert physics.named.model.geom_contype["target"] == 0
    assert physics.named.model.geom_conaffinity["target"] == 0


def test_maze_start_is_in_top_left_room_and_reproducible():
    env = envs.make("point_mass_maze_reach_bottom_right", seed=0)
    starts = []
    for seed in range(25):
        obs, _ = env.reset(seed=seed)
        x, y, vx, vy = obs
        assert -0.29 <= x < -0.15 and 0.15 <= y < 0.29
        assert vx == 0.0 and vy == 0.0
        starts.append(obs)
        np.testing.assert_array_equal(env.reset(seed=seed)[0], obs)
    assert len({tuple(s) for s in starts}) == 25
    # Unseeded resets keep drawing new starts in the same room.
    for _ in range(10):
        x, y, _, _ = env.reset()[0]
        assert -0.29 <= x < -0.15 and 0.15 <= y < 0.29


def test_maze_start_rng_is_seeded_and_independent_of_global_numpy_rng():
    np.random.seed(1)
    first = envs.make("point_mass_maze_reach_top_left", seed=7).reset()[0]
    np.random.seed(2)
    np.random.uniform(size=10)
    second = envs.make("point_mass_maze_reach_top_left", seed=7).reset()[0]
    np.testing.assert_array_equal(first, second)
    # Stream parity (docs/tasks.md §4.5): the task RNG made the stock randomiser's two draws, and the
    # start came from a RandomState(seed), as after the authors' np.random.seed(seed).
    env = envs.make("point_mass_maze_reach_top_left", seed=7)
    obs, _ = env.reset()
    reference_task_rng = np.random.RandomState(7)
    reference_task_rng.uniform(-0.29, 0.29, size=2)
    task = env.unwrapped.dmc_env.task
    assert task.random.uniform() == reference_task_rng.uniform()
    start_rng = np.random.RandomState(7)
    expected_xy = [start_rng.uniform(-0.29, -0.15), start_rng.uniform(0.15, 0.29)]
    np.testing.assert_array_equal(obs[:2], np.float32(expected_xy))


# ------------------------------------------------------------------------------------------------
# Reward-free mode and gymnasium integration


def test_reward_free_returns_zero_and_reports_task_reward():
    actions = random_actions(80, 6, seed=6)
    normal = envs.make("walker_walk", seed=3)
    free = envs.make("walker", seed=3, reward_free=True)
    assert free.unwrapped.reward_free and free.unwrapped.task_spec.name == "walker_walk"
    normal.reset()
    free.reset()
    task_rewards = []
    for action in actions:
        _, reward, _, _, info = normal.step(action)
        _, free_reward, _, _, free_info = free.step(action)
        assert free_reward == 0.0
        assert free_info["task_reward"] == info["task_reward"] == reward
        task_rewards.append(free_info["task_reward"])
    assert max(task_rewards) > 0.0


def test_gymnasium_make_works_without_extra_time_limit():
    for name in ALL_TASKS + METAWORLD_TASKS:
        assert f"dvfb/{name}" in gymnasium.registry
    env = gymnasium.make("dvfb/walker_walk", seed=5)
    assert env.unwrapped.physics is env.unwrapped.dmc_env.physics
    assert type(env.unwrapped.physics).__module__ == "dm_control.suite.walker"
    wrapper = env
    while isinstance(wrapper, gymnasium.Wrapper):
        assert not isinstance(wrapper, gymnasium.wrappers.TimeLimit)
        wrapper = wrapper.env
    actions = random_actions(30, 6, seed=8)
    obs_gym, rew_gym = rollout(env, actions)
    obs_ref, rew_ref = rollout(envs.make("walker_walk", seed=5), actions)
    np.testing.assert_array_equal(obs_gym, obs_ref)
    np.testing.assert_array_equal(rew_gym, rew_ref)

    maze = gymnasium.make("dvfb/point_mass_maze_reach_top_left", seed=0, reward_free=True)
    maze.reset()
    for step in range(1, 1001):
        _, reward, terminated, truncated, info = maze.step(np.zeros(2, np.float32))
        assert reward == 0.0 and "task_reward" in info
        assert terminated is False and truncated is (step == 1000)


# ------------------------------------------------------------------------------------------------
# Headless import (MUJOCO_GL default)


def _run_isolated(code: str, **env_overrides) -> subprocess.CompletedProcess:
    dropped = ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM")
    env = {k: v for k, v in os.environ.items() if k not in dropped}
    env.update(env_overrides)
    return subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )


SMOKE = (
    "import os, dvfb.envs as e; env = e.make('point_mass_maze_reach_top_left', seed=0); "
    "env.reset(); env.step(env.action_space.sample()); print(os.environ['MUJOCO_GL'])"
)


def test_headless_import_is_quiet_and_sets_a_backend():
    result = _run_isolated(SMOKE)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() in ("egl", "disable")
    assert "GLFW" not in result.stderr and "DISPLAY" not in result.stderr, result.stderr


def test_user_mujoco_gl_is_respected():
    result = _run_isolated(SMOKE, MUJOCO_GL="disable")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "disable"
