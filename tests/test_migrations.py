"""Run directories of earlier releases (docs/architecture.md, "Run directories"): every run directory
and checkpoint the previous release wrote loads, or is refused by the migrations module with one line
naming its format version.

``tests/fixtures/v0.1.0/`` holds run directories that dvfb 0.1.0 (commit a2f5f5f) wrote with the
commands of ``tests/fixtures/v0.1.0/README.md``: a tiny DVFB run on the maze (snapshots at 1,000 and
1,200 frames, its resume checkpoint of step 1,000, a zero-shot result and a fine-tuning run) and a
tiny RND run.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import dvfb
from dvfb.cli import main
from dvfb.core.errors import CheckpointError
from dvfb.runs import load_checkpoint, save_checkpoint
from dvfb.runs.layout import FINETUNE, PRETRAIN, FinetuneRun, PretrainRun, run_kind
from dvfb.runs.migrations import check_resume_format, check_snapshot_format, migrate_training_state
from tiny import tiny_flags

FIXTURES = Path(__file__).parent / "fixtures" / "v0.1.0"
MAZE = "point_mass_maze_reach_top_left"
# The flags the fixtures were made with (fixtures/v0.1.0/README.md): a resume repeats them.
TINY_FB = tiny_flags("fb")
TINY_EX = tiny_flags("dvfb", ("exploration",))
COMMON = ["--domain", "point_mass_maze", "--seed-frames", "500", "--update-every", "4", "--checkpoint-every", "1000",
          "--log-every", "250", "--replay-capacity", "2000", "--snapshot-frames", "1000", "--torch-threads", "1",
          "--no-progress"]
INFERENCE = ["--inference.steps", "1000", "--inference.random-action-steps", "500", "--inference.samples", "500"]
FINETUNE_FLAGS = ["--finetune.seed-frames", "500", "--finetune.eval-every", "1000", "--finetune.eval-episodes", "1",
            "--finetune.checkpoint-every", "1000", "--finetune.replay-capacity", "2000", "--no-progress"]


@pytest.fixture
def old_runs(tmp_path) -> Path:
    """A writable copy of the fixtures."""
    return Path(shutil.copytree(FIXTURES, tmp_path / "v0.1.0"))


def test_the_runs_of_the_previous_release_are_read_with_their_records(old_runs):
    dvfb_run, rnd_run = old_runs / "dvfb_maze", old_runs / "rnd_maze"
    assert run_kind(dvfb_run) == PRETRAIN and run_kind(dvfb_run / "finetune" / MAZE) == FINETUNE
    assert "kind" not in json.loads((dvfb_run / "meta.json").read_text())  # told apart by the config
    run = PretrainRun.open(dvfb_run)
    assert run.config.agent == "dvfb" and run.snapshot_frames() == [1000, 1200] and run.is_finished()
    result = run.read_zeroshot_result(MAZE)
    assert result.task == MAZE and result.snapshot_frames == 1200 and len(result.returns) == 1
    (finetune,) = run.finetune_runs()
    assert finetune.is_finished() and finetune.curve().curve[-1]["frames"] == 1200
    # It recorded no protocol (before --protocol): it is the method's own fine-tuner, by its name.
    assert "protocol" not in json.loads((finetune.path / "config.json").read_text())
    assert finetune.config.protocol == "dual_value" and finetune.config.own_protocol
    assert finetune.parent().path == run.path
    assert PretrainRun.open(rnd_run).resume_state()["kind"] == "pretrain_resume"


def test_a_model_of_the_previous_release_loads_and_acts(old_runs):
    model = dvfb.load(old_runs / "dvfb_maze")
    assert model.snapshot == 1200 and not hasattr(model.model, "optimizers")
    obs = np.zeros(4, np.float32)
    z = model.infer_z(goal=obs)
    assert model.act(obs, z).shape == (2,)
    assert dvfb.load(old_runs / "rnd_maze").act(obs).shape == (2,)


@pytest.mark.slow
def test_the_commands_continue_the_runs_of_the_previous_release(old_runs, capsys):
    dvfb_run, rnd_run = old_runs / "dvfb_maze", old_runs / "rnd_maze"
    # A new zero-shot result beside the old one, and a report over both releases' records.
    assert main(["zeroshot", str(rnd_run), "--task", MAZE, "--overwrite", "--inference.eval-episodes", "1",
                 "--no-progress"]) == 0
    assert main(["report", str(old_runs), "--out", str(old_runs / "report")]) == 0
    assert "dvfb" in (old_runs / "report" / "report.md").read_text()
    # Pre-training continues from the old resume checkpoint (step 1000) to a larger budget, and the
    # old fine-tuning run continues from its checkpoint.
    assert main(["pretrain", "--agent", "dvfb", *COMMON, "--seed", "0", "--run-dir", str(dvfb_run), *TINY_FB,
                 *TINY_EX, "--frames", "1500", "--resume"]) == 0
    assert PretrainRun.open(dvfb_run).finished_frames() == 1500
    assert main(["finetune", str(dvfb_run), "--task", MAZE, "--snapshot", "1200", *INFERENCE, *FINETUNE_FLAGS,
                 "--finetune.frames", "1500", "--resume"]) == 0
    assert FinetuneRun.open(dvfb_run / "finetune" / MAZE).finished_frames() == 1500
    assert json.loads((dvfb_run / "finetune" / MAZE / "config.json").read_text())["protocol"] == "dual_value"


def test_older_formats_are_refused_with_one_line_naming_their_format(old_runs, capsys):
    run = old_runs / "rnd_maze"
    state = load_checkpoint(run)
    state["format"] = 1
    save_checkpoint(run, state, "resume_1000")
    with pytest.raises(CheckpointError, match="format 1.*resumes format 2"):
        check_resume_format(state, run)
    code = main(["pretrain", "--agent", "rnd", *COMMON, "--seed", "1", "--run-dir", str(run), "--ddpg.hidden-dim", "32",
                 "--ddpg.batch-size", "32", "--rnd.hidden-dim", "32", "--rnd.rep-dim", "16", "--frames", "1500",
                 "--resume"])
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert code == 2 and len(errors) == 1 and "format 1" in errors[0]
    snapshot = run / "snapshots" / "snapshot_1200.pt"
    state = torch.load(snapshot, weights_only=True)
    state["format"] = 3
    torch.save(state, snapshot)
    with pytest.raises(CheckpointError, match="format 3, newer than this dvfb reads"):
        check_snapshot_format(state, snapshot)
    assert main(["zeroshot", str(run), "--task", MAZE, "--overwrite", "--no-progress"]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert len(errors) == 1 and "snapshot format 3" in errors[0]


def test_training_states_with_renamed_modules_are_migrated():
    old = {"modules": {"contrastive.state_net.0.weight": 1, "contrastive.skill_net.0.bias": 2, "actor.w": 3},
           "optimizers": {}}
    new = migrate_training_state("dvfb", old)
    assert set(new["modules"]) == {"contrastive.encoders.state_net.0.weight", "contrastive.encoders.skill_net.0.bias",
                                   "actor.w"}
    assert migrate_training_state("dvfb", new) == new and migrate_training_state("fb", old) is old
