"""Offline training (docs/methods.md, "Offline training"): the training loop over a dataset source --
run directory, checkpoints without the replay, exact resume, zero-shot from the relabelled dataset --
and the bad-input cases. Real files, a dataset exported from a real maze run."""

from __future__ import annotations

import hashlib
import json
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from dvfb.analysis.common import method_name
from dvfb.cli import main
from dvfb.core.errors import ConfigError
from dvfb.workflows.dataset_export import export_run
from dvfb.runs import load_checkpoint, load_snapshot
from tiny import run_cli, start_cli, tiny_flags, tree_bytes

TINY_FB = tiny_flags("fb")
TINY_SF = [flag.replace("--fb.", "--sf.") for flag in TINY_FB]
COMMON = ["--domain", "point_mass_maze", "--log-every", "50", "--torch-threads", "1", "--no-progress"]


@pytest.fixture(scope="module")
def dataset(fb_maze_physics_run: Path, tmp_path_factory) -> Path:
    """The two episodes of the session's FB maze run that recorded physics (conftest.py), exported."""
    out = tmp_path_factory.mktemp("offline") / "maze_data"
    export_run(fb_maze_physics_run, out, progress=None)
    return out


def offline(run: Path, dataset: Path, agent: str, updates: int, *extra: str) -> int:
    sizes = TINY_SF if agent == "sf" else TINY_FB
    return main(["pretrain", "--agent", agent, *COMMON, "--dataset", str(dataset), "--frames", str(updates),
                 "--checkpoint-every", "100", "--run-dir", str(run), *sizes, *extra])


def snapshot_tensors(run: Path, frames: int) -> dict[str, torch.Tensor]:
    state = load_snapshot(run, f"snapshot_{frames}")
    return {f"{m}.{k}": v for m, sd in state["modules"].items() for k, v in sd.items()}


@pytest.mark.slow
def test_an_offline_run_updates_every_step_and_checkpoints_without_the_replay(dataset: Path, tmp_path: Path):
    run = tmp_path / "fb_offline"
    assert offline(run, dataset, "fb", 250) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["dataset"] == str(dataset) and config["seed_frames"] == 0 and config["update_every"] == 1
    steps = [json.loads(line)["step"] for line in (run / "metrics" / "train.jsonl").read_text().splitlines()]
    assert steps == [50, 100, 150, 200, 250]  # an update at every step from the first
    summary = json.loads((run / "pretrain_summary.json").read_text())
    assert summary["frames"] == 250 and summary["episodes"] == 0  # no environment episode
    state = load_checkpoint(run)
    assert "replay" not in state and state["dataset"]["transitions"] == 2000
    assert state["dataset"]["files"] == ["episode_000000_1000.npz", "episode_000001_1000.npz"]
    assert method_name(config) == "fb@maze_data"


@pytest.mark.parametrize("agent", ["vcfb", "sf"])
@pytest.mark.slow
def test_offline_resume_equals_an_uninterrupted_run(dataset: Path, tmp_path: Path, agent: str):
    full, split = tmp_path / "full", tmp_path / "split"
    assert offline(full, dataset, agent, 200) == 0
    assert offline(split, dataset, agent, 100) == 0
    assert offline(split, dataset, agent, 200, "--resume") == 0
    a, b = snapshot_tensors(full, 200), snapshot_tensors(split, 200)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    strip = lambda run: [{k: v for k, v in json.loads(x).items() if not k.startswith("fps")}  # noqa: E731
                         for x in (run / "metrics" / "train.jsonl").read_text().splitlines()]
    assert strip(full) == strip(split)


def test_zero_shot_from_the_relabelled_dataset_or_from_online_steps(dataset: Path, tmp_path: Path):
    run = tmp_path / "fb_offline"
    assert offline(run, dataset, "fb", 100) == 0
    task = "point_mass_maze_reach_top_right"
    assert main(["zeroshot", str(run), "--task", task, "--skill-source", "dataset", "--inference.samples", "500",
                 "--inference.eval-episodes", "1"]) == 0
    result = json.loads((run / "zeroshot" / f"{task}.json").read_text())
    assert result["skill_source"] == "dataset" and result["inference_info"]["num_samples"] == 500
    assert "relabelled from physics" in result["inference_info"]["states"]
    assert torch.isclose(torch.tensor(result["z"]).norm(), torch.tensor(8.0).sqrt(), atol=1e-4)
    # The online protocol is still there: reward-labelled steps in the task.
    assert main(["zeroshot", str(run), "--task", task, "--overwrite", "--inference.steps", "300",
                 "--inference.random-action-steps", "100", "--inference.samples", "300",
                 "--inference.eval-episodes", "1"]) == 0
    assert json.loads((run / "zeroshot" / f"{task}.json").read_text())["skill_source"] == "rewards"


def test_bad_offline_input_is_one_line_and_creates_nothing(dataset: Path, tmp_path: Path, capsys):
    run = tmp_path / "never"
    cases = [
        (["--dataset", str(tmp_path / "missing")], "missing"),
        (["--dataset", str(dataset), "--replay.record-physics", "true"], "--replay.record-physics"),
        (["--dataset", str(dataset), "--replay.sampling", "loader_shards"], "uniformly"),
    ]
    for extra, needle in cases:
        code = main(["pretrain", "--agent", "fb", *COMMON, "--frames", "100", "--run-dir", str(run), *TINY_FB, *extra])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and needle in err[0], err
        assert not run.exists()
    code = main(["pretrain", "--agent", "fb", "--domain", "walker", "--log-every", "50", "--no-progress",
                 "--dataset", str(dataset), "--frames", "100", "--run-dir", str(run), *TINY_FB])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "point_mass_maze data" in err[0] and not run.exists()
    # A dataset source for a run that has none.
    online = tmp_path / "online"
    assert main(["pretrain", "--agent", "fb", *COMMON, "--frames", "1100", "--seed-frames", "1000",
                 "--run-dir", str(online), *TINY_FB]) == 0
    capsys.readouterr()
    code = main(["zeroshot", str(online), "--task", "point_mass_maze_reach_top_right", "--skill-source", "dataset"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--dataset DIR" in err[0]
    assert not (online / "zeroshot").exists()


def _reexport(dataset: Path, change) -> None:
    """Rewrite ``dataset`` in place as a re-export would: the same file names and shapes, other
    contents (``change`` maps an episode's arrays), a new dataset.json."""
    from dvfb.data.datasets import EPISODES_DIR, load_episode, read_info, write_dataset

    info = read_info(dataset)
    arrays = [(i, change(load_episode(dataset / EPISODES_DIR / name, info))) for i, name in enumerate(info.files)]
    fresh = dataset.with_name(dataset.name + "_new")
    write_dataset(fresh, info, arrays)
    shutil.rmtree(dataset)
    fresh.rename(dataset)


@pytest.mark.slow
def test_a_resume_or_an_offline_zero_shot_on_other_data_is_one_line_and_changes_nothing(dataset: Path, tmp_path: Path,
                                                                                        capsys):
    data, run = tmp_path / "data", tmp_path / "fb_offline"
    shutil.copytree(dataset, data)
    recorded = json.loads((data / "dataset.json").read_text())["digests"]
    assert sorted(recorded) == ["episode_000000_1000.npz", "episode_000001_1000.npz"]
    assert offline(run, data, "fb", 100) == 0
    assert json.loads((run / "trained_on.json").read_text())["digests"] == recorded
    # The same data under another name is the same data: the resume continues.
    _reexport(data, lambda a: a)
    assert offline(run, data, "fb", 150, "--resume") == 0
    capsys.readouterr()
    # Observations x 0.5 under the same names and shapes: not the data the run was made from.
    _reexport(data, lambda a: {**a, "observation": a["observation"] * 0.5})
    before = tree_bytes(run)
    task = "point_mass_maze_reach_top_right"
    for argv in (["pretrain", "--agent", "fb", *COMMON, "--dataset", str(data), "--frames", "200",
                  "--checkpoint-every", "100", "--run-dir", str(run), *TINY_FB, "--resume"],
                 ["zeroshot", str(run), "--task", task, "--skill-source", "dataset"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "other data" in err[0] and "episode_000000_1000.npz" in err[0], err
        assert tree_bytes(run) == before
    # A file changed behind dataset.json's back is named on every read, relabelling included.
    episode = data / "buffer" / "episode_000001_1000.npz"
    with np.load(episode) as file:
        arrays = dict(file)
    arrays["reward"] = arrays["reward"] + 1.0
    np.savez_compressed(episode, **arrays)
    assert main(["dataset", "relabel", str(data), "--task", task, "--out", str(tmp_path / "relabelled")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(episode) in err[0] and "contents changed" in err[0]
    assert not (tmp_path / "relabelled").exists()


def test_a_dataset_with_an_episode_of_0_steps_is_refused_naming_the_file(dataset: Path, tmp_path: Path, capsys):
    from dvfb.data import read_dataset

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    info = json.loads((data / "dataset.json").read_text())
    with np.load(data / "buffer" / info["files"][0]) as file:
        empty = {key: value[:1] for key, value in file.items()}  # the reset row only: 0 steps
    name = "episode_000002_0.npz"
    np.savez_compressed(data / "buffer" / name, **empty)
    info.update(files=[*info["files"], name], episodes=info["episodes"] + 1,
                digests={**info["digests"], name: hashlib.sha256((data / "buffer" / name).read_bytes()).hexdigest()})
    (data / "dataset.json").write_text(json.dumps(info))
    named = str(data / "buffer" / name)
    with pytest.raises(ConfigError, match="holds 0 steps") as exc:
        read_dataset(data)
    assert named in str(exc.value)
    before = tree_bytes(data)
    run, out = tmp_path / "never", tmp_path / "relabelled"
    for argv in (["pretrain", "--agent", "fb", *COMMON, "--dataset", str(data), "--frames", "100", "--run-dir",
                  str(run), *TINY_FB],
                 ["dataset", "relabel", str(data), "--task", "point_mass_maze_reach_top_right", "--out", str(out)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and named in err[0] and "0 steps" in err[0], err
    assert not run.exists() and not out.exists() and tree_bytes(data) == before


@pytest.mark.slow
def test_sigterm_and_resume_of_an_offline_run_write_the_same_records_and_learner(dataset: Path, tmp_path: Path):
    """The signal's checkpoint cuts a metric window and carries its rows: the resumed run's metric
    records equal an uninterrupted run's (fps aside), and so does its final snapshot."""
    full, split = tmp_path / "full", tmp_path / "split"
    args = ["pretrain", "--agent", "fb", *COMMON, "--dataset", str(dataset), "--frames", "1500",
            "--checkpoint-every", "500", *TINY_FB]
    assert main([*args, "--run-dir", str(full)]) == 0
    process = start_cli(*args, "--run-dir", str(split))
    metrics = split / "metrics" / "train.jsonl"
    deadline = time.monotonic() + 120
    while not (metrics.exists() and metrics.read_text().count("\n") >= 2) and process.poll() is None:
        assert time.monotonic() < deadline, "no metric record within 120 s"
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _out, err = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, err
    step = load_checkpoint(split)["step"]
    assert 100 <= step < 1500  # inside a window of log_every 50 unless it lands on a multiple (2%)
    resumed = run_cli(*args, "--run-dir", str(split), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    records = lambda run: [{k: v for k, v in json.loads(x).items() if not k.startswith("fps")}  # noqa: E731
                           for x in (run / "metrics" / "train.jsonl").read_text().splitlines()]
    assert len(records(full)) == 30 and records(full) == records(split)
    a, b = snapshot_tensors(full, 1500), snapshot_tensors(split, 1500)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_an_offline_group_split_over_processes_trains_each_member_as_its_own_run(dataset: Path, tmp_path: Path):
    # Shares of one member are plain runs: each equals its separate run, each process reading the data.
    assert offline(tmp_path / "g_s{seed}", dataset, "fb", 150, "--seeds", "0,1", "--processes", "2") == 0
    assert offline(tmp_path / "alone", dataset, "fb", 150, "--seed", "1") == 0
    a, b = snapshot_tensors(tmp_path / "g_s1", 150), snapshot_tensors(tmp_path / "alone", 150)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    other = snapshot_tensors(tmp_path / "g_s0", 150)  # and member 0 is not member 1
    assert any(not torch.equal(other[k], a[k]) for k in a)
