"""Datasets made from dvfb's own runs (docs/methods.md, "Datasets"): the replay's float64 physics
column, recording physics in pre-training, export -> read round trip, exact relabelling against the
online environments of every domain, damaged files and bad input. Real MuJoCo physics, real files."""

from __future__ import annotations

import json
import os
import subprocess
import shutil
from pathlib import Path

import dvfb.envs as envs  # isort: skip  (headless MUJOCO_GL default first)

import numpy as np
import pytest
import torch

from dvfb.cli import main
from dvfb.envs._common import set_mujoco_state
from dvfb.data.datasets import DatasetInfo, load_episode, read_dataset, read_info, relabel, write_dataset
from dvfb.workflows.dataset_export import export_run
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.data import Column, ReplayBuffer
from dvfb.runs import load_checkpoint
from tiny import tiny_flags

MAZE = "point_mass_maze_reach_top_left"
TINY = [*tiny_flags("fb"), "--log-every", "250", "--torch-threads", "1"]


def pretrain(run: Path, frames: int, *extra: str) -> None:
    args = ["pretrain", "--agent", "fb", "--domain", "point_mass_maze", "--seed-frames", "500", "--update-every", "4",
            "--checkpoint-every", "1000", "--replay-capacity", "2000", "--frames", str(frames), "--run-dir", str(run),
            "--no-progress", *TINY, *extra]
    assert main(args) == 0


def run_replay(run: Path) -> ReplayBuffer:
    """The pre-training replay in the run's final checkpoint."""
    state = load_checkpoint(run)["replay"]
    replay = ReplayBuffer(2000, 4, 2, 8, 1000, columns=state["columns"])
    replay.load_state_dict(state)
    return replay


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """An FB run on the maze that records physics: 1500 frames (its final checkpoint is mid-episode),
    exported then (one finished episode), then resumed to 2000 frames (two)."""
    path = tmp_path_factory.mktemp("runs") / "fb_maze"
    pretrain(path, 1500, "--replay.record-physics", "true")
    state = load_checkpoint(path)
    assert state["step"] == 1500 and "episode_state" in state  # the checkpoint that recording adds
    assert export_run(path, path / "dataset_1500", progress=None).files == ["episode_000000_1000.npz"]
    pretrain(path, 2000, "--replay.record-physics", "true", "--resume")
    return path


@pytest.fixture(scope="module")
def dataset(run: Path) -> Path:
    info = export_run(run, progress=None)
    assert info.files == ["episode_000000_1000.npz", "episode_000001_1000.npz"]
    return run / "dataset"


def test_float64_columns_with_the_observation_are_stored_sampled_saved_and_counted():
    """A float64 column that goes with the observation: row 0 from start_episode, next_obs's from
    add; batches carry it and next_<name> exactly (float64); states round trip; add_episode is the
    same as the steps one by one; the staged (accelerator) path too."""
    columns = {"physics": Column(3, "float64", "obs"), "extra": 2}
    assert ReplayBuffer.estimate_nbytes(50, 2, 1, 0, 10, columns=columns) == (
        6 * 11 * ((5 + 2) * 4 + 3 * 8) + 6 * 8)  # 6 slots of 11 rows: float32 obs..discount + extra, float64 physics
    values = 1 / 3 + np.arange(6, dtype=np.float64)  # not representable in float32
    for staged in (False, True):
        one = ReplayBuffer(50, 2, 1, max_episode_length=10, columns=columns, stage_on_host=staged)
        assert one.nbytes == ReplayBuffer.estimate_nbytes(50, 2, 1, 0, 10, columns=columns)
        one.start_episode(np.zeros(2, np.float32), physics=np.full(3, values[0]))
        for t in range(5):
            one.add(np.full(1, t, np.float32), float(t), 1.0, np.full(2, t + 1, np.float32),
                    physics=np.full(3, values[t + 1]), extra=np.full(2, 7 * t, np.float32))
        batch = one.transitions()
        assert batch.columns["physics"].dtype == torch.float64
        assert torch.equal(batch.columns["physics"][:, 0], torch.from_numpy(values[:5]))
        assert torch.equal(batch.columns["next_physics"][:, 0], torch.from_numpy(values[1:]))
        assert torch.equal(batch.columns["extra"][:, 0], 7 * torch.arange(5.0))
        sample = one.sample(16, nstep=2, generator=torch.Generator().manual_seed(0))
        step = sample.action[:, 0].long()
        assert torch.equal(sample.columns["next_physics"][:, 0], torch.from_numpy(values)[step + 2])
        bulk = ReplayBuffer(50, 2, 1, max_episode_length=10, columns=columns, stage_on_host=staged)
        bulk.add_episode(np.arange(6, dtype=np.float32)[:, None].repeat(2, 1), np.arange(5, dtype=np.float32)[:, None],
                         np.arange(5.0), np.ones(5), physics=values[:, None].repeat(3, 1),
                         extra=7 * np.arange(5.0)[:, None].repeat(2, 1))
        whole = bulk.transitions()
        assert all(torch.equal(getattr(whole, f), getattr(batch, f)) for f in ("obs", "action", "reward", "discount",
                                                                                "next_obs"))
        assert whole.columns.keys() == batch.columns.keys()
        assert all(torch.equal(whole.columns[k], batch.columns[k]) for k in batch.columns)
        state = one.state_dict()
        assert state["rows_float64"].dtype == torch.float64
        restored = ReplayBuffer(50, 2, 1, max_episode_length=10, columns=state["columns"], stage_on_host=staged)
        restored.load_state_dict(state)
        restored.add(np.zeros(1, np.float32), 0.0, 1.0, np.zeros(2, np.float32), physics=np.full(3, 0.1),
                     extra=np.zeros(2, np.float32))  # the open episode continues
        assert torch.equal(restored.transitions().columns["next_physics"][:5], batch.columns["next_physics"])
        assert restored.transitions().columns["next_physics"][5, 0] == 0.1
    with pytest.raises(CheckpointError, match="columns"):
        ReplayBuffer(50, 2, 1, max_episode_length=10, columns={"physics": 3}).load_state_dict(state)
    with pytest.raises(ValueError, match="physics"):
        one.start_episode(np.zeros(2, np.float32))
    with pytest.raises(ConfigError, match="next_"):
        ReplayBuffer(50, 2, 1, max_episode_length=10, columns={"next_x": 1})


@pytest.mark.slow
def test_pretraining_records_the_physics_of_every_observation(run: Path):
    """The replay's physics rows are the environment's states: a fresh environment reset with the
    run's seed and stepped with the recorded actions goes through the same physics, bit for bit."""
    replay = run_replay(run)
    data = replay.transitions()
    env = envs.make(MAZE, seed=0).unwrapped
    env.reset(seed=0)
    assert np.array_equal(env.physics_state(), data.columns["physics"][0].numpy())
    for t in range(20):
        env.step(data.action[t].numpy())
        assert np.array_equal(env.physics_state(), data.columns["next_physics"][t].numpy())
    assert env.physics_width == 6 and env.physics_layout == [("qpos", 2), ("qvel", 2), ("ctrl", 2)]


def test_reward_function_inference_reads_a_replay_that_records_physics(run: Path, tmp_path: Path):
    """Zero-shot from a reward function reads the run's replay, physics column and all."""
    reward_file = tmp_path / "reward.py"
    reward_file.write_text("import numpy as np\n\n\ndef left(next_obs):\n"
                           "    return (next_obs[:, 0] < 0).astype(np.float32)\n")
    assert main(["zeroshot", str(run), "--task", MAZE, "--skill-source", "reward_fn", "--reward-fn",
                 f"{reward_file}:left", "--inference.eval-episodes", "1", "--no-progress"]) == 0
    result = json.loads((run / "zeroshot" / f"{MAZE}.json").read_text())
    assert result["inference_info"]["states"] == "the run's pre-training replay"


@pytest.mark.slow
def test_export_then_read_gives_the_runs_replay(run: Path, dataset: Path):
    replay = run_replay(run)
    expected = replay.transitions()
    buffer, info = read_dataset(dataset, columns=("physics",))
    assert len(buffer) == info.transitions == 2000 and buffer.num_episodes == 2
    got = buffer.transitions()
    for name in ("obs", "action", "reward", "discount", "next_obs"):
        assert torch.equal(getattr(got, name), getattr(expected, name)), name
    for name in ("physics", "next_physics"):
        assert got.columns[name].dtype == torch.float64 and torch.equal(got.columns[name], expected.columns[name])
    meta = json.loads((dataset / "dataset.json").read_text())
    assert meta["domain"] == "point_mass_maze" and meta["task"] == meta["pretrain_task"] == MAZE
    assert (meta["agent"], meta["frames"], meta["episodes"], meta["transitions"]) == ("fb", 2000, 2, 2000)
    assert (meta["obs_dim"], meta["action_dim"], meta["physics_width"]) == (4, 2, 6)
    assert meta["physics_layout"] == [["qpos", 2], ["qvel", 2], ["ctrl", 2]] and meta["dvfb_version"]
    with np.load(dataset / "buffer" / "episode_000001_1000.npz") as file:  # ExORL's keys and row 0
        assert sorted(file.files) == ["action", "discount", "observation", "physics", "reward"]
        assert file["action"].shape == (1001, 2) and not file["action"][0].any() and file["reward"][0, 0] == 0
        assert file["discount"].shape == (1001, 1) and file["physics"].dtype == np.float64
    skills, _ = read_dataset(dataset, z_dim=8)  # a skill column for an offline learner, no physics
    assert skills.sample(4).z.shape == (4, 8) and not skills.transitions().columns
    # The export at 1500 frames left out the episode in progress.
    assert read_info(run / "dataset_1500").transitions == 1000


def test_relabel_with_the_pretraining_task_gives_the_recorded_rewards(dataset: Path, tmp_path: Path):
    """Across the resumed mid-episode checkpoint too: the physics rows line up with the rewards."""
    out = relabel(dataset, MAZE, tmp_path / "same", progress=None)
    assert out.task == MAZE and out.relabelled_from == str(dataset.resolve())
    for name in out.files:
        a, b = load_episode(dataset / "buffer" / name, out), load_episode(tmp_path / "same" / "buffer" / name, out)
        assert all(np.array_equal(a[k], b[k]) for k in a)
    other = "point_mass_maze_reach_bottom_right"
    assert main(["dataset", "relabel", str(dataset), "--task", other, "--no-progress"]) == 0
    relabelled = read_info(dataset.parent / f"dataset_{other}")
    assert relabelled.task == other and relabelled.transitions == 2000


def _roll(task: str, steps: int, seed: int = 0):
    """A random episode of ``steps`` steps in ``task``'s environment: its ExORL-layout arrays and
    the actions and (reset) episode state to replay it elsewhere."""
    env = envs.make(task, seed=seed).unwrapped
    obs, _ = env.reset(seed=seed)
    start = env.get_episode_state()
    rng = np.random.default_rng(seed)
    arrays = {"observation": [obs], "action": [np.zeros(env.action_space.shape, np.float32)], "reward": [0.0],
              "discount": [1.0], "physics": [env.physics_state()]}
    for _ in range(steps):
        action = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        obs, _, _, _, info = env.step(action)
        for key, value in zip(arrays, (obs, action, info["task_reward"], 1.0, env.physics_state())):
            arrays[key].append(value)
    arrays = {k: np.asarray(v, np.float64 if k == "physics" else np.float32) for k, v in arrays.items()}
    arrays["reward"], arrays["discount"] = arrays["reward"][:, None], arrays["discount"][:, None]
    return env, arrays, start


def _write(tmp_path: Path, env, arrays) -> Path:
    spec = env.task_spec
    info = DatasetInfo(domain=spec.domain, task=spec.name, pretrain_task=spec.name, source_run="(test rollout)",
                       agent="random", seed=0, frames=len(arrays["reward"]) - 1, obs_dim=spec.obs_dim,
                       action_dim=spec.action_dim, physics_width=env.physics_width,
                       physics_layout=[list(p) for p in env.physics_layout], episode_length=spec.episode_length,
                       episodes=1, transitions=len(arrays["reward"]) - 1, files=[])
    write_dataset(tmp_path / "data", info, [(0, arrays)], progress=None)
    return tmp_path / "data"


DOMAIN_TASKS = [("walker_walk", "walker_flip"), ("quadruped_walk", "quadruped_jump"),
                ("hopper_hop", "hopper_flip_backward"), ("cheetah_walk", "cheetah_run_backward"),
                ("point_mass_maze_reach_bottom_right", MAZE),  # the start room is the top left one
                ("metaworld_faucet_open", "metaworld_faucet_close")]


@pytest.mark.parametrize("task,other", DOMAIN_TASKS, ids=[t for t, _ in DOMAIN_TASKS])
@pytest.mark.slow
def test_relabelled_rewards_are_the_environments_bit_for_bit(task: str, other: str, tmp_path: Path):
    """For the episode's own task: the rewards the environment returned. For another task of the
    domain: the rewards of that task's environment started in the same state and stepped with the
    same actions (whose physics stays the same, bit for bit)."""
    source, arrays, start = _roll(task, 60)
    data = _write(tmp_path, source, arrays)
    same = relabel(data, task, tmp_path / "same", progress=None)
    reward = load_episode(tmp_path / "same" / "buffer" / same.files[0], same)["reward"]
    assert reward.tobytes() == arrays["reward"].tobytes()

    env = envs.make(other, seed=1).unwrapped
    env.reset(seed=1)
    if task.startswith("metaworld"):  # the other task's environment with the episode's faucet
        env.mw_env._last_rand_vec = source.mw_env._last_rand_vec.copy()
        env.mw_env.reset()
        set_mujoco_state(env.mw_env.model, env.mw_env.data, start["physics"], recompute="forward")
    else:
        env.set_episode_state({**start, "rng": env.get_rng_state()})
    expected = [0.0]
    for t in range(1, 61):
        _, _, _, _, info = env.step(arrays["action"][t])
        assert np.array_equal(env.physics_state(), arrays["physics"][t])
        expected.append(info["task_reward"])
    relabelled = relabel(data, other, tmp_path / "other", progress=None)
    reward = load_episode(tmp_path / "other" / "buffer" / relabelled.files[0], relabelled)["reward"]
    assert reward.tobytes() == np.asarray(expected, np.float32)[:, None].tobytes()
    assert not np.array_equal(reward, arrays["reward"])


DAMAGE = {
    "truncated": lambda path: path.write_bytes(path.read_bytes()[: path.stat().st_size // 2]),
    "corrupt": lambda path: path.write_bytes(path.read_bytes()[:200] + b"\x00" * 400 + path.read_bytes()[600:]),
    "missing key": lambda path: _rewrite(path, lambda a: a.pop("discount")),
    "inconsistent lengths": lambda path: _rewrite(path, lambda a: a.update(action=a["action"][:-1])),
    "non-finite": lambda path: _rewrite(path, lambda a: a["physics"].__setitem__((3, 1), np.nan)),
    "unlisted": lambda path: shutil.copy(path, path.with_name("episode_000009_1000.npz")),
    "missing": lambda path: path.unlink(),
}


def _rewrite(path: Path, change) -> None:
    with np.load(path) as file:
        arrays = dict(file)
    change(arrays)
    np.savez_compressed(path, **arrays)


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_episode_file_is_one_line_naming_it(dataset: Path, tmp_path: Path, damage: str, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    damaged = copy / "buffer" / "episode_000001_1000.npz"
    DAMAGE[damage](damaged)
    with pytest.raises(ConfigError) as exc:
        read_dataset(copy)
    message = str(exc.value)
    assert "\n" not in message and ("episode_000009_1000.npz" if damage == "unlisted" else str(damaged)) in message
    nested = tmp_path / "new" / "parents" / "out"  # parents the relabel would create
    assert main(["dataset", "relabel", str(copy), "--task", MAZE, "--out", str(nested)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and (damage == "unlisted" or str(damaged) in err)
    assert not (tmp_path / "new").exists()


@pytest.mark.slow
def test_a_read_only_or_full_disk_is_one_line_and_leaves_nothing(run: Path, dataset: Path, small_disk: Path, capsys):
    def fails(args, *words):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and all(w in err for w in words), err

    # Full: a few kilobytes free, less than one compressed episode.
    ballast = small_disk / "ballast"
    disk = os.statvfs(small_disk)
    ballast.write_bytes(b"\0" * (disk.f_bavail * disk.f_frsize - 16 * 1024))
    fails(["dataset", "export", str(run), "--out", str(small_disk / "a" / "ds")], "No space left on device",
          str(small_disk / "a" / "ds"))
    fails(["dataset", "relabel", str(dataset), "--task", MAZE, "--out", str(small_disk / "b")],
          "No space left on device")
    assert sorted(p.name for p in small_disk.iterdir()) == ["ballast"]
    ballast.unlink()
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    fails(["dataset", "export", str(run), "--out", str(small_disk / "a" / "ds")], "Read-only file system")
    fails(["dataset", "relabel", str(dataset), "--task", MAZE, "--out", str(small_disk / "b")],
          "Read-only file system")
    assert list(small_disk.iterdir()) == []


def test_bad_input_is_one_line_and_writes_nothing(run: Path, dataset: Path, tmp_path: Path, capsys):
    def fails(args, *words):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and all(w in err for w in words), err

    fails(["dataset", "export", str(tmp_path / "nope")], "does not exist")
    fails(["dataset", "export", str(dataset)], "not a dvfb run directory")
    plain = tmp_path / "plain"
    pretrain(plain, 600)
    capsys.readouterr()
    fails(["dataset", "export", str(plain)], "--replay.record-physics")
    assert not (plain / "dataset").exists()
    before = sorted(p.name for p in (dataset / "buffer").iterdir())
    fails(["dataset", "export", str(run), "--out", str(dataset)], "not an empty directory")
    assert sorted(p.name for p in (dataset / "buffer").iterdir()) == before
    fails(["dataset", "relabel", str(dataset), "--task", "walker_walk"], "not a task of the dataset's domain")
    fails(["dataset", "relabel", str(dataset), "--task", "walker_jump"], "unknown task")
    fails(["dataset", "relabel", str(dataset), "--task", MAZE, "--out", str(dataset)], "new directory")
    fails(["dataset", "relabel", str(tmp_path), "--task", MAZE], "no dataset.json")
    assert not (tmp_path / f"{tmp_path.name}_{MAZE}").exists() and not (dataset.parent / f"dataset_{MAZE}").exists()


def test_cli_help_shows_the_defaults(capsys):
    for command in (["dataset", "export"], ["dataset", "relabel"]):
        with pytest.raises(SystemExit):
            main([*command, "--help"])
        out = capsys.readouterr().out
        assert "(default: RUN/dataset)" in out or "(default: DATASET_<task>" in out
        assert "--no-progress" in out
