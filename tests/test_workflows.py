"""End-to-end workflows on real physics with tiny budgets: pretrain -> zeroshot -> finetune,
exact resume, and the bad-input cases (clear message, exit status 2, nothing overwritten)."""

from __future__ import annotations

import json
import shutil
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dvfb.cli import main
from dvfb.runs import latest_checkpoint, load_checkpoint, load_snapshot
from tiny import FAST_INFERENCE, copy_run, pretrain_args, replayed_return


@pytest.mark.slow
def test_pretrain_writes_run_directory(dvfb_maze_run: Path):
    config = json.loads((dvfb_maze_run / "config.json").read_text())
    assert config["agent"] == "dvfb" and config["domain"] == "point_mass_maze"
    assert config["fb"]["hidden_dim"] == 32 and config["preset"] == "small"
    assert (dvfb_maze_run / "snapshots" / "snapshot_2000.pt").is_file()
    assert latest_checkpoint(dvfb_maze_run).name == "resume_2000.pt"
    lines = (dvfb_maze_run / "metrics" / "train.jsonl").read_text().splitlines()
    # Updates start at 500 frames; metrics are read back every 250 frames.
    assert [json.loads(line)["step"] for line in lines] == list(range(750, 2001, 250))
    assert {"fb_loss", "rnd_loss", "nce_loss", "exploration_critic_loss", "actor_loss"} <= set(json.loads(lines[-1]))
    assert any(p.name.startswith("events.out.tfevents") for p in (dvfb_maze_run / "tb").iterdir())
    summary = json.loads((dvfb_maze_run / "pretrain_summary.json").read_text())
    assert summary["frames"] == 2000 and summary["episodes"] == 2


@pytest.mark.slow
@pytest.mark.e2e
def test_zeroshot_then_finetune(dvfb_maze_run: Path, tmp_path: Path, capsys):
    run = copy_run(dvfb_maze_run, tmp_path)  # it writes results: on a copy of the session's run
    assert main(["zeroshot", str(run), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE]) == 0
    result = json.loads((run / "zeroshot" / "point_mass_maze_reach_top_left.json").read_text())
    assert result["eval_episodes"] == 1 and len(result["returns"]) == 1
    # The recorded return is the episode's: the stored skill, replayed by hand with the model's mean
    # actions in the task's environment (the run's seed), gives it again.
    assert result["returns"][0] == pytest.approx(
        replayed_return(run, "point_mass_maze_reach_top_left", result["z"], result["seed"]), rel=1e-6)
    assert result["mean_return"] == pytest.approx(np.mean(result["returns"]))
    z = torch.tensor(result["z"])
    assert torch.isclose(z.norm(), torch.tensor(16.0).sqrt(), atol=1e-4)  # z_r on the sphere
    assert result["inference_info"]["num_samples"] == 300
    assert "point_mass_maze_reach_top_left" in capsys.readouterr().out

    args = ["finetune", str(run), "--task", "point_mass_maze_reach_top_right", *FAST_INFERENCE,
            "--finetune.frames", "1200", "--finetune.seed-frames", "400", "--finetune.eval-every", "600",
            "--finetune.eval-episodes", "1", "--finetune.checkpoint-every", "1000", "--no-progress"]
    assert main(args) == 0
    curve = json.loads((run / "finetune" / "point_mass_maze_reach_top_right" / "curve.json").read_text())
    assert [p["frames"] for p in curve["curve"]] == [0, 600, 1200]
    # F and B stayed frozen: the fine-tuning checkpoint holds only the actor and the task critic.
    state = load_checkpoint(run / "finetune" / "point_mass_maze_reach_top_right")
    assert any(k.startswith("task_critic.") for k in state["finetuner"]["finetuner"])
    assert not any(k.startswith("agent.") for k in state["finetuner"]["finetuner"])


@pytest.mark.slow
def test_reward_fn_and_goal_inference(dvfb_maze_run: Path, tmp_path: Path):
    run = copy_run(dvfb_maze_run, tmp_path)  # it writes results: on a copy of the session's run
    reward_file = tmp_path / "reward.py"
    reward_file.write_text("import numpy as np\n\ndef right_side(next_obs):\n    return (next_obs[:, 0] > 0).astype(np.float32)\n")
    assert main(["zeroshot", str(run), "--task", "point_mass_maze_reach_top_right", "--skill-source", "reward_fn",
                 "--reward-fn", f"{reward_file}:right_side", "--inference.eval-episodes", "1"]) == 0
    result = json.loads((run / "zeroshot" / "point_mass_maze_reach_top_right.json").read_text())
    assert result["skill_source"] == "reward_fn" and result["inference_info"]["num_samples"] > 0
    assert main(["zeroshot", str(run), "--task", "point_mass_maze_reach_bottom_left", "--skill-source", "goal",
                 "--goal=-0.15,-0.15,0,0", "--inference.eval-episodes", "1"]) == 0
    result = json.loads((run / "zeroshot" / "point_mass_maze_reach_bottom_left.json").read_text())
    assert result["skill_source"] == "goal" and len(result["z"]) == 16


def _snapshot_tensors(run_dir: Path, frames: int) -> dict[str, torch.Tensor]:
    state = load_snapshot(run_dir, f"snapshot_{frames}")
    return {f"{m}.{k}": v for m, sd in state["modules"].items() for k, v in sd.items()}


# The authors' loader shards keep their own state (what each shard has seen, when it looks next).
SAMPLINGS = {"uniform": [], "loader_shards": ["--replay.sampling", "loader_shards", "--replay.loader-workers", "2",
                                             "--replay.loader-refresh", "150"]}


@pytest.mark.parametrize("sampling", sorted(SAMPLINGS))
@pytest.mark.slow
def test_resume_continues_as_if_uninterrupted(tmp_path: Path, sampling: str):
    full, split = tmp_path / "full", tmp_path / "split"
    extra = SAMPLINGS[sampling]
    assert main(pretrain_args(full, 2000, agent="fb", extra=extra)) == 0
    assert main(pretrain_args(split, 1000, agent="fb", extra=extra)) == 0
    assert main(pretrain_args(split, 2000, agent="fb", extra=["--resume", *extra])) == 0
    assert json.loads((split / "config.json").read_text())["replay"]["sampling"] == sampling
    a, b = _snapshot_tensors(full, 2000), _snapshot_tensors(split, 2000)
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    full_metrics = (full / "metrics" / "train.jsonl").read_text().splitlines()
    split_metrics = (split / "metrics" / "train.jsonl").read_text().splitlines()
    strip = lambda lines: [{k: v for k, v in json.loads(x).items() if not k.startswith("fps")}  # noqa: E731
                           for x in lines]
    assert strip(full_metrics) == strip(split_metrics)


def test_nan_loss_stops_and_keeps_last_good_checkpoint(tmp_path: Path):
    """A NaN ridge (which the CLI refuses; set here behind its back) poisons the implicit reward of
    the first update after the first checkpoint: the error names the step, the ridge option and
    the checkpoint that is really there."""
    from dvfb.core.errors import NonFiniteLossError
    from dvfb.workflows.pretrain import pretrain
    from tiny import tiny_run_config

    run_dir = tmp_path / "nan"
    config = tiny_run_config("fb", frames=3000, seed_frames=1000)
    object.__setattr__(config.fb, "cov_ridge", float("nan"))
    with pytest.raises(NonFiniteLossError) as exc:
        pretrain(config, run_dir, progress=False)
    message = str(exc.value)
    assert "non-finite" in message and "fb_q_loss" in message and "step 1000" in message
    assert "--fb.cov-ridge" in message and "resume checkpoint of step 1000 is intact" in message
    assert latest_checkpoint(run_dir).name == "resume_1000.pt"
    assert load_checkpoint(run_dir)["step"] == 1000
    assert not (run_dir / "snapshots" / "snapshot_3000.pt").exists()


# ---------------------------------------------------------------------------------------------
# Bad input: a message naming the problem, exit 2, nothing overwritten


def test_existing_run_is_not_overwritten(dvfb_maze_run: Path, capsys):
    before = (dvfb_maze_run / "config.json").read_bytes()
    assert main(pretrain_args(dvfb_maze_run, 1000)) == 2
    assert "already exists" in capsys.readouterr().err
    assert (dvfb_maze_run / "config.json").read_bytes() == before
    assert (dvfb_maze_run / "snapshots" / "snapshot_2000.pt").is_file()


def test_zeroshot_missing_and_corrupt_run(tmp_path: Path, capsys):
    assert main(["zeroshot", str(tmp_path / "nope"), "--task", "walker_walk"]) == 2
    assert "does not exist" in capsys.readouterr().err
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "config.json").write_text("{not json")
    assert main(["finetune", str(corrupt), "--task", "walker_walk"]) == 2
    assert "corrupt" in capsys.readouterr().err
    assert (corrupt / "config.json").read_text() == "{not json"


def test_corrupt_snapshot(dvfb_maze_run: Path, tmp_path: Path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(dvfb_maze_run, copy)
    (copy / "snapshots" / "snapshot_2000.pt").write_bytes(b"truncated")
    assert main(["zeroshot", str(copy), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE]) == 2
    assert "snapshot_2000.pt" in capsys.readouterr().err


def test_task_from_another_domain(dvfb_maze_run: Path, capsys):
    assert main(["zeroshot", str(dvfb_maze_run), "--task", "walker_walk"]) == 2
    err = capsys.readouterr().err
    assert "walker_walk" in err and "point_mass_maze" in err and "point_mass_maze_reach_top_left" in err
    assert main(["zeroshot", str(dvfb_maze_run), "--task", "walker_moonwalk"]) == 2
    assert "walker_walk" in capsys.readouterr().err  # lists the valid names


@pytest.mark.slow
def test_snapshot_from_another_agent_or_config(dvfb_maze_run: Path, tmp_path: Path, capsys):
    fb_run = tmp_path / "fb"
    assert main(pretrain_args(fb_run, 1000, agent="fb")) == 0
    mixed = tmp_path / "mixed"
    shutil.copytree(dvfb_maze_run, mixed)
    shutil.copy(fb_run / "snapshots" / "snapshot_1000.pt", mixed / "snapshots" / "snapshot_2000.pt")
    assert main(["zeroshot", str(mixed), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE]) == 2
    assert "agent 'fb'" in capsys.readouterr().err
    config = json.loads((mixed / "config.json").read_text())
    config["agent"] = "fb"
    config["fb"]["hidden_dim"] = 64
    for section in ("exploration", "icm_apt", "proto", "cic"):  # DVFB's own sections
        config.pop(section)
    (mixed / "config.json").write_text(json.dumps(config))
    assert main(["zeroshot", str(mixed), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE]) == 2
    assert "another configuration" in capsys.readouterr().err


def test_resume_with_other_config_is_refused(dvfb_maze_run: Path, capsys):
    assert main(pretrain_args(dvfb_maze_run, 3000, extra=["--resume", "--exploration.alpha", "50"])) == 2
    assert "exploration" in capsys.readouterr().err


def test_unknown_preset_and_option_values(tmp_path: Path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["pretrain", "--preset", "huge", "--run-dir", str(tmp_path / "x")])
    assert exc.value.code == 2
    assert "huge" in capsys.readouterr().err
    assert main(pretrain_args(tmp_path / "y", 1000, extra=["--fb.backward-input", "future"])) == 2
    assert "--fb.backward-input 'future'" in capsys.readouterr().err
    assert main(pretrain_args(tmp_path / "z", 1000, extra=["--domain", "jaco"])) == 2
    assert "walker" in capsys.readouterr().err
    assert not (tmp_path / "y").exists() and not (tmp_path / "z").exists()


@pytest.mark.slow
def test_cli_help_and_tasks_as_a_real_process():
    """The installed entry point runs as a separate process (what a user types)."""
    out = subprocess.run([sys.executable, "-m", "dvfb", "tasks"], capture_output=True, text=True, check=True).stdout
    for name in ("walker_flip", "quadruped_jump", "hopper_flip_backward", "cheetah_walk_backward",
                 "point_mass_maze_reach_bottom_right"):
        assert name in out
    help_text = subprocess.run([sys.executable, "-m", "dvfb", "pretrain", "--help"], capture_output=True,
                               text=True, check=True).stdout
    assert "--fb.hidden-dim" in help_text and "(default: 256)" in help_text and "--exploration.alpha" in help_text


@pytest.mark.slow
@pytest.mark.e2e
def test_code_preset_runs_end_to_end(tmp_path: Path):
    """The authors' constants: B on their state pairings (needs s'' from replay), alpha 50, RND on s_t."""
    run_dir = tmp_path / "code"
    args = pretrain_args(run_dir, 2000)
    args[args.index("pretrain") + 1:args.index("pretrain") + 1] = ["--preset", "code"]
    assert main(args) == 0
    config = json.loads((run_dir / "config.json").read_text())
    assert config["fb"]["backward_input"] == "code_exact" and config["exploration"]["alpha"] == 50.0
    assert config["exploration"]["rnd_input"] == "obs" and config["finetune"]["qf_coef"] == 50.0
    assert main(["zeroshot", str(run_dir), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE]) == 0
    result = json.loads((run_dir / "zeroshot" / "point_mass_maze_reach_top_left.json").read_text())
    assert len(result["z"]) == 16


@pytest.mark.slow
def test_finetune_resume_continues_as_if_uninterrupted(dvfb_maze_run: Path, tmp_path: Path):
    run = copy_run(dvfb_maze_run, tmp_path)  # it writes results: on a copy of the session's run
    common = ["--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE, "--finetune.seed-frames", "400",
              "--finetune.eval-every", "1000", "--finetune.eval-episodes", "1", "--finetune.checkpoint-every", "1000",
              "--no-progress"]
    assert main(["finetune", str(run), "--name", "full", "--finetune.frames", "2000", *common]) == 0
    assert main(["finetune", str(run), "--name", "split", "--finetune.frames", "1000", *common]) == 0
    assert main(["finetune", str(run), "--name", "split", "--finetune.frames", "2000", "--resume", *common]) == 0
    full = json.loads((run / "finetune" / "full" / "curve.json").read_text())
    split = json.loads((run / "finetune" / "split" / "curve.json").read_text())
    assert [p["frames"] for p in split["curve"]] == [0, 1000, 2000]
    assert full["curve"] == split["curve"]
    a = load_checkpoint(run / "finetune" / "full")["finetuner"]
    b = load_checkpoint(run / "finetune" / "split")["finetuner"]
    for part in ("actor", "finetuner"):
        assert a[part].keys() == b[part].keys()
        for key in a[part]:
            assert torch.equal(a[part][key], b[part][key]), (part, key)


def test_the_demo_ranks_dvfb_and_random_only_when_two_standard_errors_apart():
    from dvfb.cli.demo import demo_table, mean_and_error, verdict

    assert mean_and_error([10.0, 12.0, 14.0]) == pytest.approx((12.0, 2.0 / np.sqrt(3)))
    assert verdict([10.0, 12.0, 14.0], [0.0, 1.0, 2.0]) == "DVFB above random"
    assert verdict([0.0, 1.0, 2.0], [10.0, 12.0, 14.0]) == "DVFB below random"
    # 15 ± 5 against 15.5 ± 0.5: the difference is well inside two standard errors.
    assert verdict([10.0, 20.0], [15.0, 16.0]) == "not distinguishable"
    # Exactly two standard errors apart is not apart: 2 * hypot(1, 0) = 2.
    assert verdict([1.0, 3.0], [0.0, 0.0]) == "not distinguishable"
    table = demo_table([("walker_walk", [10.0, 12.0, 14.0], [0.0, 1.0, 2.0])]).splitlines()
    assert table[-1].split() == ["walker_walk", "12.0", "±", "1.2", "1.0", "±", "0.6", "DVFB", "above", "random"]


@pytest.mark.parametrize("flags, says", [
    (["--gif-task", "walker_dance"], "--gif-task 'walker_dance' is not a walker task"),
    (["--gif-task", "hopper_hop"], "--gif-task 'hopper_hop' is not a walker task"),
])
def test_the_demo_refuses_bad_input_up_front_and_creates_nothing(tmp_path: Path, flags, says):
    out = tmp_path / "demo"
    done = subprocess.run([sys.executable, "-m", "dvfb", "demo", "--out-dir", str(out), *flags],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and says in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not out.exists()


def test_the_demo_never_replaces_a_directory_it_did_not_make(tmp_path: Path):
    mine = tmp_path / "demo" / "live_pretrain"
    mine.mkdir(parents=True)
    (mine / "notes.txt").write_text("mine")
    done = subprocess.run([sys.executable, "-m", "dvfb", "demo", "--out-dir", str(tmp_path / "demo")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "does not look like a dvfb run directory" in done.stderr, done.stderr
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == ["live_pretrain"]
    assert (mine / "notes.txt").read_text() == "mine"


@pytest.mark.slow
@pytest.mark.e2e
def test_demo_runs_the_bundled_agent_a_gif_and_a_live_pretraining(tmp_path: Path):
    """`dvfb demo` (the README's first command) with tiny budgets, rendering with software OpenGL."""
    out = tmp_path / "demo"
    done = subprocess.run([sys.executable, "-m", "dvfb", "demo", "--out-dir", str(out), "--frames", "1200",
                           "--inference-steps", "200", "--eval-episodes", "2", "--gif-steps", "20", "--no-progress"],
                          capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"})
    assert done.returncode == 0, done.stderr
    rows = [line.split() for line in done.stdout.splitlines() if line.startswith("walker_")]
    assert [r[0] for r in rows] == ["walker_stand", "walker_walk", "walker_run", "walker_flip"]
    bundled = out / "pretrained_dvfb_walker"
    for row in rows:  # task, DVFB mean ± s.e., random mean ± s.e., the verdict
        assert row[2] == row[5] == "±" and " ".join(row[7:]) in (
            "not distinguishable", "DVFB above random", "DVFB below random")
        result = json.loads((bundled / "zeroshot" / f"{row[0]}.json").read_text())
        returns = np.asarray(result["returns"])
        assert len(returns) == 2 and result["inference"]["steps"] == 200
        assert (row[1], row[3]) == (f"{returns.mean():.1f}", f"{returns.std(ddof=1) / np.sqrt(2):.1f}")
    provenance = json.loads((bundled / "provenance.json").read_text())
    assert "dvfb pretrain" in provenance["command"]
    assert (out / "walker_walk.gif").stat().st_size > 0
    assert json.loads((out / "live_pretrain" / "pretrain_summary.json").read_text())["frames"] == 1200
