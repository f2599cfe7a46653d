"""Meta-World faucet-open / faucet-close (docs/tasks.md §4.6, §7) on real MuJoCo physics.

These tests need the optional extra (``pip install -e '.[metaworld]'``), which ``make test``
installs: without it they fail at the import below, loudly, instead of being skipped. Reward and
observation checks compare with values computed here from MuJoCo's state arrays and the spec's
formulas, not with dvfb's or Meta-World's own helpers.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import dvfb.envs as envs  # isort: skip  (headless MUJOCO_GL default first)

import gymnasium
import metaworld
import mujoco
import numpy as np
import pytest
from dm_control.utils import rewards as dm_rewards
from gymnasium.error import ResetNeeded
from metaworld.policies import SawyerFaucetCloseV3Policy, SawyerFaucetOpenV3Policy

from dvfb.core.errors import ConfigError

TASKS = ["metaworld_faucet_open", "metaworld_faucet_close"]
# docs/tasks.md §4.6, written out independently of the package.
EPISODE = 250
BASE_X = {"metaworld_faucet_open": 0.05, "metaworld_faucet_close": 0.10}  # |x| bound of the faucet base
TARGET_OFFSET = {"metaworld_faucet_open": (0.175, 0.0, 0.125), "metaworld_faucet_close": (-0.175, 0.0, 0.125)}
OBJ_OFFSET = {"metaworld_faucet_open": (-0.04, 0.0, 0.03), "metaworld_faucet_close": (0.0, 0.0, 0.0)}
HANDLE_SITE = {"metaworld_faucet_open": "handleStartOpen", "metaworld_faucet_close": "handleStartClose"}
TARGET_RADIUS = 0.07
EXPERTS = {"metaworld_faucet_open": SawyerFaucetOpenV3Policy, "metaworld_faucet_close": SawyerFaucetCloseV3Policy}
REPO = Path(__file__).resolve().parents[1]


def random_actions(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, 4)).astype(np.float32)


def base_position(env) -> np.ndarray:
    mw = env.unwrapped.mw_env
    return mw.model.body("faucetBase").pos.copy()


def tcp(env) -> np.ndarray:
    data = env.unwrapped.mw_env.data
    return (data.site("rightEndEffector").xpos + data.site("leftEndEffector").xpos) / 2.0


# ------------------------------------------------------------------------------------------------
# Building, stepping, truncation


@pytest.mark.parametrize("name", TASKS)
def test_task_builds_steps_and_truncates_at_250(name):
    env = envs.make(name, seed=1)
    spec = envs.TASKS[name]
    assert (spec.domain, spec.obs_dim, spec.action_dim, spec.episode_length) == ("metaworld", 39, 4, EPISODE)
    assert env.observation_space.shape == (39,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (4,) and env.action_space.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)
    mw = env.unwrapped.mw_env
    assert mw.frame_skip == 5 and mw.model.opt.timestep == pytest.approx(0.0025)
    assert spec.control_dt == pytest.approx(mw.frame_skip * mw.model.opt.timestep)
    assert mw.reward_function_version == "v2"

    obs, info = env.reset()
    assert obs.dtype == np.float32 and obs.shape == (39,) and info == {}
    actions = random_actions(EPISODE + 1, seed=2)
    for step, action in enumerate(actions[:EPISODE], start=1):
        obs, reward, terminated, truncated, info = env.step(action)
        assert obs.dtype == np.float32 and np.all(np.isfinite(obs))
        assert type(reward) is float and 0.0 <= reward <= 10.0
        assert info["task_reward"] == reward and type(info["success"]) is bool
        assert terminated is False
        assert truncated is (step == EPISODE), f"truncated={truncated} at step {step}"
    with pytest.raises(ResetNeeded):
        env.step(actions[-1])
    env.reset()
    assert env.step(actions[0])[3] is False


def test_pretraining_env_is_faucet_open_and_reward_free():
    env = envs.make("metaworld", seed=0, reward_free=True)
    assert env.unwrapped.task_spec.name == "metaworld_faucet_open" == envs.pretrain_task("metaworld")
    with pytest.raises(ConfigError, match="metaworld_faucet_open"):
        envs.make("metaworld")  # a reward-using run must name its task
    env.reset()
    task_rewards = []
    for action in random_actions(50, seed=3):
        _, reward, _, _, info = env.step(action)
        assert reward == 0.0
        task_rewards.append(info["task_reward"])
    assert max(task_rewards) > 0.0


def test_gymnasium_registration_matches_make():
    env = gymnasium.make("dvfb/metaworld_faucet_close", seed=4)
    wrapper = env
    while isinstance(wrapper, gymnasium.Wrapper):
        assert not isinstance(wrapper, gymnasium.wrappers.TimeLimit)
        wrapper = wrapper.env
    reference = envs.make("metaworld_faucet_close", seed=4, render_mode="rgb_array")
    np.testing.assert_array_equal(env.reset()[0], reference.reset()[0])
    frame = reference.render()  # the authors' corner view, the right way up
    assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8 and frame.std() > 0
    for action in random_actions(20, seed=5):
        a, b = env.step(action), reference.step(action)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1] == b[1]


# ------------------------------------------------------------------------------------------------
# ML1 test tasks, switched at every reset


@pytest.mark.parametrize("name", TASKS)
@pytest.mark.slow
def test_each_reset_switches_to_an_ml1_test_task(name):
    seed = 7
    env = envs.make(name, seed=seed)
    mw_name = {"metaworld_faucet_open": "faucet-open-v3", "metaworld_faucet_close": "faucet-close-v3"}[name]
    benchmark = metaworld.ML1(mw_name, seed=seed)
    import pickle

    test_positions = np.array([pickle.loads(t.data)["rand_vec"] for t in benchmark.test_tasks])
    train_positions = np.array([pickle.loads(t.data)["rand_vec"] for t in benchmark.train_tasks])
    assert test_positions.shape == (50, 3)
    seen = []
    for _ in range(30):
        obs, _ = env.reset()
        base = base_position(env)
        seen.append(tuple(base))
        # The base is one of ML1's 50 test positions (never a train-only one), inside the spec's range.
        assert np.min(np.abs(test_positions - base).max(axis=1)) == 0.0
        assert np.min(np.abs(train_positions - base).max(axis=1)) > 0.0
        assert abs(base[0]) <= BASE_X[name] and 0.8 <= base[1] <= 0.85 and base[2] == 0.0
        # ML1 is partially observable: the goal coordinates are zero.
        np.testing.assert_array_equal(obs[36:39], 0.0)
    assert len(set(seen)) > 10  # tasks switch (30 draws from 50)
    # Same seed, same sequence of tasks; reset(seed=s) reproduces an env made with seed s.
    again = envs.make(name, seed=seed)
    replay = []
    for _ in range(30):
        again.reset()
        replay.append(tuple(base_position(again)))
    assert replay == seen
    other = envs.make(name, seed=0)
    first, _ = other.reset(seed=seed)
    assert tuple(base_position(other)) == seen[0]


# ------------------------------------------------------------------------------------------------
# Observation layout


@pytest.mark.parametrize("name", TASKS)
def test_observation_layout(name):
    env = envs.make(name, seed=3)
    obs, _ = env.reset()
    np.testing.assert_array_equal(obs[18:36], obs[0:18])  # at reset the previous frame is the current one
    data = env.unwrapped.mw_env.data
    previous = obs
    for action in random_actions(30, seed=6):
        obs, *_ = env.step(action)
        hand = data.body("hand").xpos
        gripper = np.clip(np.linalg.norm(data.body("rightclaw").xpos - data.body("leftclaw").xpos) / 0.1, 0, 1)
        handle = data.site(HANDLE_SITE[name]).xpos - np.array([0.0, 0.0, 0.01])
        quaternion = data.body("faucetBase").xquat
        current = np.concatenate([hand, [gripper], handle, quaternion, np.zeros(7)]).astype(np.float32)
        np.testing.assert_allclose(obs[0:18], current, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(obs[11:18], 0.0)  # padding for a second object
        np.testing.assert_array_equal(obs[18:36], previous[0:18])  # the previous frame
        np.testing.assert_array_equal(obs[36:39], 0.0)  # the zeroed goal
        previous = obs
    # The two tasks observe different handle sites, 3 cm apart on the handle.
    distance = np.linalg.norm(data.site("handleStartOpen").xpos - data.site("handleStartClose").xpos)
    assert distance == pytest.approx(0.03, abs=1e-3)


# ------------------------------------------------------------------------------------------------
# The v2 reward and success, against a hand computation from set states


def hand_reward(name: str, handle: np.ndarray, tcp_now: np.ndarray, base: np.ndarray, tcp_init: np.ndarray):
    """The v2 reward and success of docs/tasks.md §4.6 from the observed handle position (float64)."""
    obj = handle + np.array(OBJ_OFFSET[name])
    target = base + np.array(TARGET_OFFSET[name])
    d = np.linalg.norm(obj - target)
    d0 = np.linalg.norm(base - target)
    in_place = dm_rewards.tolerance(d, bounds=(0, TARGET_RADIUS), margin=abs(d0 - TARGET_RADIUS),
                                    sigmoid="long_tail", value_at_margin=0.1)
    reach = dm_rewards.tolerance(np.linalg.norm(obj - tcp_now), bounds=(0, 0.01),
                                 margin=abs(np.linalg.norm(base - tcp_init) - 0.01), sigmoid="gaussian",
                                 value_at_margin=0.1)
    reward = 10.0 if d <= TARGET_RADIUS else 2.0 * (2.0 * reach + 3.0 * in_place)
    return reward, bool(d <= TARGET_RADIUS)


@pytest.mark.parametrize("name", TASKS)
def test_reward_and_success_match_a_hand_computation(name):
    env = envs.make(name, seed=11)
    mw = env.unwrapped.mw_env
    joint = mw.model.joint("knob_Joint_1")
    address = mw.model.jnt_qposadr[joint.id]
    regimes = set()
    for episode, angle in enumerate(np.linspace(-1.5, 1.5, 13)):
        env.reset()
        # tcp_init is the gripper centre Meta-World recorded when the hand settled during the reset
        # (before the faucet was placed, so MuJoCo's positions may have been refreshed since).
        base, tcp_init = base_position(env), mw.init_tcp.copy()
        # Open places the faucet without refreshing positions; close refreshes them (docs/tasks.md §4.6).
        drift = np.linalg.norm(tcp(env) - tcp_init)
        assert drift == 0.0 if name == "metaworld_faucet_open" else drift < 1e-4
        # Set the handle's angle (and move the hand a little), then take one step with no hand motion.
        mw.data.qpos[address] = angle
        mw.data.qvel[:] = 0.0
        mujoco.mj_forward(mw.model, mw.data)
        action = np.array([0.0, 0.3 * (episode % 3 - 1), 0.0, 0.0], dtype=np.float32)
        obs, reward, _, _, info = env.step(action)
        handle = mw.data.site(HANDLE_SITE[name]).xpos - np.array([0.0, 0.0, 0.01])
        np.testing.assert_allclose(obs[4:7], handle, rtol=0, atol=1e-6)  # what the reward reads
        expected, success = hand_reward(name, handle, tcp(env), base, tcp_init)
        assert reward == pytest.approx(expected, rel=1e-9, abs=1e-9), f"angle {angle}"
        assert info["success"] is success
        regimes.add(success)
    assert regimes == {True, False}  # both branches of the reward were exercised


@pytest.mark.parametrize("name", TASKS)
def test_scripted_expert_reaches_success(name):
    env = envs.make(name, seed=0)
    expert = EXPERTS[name]()
    for _ in range(3):
        obs, _ = env.reset()
        reached, done = False, False
        while not done:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "constants may be too high": it clips
                action = np.clip(expert.get_action(obs.astype(np.float64)), -1, 1).astype(np.float32)
            obs, _, _, done, info = env.step(action)
            reached |= info["success"]
        assert reached, f"the expert never succeeded on task {env.unwrapped.task_index}"


# ------------------------------------------------------------------------------------------------
# Exact resume


def test_mid_episode_state_restores_the_episode_bit_for_bit():
    env = envs.make("metaworld_faucet_close", seed=5)
    actions = random_actions(EPISODE, seed=9)
    env.reset()
    env.reset()  # a second task draw, so the RNG stream has moved
    for action in actions[:120]:
        env.step(action)
    state = json.loads(json.dumps(env.unwrapped.get_episode_state()))  # as written in a checkpoint
    reference = [env.step(action) for action in actions[120:]]
    next_reference = env.reset()[0]

    restored = envs.make("metaworld_faucet_close", seed=99)
    restored.unwrapped.set_episode_state(state)
    replay = [restored.step(action) for action in actions[120:]]
    for a, b in zip(reference, replay, strict=True):
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1:4] == b[1:4] and a[4] == b[4]
    np.testing.assert_array_equal(restored.reset()[0], next_reference)


# ------------------------------------------------------------------------------------------------
# The extra does not change DMC physics; without it, the names say how to install it


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          cwd=REPO, env={**os.environ, "PYTHONWARNINGS": "ignore"})


DMC_ROLLOUT = (
    "import numpy as np, dvfb.envs as e\n"
    "{prelude}\n"
    "env = e.make('walker_flip', seed=3); env.reset(); out = []\n"
    "for a in np.random.default_rng(0).uniform(-1, 1, (300, 6)).astype(np.float32):\n"
    "    o, r, *_ = env.step(a); out.append(np.append(o, r))\n"
    "print(np.asarray(out).tobytes().hex())\n"
)


def test_meta_world_does_not_change_dmc_physics():
    plain = _python(DMC_ROLLOUT.format(prelude="import sys; assert 'metaworld' not in sys.modules"))
    with_mw = _python(DMC_ROLLOUT.format(
        prelude="e.make('metaworld_faucet_open', seed=0).reset(); import sys; assert 'metaworld' in sys.modules"))
    assert plain.returncode == 0, plain.stderr
    assert with_mw.returncode == 0, with_mw.stderr
    assert plain.stdout == with_mw.stdout and len(plain.stdout) > 1000


WITHOUT_EXTRA = "import sys; sys.modules['metaworld'] = None  # as if the extra were not installed\n"


def test_without_the_extra_the_tasks_are_listed_as_unavailable(tmp_path):
    run_dir = tmp_path / "run"
    result = _python(WITHOUT_EXTRA + (
        "from dvfb import envs\n"
        "from dvfb.core.errors import ConfigError\n"
        "print(envs.format_task_table())\n"
        "try:\n"
        "    envs.make('metaworld_faucet_close', seed=0)\n"
        "except ConfigError as exc:\n"
        "    print('ERROR', exc)\n"
        "e = envs.make('walker_walk', seed=0); e.reset(); e.step(e.action_space.sample())\n"
        "from dvfb.sweep.spec import SweepConfig, check\n"
        "try:\n"
        "    check(SweepConfig(agents=['fb'], domains=['walker', 'metaworld'], seeds=[0]))\n"
        "except ConfigError as exc:\n"
        "    print('SWEEP', exc)\n"
        "from dvfb.cli import main\n"
        f"sys.exit(main(['pretrain', '--agent', 'fb', '--domain', 'metaworld', '--preset', 'small', "
        f"'--frames', '10000', '--run-dir', {str(run_dir)!r}]))\n"))
    assert result.returncode != 0
    lines = result.stdout.splitlines()
    assert any(line.startswith("| metaworld_faucet_open * (unavailable)") for line in lines)
    assert any(line.startswith("| metaworld_faucet_close (unavailable)") for line in lines)
    assert any("unavailable:" in line and "pip install -e '.[metaworld]'" in line for line in lines)
    error = [line for line in lines if line.startswith("ERROR")]
    assert len(error) == 1 and "pip install -e '.[metaworld]'" in error[0]
    sweep = [line for line in lines if line.startswith("SWEEP")]  # refused before any cell starts
    assert len(sweep) == 1 and "pip install -e '.[metaworld]'" in sweep[0]
    # The CLI: one line naming the problem and the install command, nothing created.
    stderr = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(stderr) == 1 and "metaworld" in stderr[0] and "pip install" in stderr[0], result.stderr
    assert not run_dir.exists()


def test_with_the_extra_the_task_table_marks_nothing_unavailable():
    assert "unavailable" not in envs.format_task_table()
    assert envs.missing_extra("metaworld") is None


# ------------------------------------------------------------------------------------------------
# pre-train -> zero-shot -> fine-tune -> report, through the command line, with tiny budgets

TINY = ["--fb.z-dim", "16", "--fb.hidden-dim", "32", "--fb.feature-dim", "16", "--fb.backward-hidden-dim", "32",
        "--fb.batch-size", "64", "--log-every", "250", "--seed-frames", "250", "--update-every", "4",
        "--checkpoint-every", "750", "--no-progress"]
TINY_EXPLORATION = ["--exploration.contrastive-hidden-dim", "32", "--exploration.rnd-rep-dim", "16",
                    "--exploration.ce-k", "4"]
FAST_INFERENCE = ["--inference.steps", "300", "--inference.random-action-steps", "100",
                  "--inference.samples", "300", "--inference.eval-episodes", "2"]


@pytest.mark.slow
@pytest.mark.e2e
def test_pretrain_zeroshot_finetune_and_report_record_success_rates(tmp_path, capsys):
    from dvfb.cli import main

    runs = tmp_path / "runs"
    for agent in ("dvfb", "fb"):
        run = runs / f"{agent}_metaworld_s0"
        assert main(["pretrain", "--agent", agent, "--domain", "metaworld", "--frames", "750", "--run-dir",
                     str(run), *TINY, *(TINY_EXPLORATION if agent == "dvfb" else ())]) == 0
        summary = json.loads((run / "pretrain_summary.json").read_text())
        assert summary["frames"] == 750 and summary["episodes"] == 3  # 250-step episodes
        assert main(["zeroshot", str(run), "--task", "all", *FAST_INFERENCE]) == 0
        out = capsys.readouterr().out
        assert "success" in out and "metaworld_faucet_close" in out
        for task in TASKS:
            result = json.loads((run / "zeroshot" / f"{task}.json").read_text())
            assert result["eval_episodes"] == 2 and len(result["successes"]) == 2
            assert all(type(s) is bool for s in result["successes"])
            assert result["success_rate"] == np.mean(result["successes"])
            assert 0.0 <= result["mean_return"] <= 10.0 * EPISODE
    # Fine-tuning evaluations carry success rates too.
    run = runs / "fb_metaworld_s0"
    assert main(["finetune", str(run), "--task", "metaworld_faucet_close", *FAST_INFERENCE, "--finetune.frames",
                 "500", "--finetune.seed-frames", "250", "--finetune.eval-every", "250", "--finetune.eval-episodes",
                 "1", "--finetune.checkpoint-every", "500", "--no-progress"]) == 0
    curve = json.loads((run / "finetune" / "metaworld_faucet_close" / "curve.json").read_text())["curve"]
    assert [p["frames"] for p in curve] == [0, 250, 500]
    assert all(p["success_rate"] in (0.0, 1.0) and len(p["successes"]) == 1 for p in curve)
    summary = json.loads((run / "finetune" / "metaworld_faucet_close" / "finetune_summary.json").read_text())
    assert summary["final_success_rate"] == curve[-1]["success_rate"]
    # The random policy's floor, and the report's Table 6.
    random_file = tmp_path / "random_metaworld.json"
    assert main(["random-policy", "--domain", "metaworld", "--episodes", "2", "--output", str(random_file)]) == 0
    random_result = json.loads(random_file.read_text())["tasks"]
    assert set(random_result) == set(TASKS) and all("success_rate" in r for r in random_result.values())
    report_dir = tmp_path / "report"
    assert main(["report", str(runs), "--out", str(report_dir), "--random", str(random_file)]) == 0
    table6 = (report_dir / "table6_success.md").read_text()
    assert "Table 6: zero-shot success rate" in table6 and "after fine-tuning" in table6
    rows = [line for line in table6.splitlines() if line.startswith("| metaworld |")]
    assert len(rows) == 3 + 3  # each table: 2 tasks + average (a task without a run is a gap)
    zero_shot = {line.split("|")[2].strip(): line for line in rows[:3]}
    dvfb_open = json.loads((runs / "dvfb_metaworld_s0" / "zeroshot" / "metaworld_faucet_open.json").read_text())
    assert f"{dvfb_open['success_rate']:.2f}" == zero_shot["metaworld_faucet_open"].split("|")[3].strip()
    csv_lines = (report_dir / "table6_success_zeroshot.csv").read_text().splitlines()
    assert csv_lines[0].startswith("domain,task,dvfb_mean") and len(csv_lines) == 4
    assert "Table 6" in (report_dir / "report.md").read_text()
    # Returns still make Table 1 (Meta-World rows), and DMC-only reports get no Table 6 (tests/test_analysis.py).
    assert "metaworld_faucet_open" in (report_dir / "table1_zeroshot.md").read_text()
    # The analyses that render or read positions work on the faucet too.
    import imageio.v3 as iio

    dvfb_run = runs / "dvfb_metaworld_s0"
    gif = tmp_path / "faucet.gif"
    assert main(["video", str(dvfb_run), "--task", "metaworld_faucet_open", "--max-steps", "8", "--frame-skip", "4",
                 "--height", "48", "--width", "64", "--out", str(gif)]) == 0
    frames = iio.imread(gif)
    assert frames.shape == (3, 48, 64, 3) and frames.std() > 0
    assert main(["analyze-exploration", str(dvfb_run), "--skills", "2", "--repeats", "1"]) == 0
    exploration = json.loads((dvfb_run / "analysis" / "exploration.json").read_text())
    assert exploration["coordinates"] == ["hand_x", "hand_y"] and exploration["coverage_cells"] >= 1
    assert exploration["steps"] == EPISODE  # by default one whole episode
