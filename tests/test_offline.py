"""Offline training (docs/methods.md, "Offline training"): the training loop over a dataset source --
run directory, checkpoints without the replay, exact resume, zero-shot from the relabelled dataset --
and the bad-input cases. Real files, a dataset exported from a real maze run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from dvfb.analysis.common import method_name
from dvfb.cli import main
from dvfb.workflows.datasets import export_run
from dvfb.runs import load_checkpoint, load_snapshot

TINY_FB = ["--fb.z-dim", "8", "--fb.hidden-dim", "32", "--fb.feature-dim", "16", "--fb.backward-hidden-dim", "32",
           "--fb.batch-size", "32"]
TINY_SF = [flag.replace("--fb.", "--sf.") for flag in TINY_FB]
COMMON = ["--domain", "point_mass_maze", "--log-every", "50", "--torch-threads", "1", "--no-progress"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Two episodes of an FB maze run that recorded physics, exported."""
    root = tmp_path_factory.mktemp("offline")
    run = root / "source"
    assert main(["pretrain", "--agent", "fb", *COMMON, "--seed-frames", "500", "--update-every", "4",
                 "--checkpoint-every", "1000", "--frames", "2000", "--run-dir", str(run),
                 "--replay.record-physics", "true", *TINY_FB]) == 0
    export_run(run, root / "maze_data", progress=None)
    return root / "maze_data"


def offline(run: Path, dataset: Path, agent: str, updates: int, *extra: str) -> int:
    sizes = TINY_SF if agent == "sf" else TINY_FB
    return main(["pretrain", "--agent", agent, *COMMON, "--dataset", str(dataset), "--frames", str(updates),
                 "--checkpoint-every", "100", "--run-dir", str(run), *sizes, *extra])


def snapshot_tensors(run: Path, frames: int) -> dict[str, torch.Tensor]:
    state = load_snapshot(run, f"snapshot_{frames}")
    return {f"{m}.{k}": v for m, sd in state["modules"].items() for k, v in sd.items()}


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
def test_offline_resume_equals_an_uninterrupted_run(dataset: Path, tmp_path: Path, agent: str):
    full, split = tmp_path / "full", tmp_path / "split"
    assert offline(full, dataset, agent, 200) == 0
    assert offline(split, dataset, agent, 100) == 0
    assert offline(split, dataset, agent, 200, "--resume") == 0
    a, b = snapshot_tensors(full, 200), snapshot_tensors(split, 200)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    strip = lambda run: [{k: v for k, v in json.loads(x).items() if k != "fps"}  # noqa: E731
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
