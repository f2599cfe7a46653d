"""Does my run learn? The zero-shot evaluations while pre-training (``--eval-every``), the
reference bands made from a study's results, and the verdict of ``dvfb status`` (docs/health.md)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dvfb.cli import main
from dvfb.envs import tasks_of_domain
from dvfb.runs import load_snapshot
from dvfb.runs.directory import RunDir
from tiny import MAZE_SCHEDULE, tiny_flags

MAZE_TASKS = tasks_of_domain("point_mass_maze")
EVAL = ["--eval-episodes", "1", "--eval-samples", "600", "--eval-skill-steps", "1000"]


def pretrain_argv(agent: str, run: Path, frames: int, *extra: str) -> list[str]:
    return ["pretrain", "--agent", agent, *MAZE_SCHEDULE, "--frames", str(frames), "--run-dir", str(run),
            "--no-progress", "--log-every", "250", "--torch-threads", "1", *tiny_flags(agent), *extra]


def records(run: Path, prefix: str, leave_out: tuple[str, ...] = ("fps", "fps_recent", "seconds")) -> list[dict]:
    path = run / "metrics" / f"{prefix}.jsonl"
    return [{k: v for k, v in json.loads(line).items() if k not in leave_out} for line in path.read_text().splitlines()]


def snapshot_tensors(run: Path, frames: int) -> dict:
    modules = load_snapshot(RunDir(run), f"snapshot_{frames}")["modules"]
    return {(m, k): t for m, state in modules.items() for k, t in state.items()}


@pytest.mark.slow
def test_evaluations_leave_training_bit_identical_and_a_resume_continues_them_exactly(tmp_path):
    """The same DVFB run with evaluations every 500 frames, without them, and stopped by SIGTERM
    then resumed: equal weights and train records; the evaluations of the resumed run equal the
    uninterrupted run's."""
    with_eval, without, split = tmp_path / "with", tmp_path / "without", tmp_path / "split"
    assert main(pretrain_argv("dvfb", with_eval, 1500, "--eval-every", "500", *EVAL)) == 0
    assert main(pretrain_argv("dvfb", without, 1500, "--eval-every", "0")) == 0
    a, b = snapshot_tensors(with_eval, 1500), snapshot_tensors(without, 1500)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert records(with_eval, "train") == records(without, "train")
    assert not (without / "metrics" / "eval.jsonl").exists()
    evaluations = records(with_eval, "eval")
    assert [(r["step"], r["task"]) for r in evaluations] == [(s, t) for s in (500, 1000, 1500) for t in MAZE_TASKS]
    for record in evaluations:
        assert record["protocol"] == "reward_inference" and record["episodes"] == 1 and len(record["skill"]) == 8
        assert record["return"] == record["returns"][0]

    process = subprocess.Popen([sys.executable, "-m", "dvfb", *pretrain_argv("dvfb", split, 1500, "--eval-every", "500",
                                                                          *EVAL)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    deadline = time.monotonic() + 300
    eval_file = split / "metrics" / "eval.jsonl"
    while not (eval_file.exists() and eval_file.read_text().count("\n") >= 4):  # past the first evaluation
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    _out, err = process.communicate(timeout=300)
    assert process.returncode == 128 + signal.SIGTERM, err
    resumed = subprocess.run([sys.executable, "-m", "dvfb", *pretrain_argv("dvfb", split, 1500, "--eval-every", "500",
                                                                          *EVAL, "--resume")],
                             capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert records(split, "eval") == evaluations
    c = snapshot_tensors(split, 1500)
    assert all(torch.equal(a[k], c[k]) for k in a)


@pytest.mark.slow
@pytest.mark.parametrize("agent, protocol", [("cic", "skill_selection"), ("rnd", "single_policy")])
def test_methods_that_do_not_infer_from_rewards_are_evaluated_by_their_own_protocol(tmp_path, agent, protocol):
    run = tmp_path / agent
    assert main(pretrain_argv(agent, run, 1000, "--eval-every", "1000", "--eval-tasks",
                              "point_mass_maze_reach_top_left", *EVAL)) == 0
    (record,) = records(run, "eval")
    assert (record["step"], record["task"], record["protocol"]) == (1000, "point_mass_maze_reach_top_left", protocol)
    assert (record["skill"] is None) == (protocol == "single_policy")


def test_eval_tasks_of_another_domain_are_refused_with_one_line(tmp_path, capsys):
    assert main(pretrain_argv("fb", tmp_path / "run", 1000, "--eval-tasks", "walker_walk")) == 2
    err = capsys.readouterr().err.strip()
    assert "--eval-tasks: 'walker_walk' is not a task of point_mass_maze" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_a_config_from_before_the_evaluations_never_evaluates(tmp_path):
    from dvfb.core.config import to_dict
    from dvfb.runs.presets import preset_config
    from dvfb.runs.run_config import run_config_from_dict

    data = to_dict(preset_config("small", "fb", domain="walker"))
    assert data["eval_every"] == 10_000  # the small preset's default
    old = {k: v for k, v in data.items() if not k.startswith("eval_")}
    assert run_config_from_dict(old).eval_every == 0


# ---------------------------------------------------------------------------------------------
# bands and verdicts

WALK = "walker_walk"


def _study(root: Path) -> Path:
    """Three synthetic DVFB walker runs of a 100k-frame study with walker_walk results at 25k frames
    (60, 80, 100) and at the end."""
    from tiny import make_pretrain_run

    for seed, value in enumerate((60.0, 80.0, 100.0)):
        run = make_pretrain_run(root / f"dvfb_walker_s{seed}", seed=seed, zeroshot={WALK: value + 100})
        (run / "zeroshot" / f"{WALK}@25000.json").write_text(json.dumps(
            {"task": WALK, "snapshot_frames": 25000, "mean_return": value, "returns": [value]}))
    return root


def _random(path: Path) -> Path:
    path.write_text(json.dumps({"agent": "random", "domain": "walker", "seed": 0, "episodes": 3, "tasks": {
        WALK: {"mean_return": 30.0, "std_return": 8.2, "returns": [20.0, 30.0, 40.0]}}}))
    return path


def test_bands_are_made_from_a_studys_results_by_a_command(tmp_path, capsys):
    study, out = _study(tmp_path / "runs"), tmp_path / "bands.json"
    assert main(["bands", str(study), "--random", str(_random(tmp_path / "random.json")), "--out", str(out)]) == 0
    assert "2 bands (1 method x domain pairs) and 1 random-policy bands written" in capsys.readouterr().out
    data = json.loads(out.read_text())
    early = next(b for b in data["bands"] if b["frames"] == 25000)
    assert early == {"method": "dvfb", "domain": "walker", "preset": "small", "budget": 100000, "task": WALK,
                     "frames": 25000, "seeds": 3, "mean": 80.0, "min": 60.0, "max": 100.0}
    assert data["random"] == [{"domain": "walker", "task": WALK, "episodes": 3, "mean": 30.0, "min": 20.0, "max": 40.0}]
    assert main(["bands", str(study), "--out", str(out)]) == 2  # never replaced without --overwrite
    assert "exists; pass --overwrite" in capsys.readouterr().err


@pytest.mark.parametrize("step, value, where, warning", [
    (20000, 70.0, "inside", None),
    (30000, 150.0, "above", None),
    (25000, 50.0, "below", "below every reference seed"),
    (25000, 35.0, "below", "not learning: no better than the random policy's returns (20.0-40.0) where every "
                           "reference run had left them by 25,000 frames"),
    (25000, float("nan"), "not finite", "the networks have diverged"),
    (5000, 70.0, "no band at 5,000 frames (the dvfb bands are at 25,000, 100,000 frames)", None),
])
def test_a_verdict_reads_the_newest_evaluation_against_the_nearest_snapshots_band(tmp_path, step, value, where,
                                                                                  warning):
    from dvfb.analysis.bands import load_bands, make_bands, verdicts, write_bands

    bands = load_bands(write_bands(make_bands([_study(tmp_path / "runs")], [_random(tmp_path / "r.json")]),
                                   tmp_path / "bands.json"))
    old = {"step": 1000, "task": WALK, "return": 500.0}  # an older evaluation: not the one read
    (verdict,) = verdicts("dvfb", "walker", "small", [old, {"step": step, "task": WALK, "return": value}], bands)
    assert verdict.where == where and verdict.step == step
    assert (verdict.warning is None) if warning is None else warning in verdict.warning
    (other,) = verdicts("fb", "walker", "small", [{"step": step, "task": WALK, "return": 70.0}], bands)
    assert other.where == "no band for fb on walker_walk at the small preset"


def test_a_reference_barely_above_random_flags_no_run_as_not_learning():
    # The reference's lowest seed less than the random policy's spread above its best episode (DVFB
    # on walker_walk at 25k: 52.6 against 29.5-43.1; here 50 against 20-40): a run within
    # the random returns is below the band, not "not learning".
    from dvfb.analysis.bands import Band, Bands, RandomBand, verdicts

    random = RandomBand("walker", WALK, 3, 30.0, 20.0, 40.0)
    for low, flagged in ((50.0, False), (60.0, True)):
        band = Band("dvfb", "walker", "small", 100000, WALK, 25000, 3, 80.0, low, 100.0)
        (verdict,) = verdicts("dvfb", "walker", "small", [{"step": 25000, "task": WALK, "return": 35.0}],
                              Bands((band,), (random,), "test"))
        assert verdict.where == "below"
        assert verdict.warning.startswith("not learning" if flagged else "below every reference seed")


def test_status_gives_the_verdict_and_draws_the_evaluations_over_the_band(dvfb_maze_run, tmp_path, capsys):
    from tiny import copy_run, make_pretrain_run

    task = "point_mass_maze_reach_top_left"
    for seed, value in enumerate((10.0, 20.0, 30.0)):
        run = make_pretrain_run(tmp_path / "study" / f"s{seed}", domain="point_mass_maze", seed=seed)
        (run / "zeroshot").mkdir()
        (run / "zeroshot" / f"{task}@2000.json").write_text(json.dumps(
            {"task": task, "snapshot_frames": 2000, "mean_return": value, "returns": [value]}))
    random = tmp_path / "random.json"
    random.write_text(json.dumps({"agent": "random", "domain": "point_mass_maze", "seed": 0, "tasks": {
        task: {"mean_return": 0.5, "returns": [0.0, 1.0]}}}))
    assert main(["bands", str(tmp_path / "study"), "--random", str(random), "--out", str(tmp_path / "b.json")]) == 0
    run = copy_run(dvfb_maze_run, tmp_path)
    (run / "metrics" / "eval.jsonl").write_text(
        json.dumps({"step": 1000, "task": task, "return": 4.0}) + "\n"
        + json.dumps({"step": 2000, "task": task, "return": 0.5}) + "\n")
    capsys.readouterr()
    plot = tmp_path / "health.png"
    assert main(["status", str(run), "--bands", str(tmp_path / "b.json"), "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert (f"  health: {task} 0.5 at 2,000 frames: below the dvfb band at 2,000 frames (10.0-30.0, mean 20.0, 3 seeds, "
            "small preset) -- not learning: no better than the random policy's returns (0.0-1.0)") in out
    assert plot.stat().st_size > 0 and f"evaluations over the reference bands: {plot}" in out
    assert main(["status", str(run), "--plot", str(plot)]) == 2  # never replaced without --overwrite
    assert "exists; pass --overwrite" in capsys.readouterr().err


@pytest.mark.slow
def test_each_member_of_a_group_evaluates_itself(tmp_path):
    template = str(tmp_path / "fb_s{seed}")
    argv = pretrain_argv("fb", Path(template), 1000, "--eval-every", "1000", "--eval-tasks",
                         "point_mass_maze_reach_top_left", *EVAL)
    at = argv.index("--run-dir")
    argv[at + 1] = template
    assert main([*argv, "--seeds", "0,1"]) == 0
    skills = []
    for seed in (0, 1):
        (record,) = records(tmp_path / f"fb_s{seed}", "eval")
        assert (record["step"], record["protocol"]) == (1000, "reward_inference")
        skills.append(record["skill"])
    assert skills[0] != skills[1]  # each member's own networks and data
