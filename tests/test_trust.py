"""Trustworthy runs: bad inputs, signals, the run-directory lock, disk errors, resume hygiene,
numerics and progress (issue "Trustworthy runs").

Every bad input ends in one line naming the problem, exit status 2 and no run directory. Signals and
the lock use real subprocesses; the disk-full and read-only cases a real tmpfs mount (root, as in
CI: a machine where it cannot be mounted fails these tests loudly).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dvfb.agents.fb import FBAgent
from dvfb.cli import main
from dvfb.core.errors import NonFiniteLossError
from dvfb.data import Batch
from dvfb.runs import RunDir, latest_checkpoint, load_checkpoint, load_snapshot, save_checkpoint
from dvfb.runs.layout import FinetuneRun
from dvfb.runs.machine import cores
from dvfb.training.metric_windows import MetricWindow
from tiny import ACT, MAZE_SCHEDULE, OBS, run_cli, tiny_config, tiny_flags

TINY = [*tiny_flags("fb"), "--log-every", "250", "--torch-threads", "1"]
FAST_INFERENCE = ["--inference.steps", "200", "--inference.random-action-steps", "100",
                  "--inference.samples", "200", "--inference.eval-episodes", "1"]
DVFB = [sys.executable, "-m", "dvfb"]


def pretrain_argv(run_dir: Path, frames: int, *extra: str) -> list[str]:
    return ["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--frames", str(frames), "--run-dir", str(run_dir),
            "--no-progress", *TINY, *extra]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("trust") / "fb"
    assert main(pretrain_argv(run_dir, 1000)) == 0
    return run_dir


# ---------------------------------------------------------------------------------------------
# Bad inputs: one line, exit 2, nothing created

BAD_PRETRAIN = [
    (["--frames", "0"], "--frames 0 is out of range: it must be >= 1"),
    (["--frames", "-5"], "--frames -5 is out of range"),
    (["--frames", "400"], "--frames 400 must be larger than --seed-frames 500"),
    (["--fb.batch-size", "0"], "--fb.batch-size 0 is out of range: it must be >= 2"),
    (["--fb.hidden-dim", "0"], "--fb.hidden-dim 0 is out of range"),
    (["--fb.lr", "-1"], "--fb.lr -1.0 is out of range: it must be > 0"),
    (["--fb.lr", "nan"], "--fb.lr nan is not a finite number"),
    (["--update-every", "0"], "--update-every 0 is out of range"),
    (["--log-every", "0"], "--log-every 0 is out of range"),
    (["--seed", "-1"], "--seed -1 is out of range: it must be >= 0"),
    (["--fb.z-dim", "0"], "--fb.z-dim 0 is out of range"),
    (["--replay-capacity", "1000000000000"], "lower --replay-capacity"),
    (["--replay-capacity", "500"], "--replay-capacity 500 must be at least the episode length"),
    (["--device", "cuda"], "device 'cuda' was requested but torch sees no CUDA device"),
    (["--resume", "--overwrite"], "--resume and --overwrite contradict each other"),
    (["--preset", "fbee"], "preset 'fbee' holds the constants of fbee; 'fb' has the presets small, paper, code"),
]


@pytest.mark.parametrize("extra,message", BAD_PRETRAIN, ids=[" ".join(e) for e, _ in BAD_PRETRAIN])
def test_bad_pretrain_option_is_one_line_exit_2_and_creates_nothing(extra, message, tmp_path, capsys):
    if "--device" in extra and torch.cuda.is_available():
        pytest.fail("this test needs a machine without CUDA")
    run_dir = tmp_path / "run"
    assert main(pretrain_argv(run_dir, 1000, *extra)) == 2
    err = capsys.readouterr().err.strip()
    assert message in err, err
    assert len(err.splitlines()) <= 2 and "Traceback" not in err  # the memory estimate may precede it
    assert not run_dir.exists()


BAD_ZEROSHOT = [
    (["--inference.eval-episodes", "0"], "--inference.eval-episodes 0 is out of range"),
    (["--inference.reward-quantile", "2"], "--inference.reward-quantile 2.0 is out of range: it must be >= 0 and <= 1"),
    (["--inference.random-action-steps", "300"], "must be at most --inference.steps 200"),
    (["--skill-source", "goal", "--goal", "1,2,3"], "--goal has 3 values but point_mass_maze observations have 4"),
    (["--protocol", "latent_search"], "--protocol latent_search is not a zero-shot protocol that runs in the task; "
                                      "choose one of online_inference"),
    (["--resume"], "--resume continues a zero-shot protocol that runs in the task: pass --protocol with it"),
    (["--protocol", "online_inference"], "--inference.* options do not apply to --protocol online_inference"),
    (["--protocol", "online_inference", "--goal", "1,2,3,4"], "--goal does not apply to --protocol online_inference"),
]


@pytest.mark.parametrize("extra,message", BAD_ZEROSHOT, ids=[" ".join(e) for e, _ in BAD_ZEROSHOT])
@pytest.mark.slow
def test_bad_zeroshot_option_writes_nothing(finished_run, extra, message, capsys):
    argv = ["zeroshot", str(finished_run), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE, *extra]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (finished_run / "zeroshot").exists()


BAD_PROTOCOL = [
    (["finetune", "--task", "point_mass_maze_reach_top_left", "--protocol", "urlb"],
     "--protocol urlb is not a protocol of 'fb'; choose one of dual_value, latent_search, online_inference"),
    (["finetune", "--task", "point_mass_maze_reach_top_left", "--protocol", "latent_search", "--finetune.eta", "1"],
     "--finetune.eta is not an option of the latent_search protocol; it is an option of dual_value (--protocol)"),
    (["finetune", "--task", "point_mass_maze_reach_top_left", "--finetune.method", "rela"],
     "--finetune.method is not an option of the dual_value protocol; it is an option of latent_search "
     "(--protocol)"),
    (["finetune", "--task", "point_mass_maze_reach_top_left", "--finetune.cov-ridge", "0.1", "--finetune.rule", "ts"],
     "--finetune.rule is not an option of the dual_value protocol; it is an option of online_inference "
     "(--protocol)"),
    (["finetune", "--task", "point_mass_maze_reach_top_left", "--finetune.init-critic", "all"],
     "--finetune.init-critic is not an option of the dual_value protocol; it is an option of urlb (--protocol)"),
    (["finetune", "--task", "point_mass_maze_reach_top_left", "--protocol", "online_inference",
      "--finetune.beta", "-1"], "--finetune.beta -1.0 is out of range"),
    (["zeroshot", "--task", "point_mass_maze_reach_top_left", "point_mass_maze_reach_top_right",
      "--protocol", "online_inference"], "--protocol online_inference runs in one task at a time"),
]


@pytest.mark.parametrize("argv,message", BAD_PROTOCOL, ids=[" ".join(a[3:]) for a, _ in BAD_PROTOCOL])
def test_bad_protocol_choices_are_one_line_and_create_nothing(finished_run, argv, message, capsys):
    assert main([argv[0], str(finished_run), *argv[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not (finished_run / "finetune").exists() and not (finished_run / "zeroshot").exists()


def test_verbose_flag_after_the_subcommand(finished_run, tmp_path, capsys):
    run = Path(shutil.copytree(finished_run, tmp_path / "copy"))  # the module's run stays without results
    argv = ["zeroshot", str(run), "--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE, "-v",
            "--overwrite", "--no-progress"]
    assert main(argv) == 0
    assert (run / "zeroshot" / "point_mass_maze_reach_top_left.json").is_file()


# ---------------------------------------------------------------------------------------------
# Resume hygiene


def test_resume_of_a_finished_run_is_a_no_op(finished_run, capsys):
    summary = (finished_run / "pretrain_summary.json").read_text()
    config = (finished_run / "config.json").read_text()
    assert main(pretrain_argv(finished_run, 1000, "--resume")) == 0
    assert "already finished at 1000 frames" in capsys.readouterr().err
    assert (finished_run / "pretrain_summary.json").read_text() == summary
    assert (finished_run / "config.json").read_text() == config


def test_failed_resume_changes_no_file(finished_run, tmp_path, capsys):
    run = tmp_path / "copy"
    import shutil

    shutil.copytree(finished_run, run)
    checkpoint = latest_checkpoint(run)
    checkpoint.write_bytes(os.urandom(2048))  # unreadable
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert main(pretrain_argv(run, 2000, "--resume")) == 2
    err = capsys.readouterr().err
    assert "cannot resume" in err and "truncated or corrupt" in err
    after = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert after == before  # config.json still says 1000 frames; nothing else written


def test_orphaned_checkpoint_is_removed_on_the_next_start(finished_run, tmp_path):
    import shutil

    run = tmp_path / "orphan"
    shutil.copytree(finished_run, run)
    orphan = run / "checkpoints" / "resume_500.pt"
    save_checkpoint(run, {"step": 1}, "resume_999", keep_previous=True)  # a kill between move and cleanup
    orphan.write_bytes(b"left behind")
    save_checkpoint(run, {"step": 0}, "keep")  # the pointer moves on; resume_999 becomes an orphan too
    (run / "checkpoints" / "latest").write_text(f"{latest_checkpoint(finished_run).name}\n")
    shutil.copy(latest_checkpoint(finished_run), run / "checkpoints" / latest_checkpoint(finished_run).name)
    assert main(pretrain_argv(run, 2000, "--resume")) == 0
    names = sorted(p.name for p in (run / "checkpoints").glob("*.pt"))
    assert names == ["resume_2000.pt"]


# ---------------------------------------------------------------------------------------------
# Signals and the lock (real processes)


def _spawn(argv: list[str], **env) -> subprocess.Popen:
    return subprocess.Popen([*DVFB, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", **env})


def _wait_for(path: Path, process: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if process.poll() is not None:
            raise AssertionError(f"process ended early: {process.communicate()}")
        if time.monotonic() > deadline:
            process.kill()
            raise AssertionError(f"{path} did not appear in {timeout} s")
        time.sleep(0.05)


def _snapshot_modules(run: Path, frames: int) -> dict:
    return load_snapshot(RunDir(run), f"snapshot_{frames}")["modules"]


def metric_records(run: Path) -> dict[str, list[dict]]:
    """Every metric record of a run, by file, without its speed fields (fps, fps_recent: wall-clock readings)."""
    return {path.name: [{k: v for k, v in json.loads(line).items() if not k.startswith("fps")}
                        for line in path.read_text().splitlines()]
            for path in sorted((run / "metrics").glob("*.jsonl"))}


@pytest.mark.slow
def test_sigterm_checkpoints_and_resume_equals_uninterrupted(tmp_path):
    full, split = tmp_path / "full", tmp_path / "split"
    assert main(pretrain_argv(full, 2000)) == 0
    process = _spawn(pretrain_argv(split, 2000))
    # Once metrics are written the loop is running (updates start at 500 frames).
    _wait_for(split / "metrics" / "train.jsonl", process)
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, err
    assert "SIGTERM received: pre-training stopped at step" in err and "--resume" in err
    state = load_checkpoint(split)
    step = state["step"]
    assert 750 <= step < 2000
    assert latest_checkpoint(split).name == f"resume_{step}.pt"
    assert (state.get("episode_state") is not None) == (step % 1000 != 0)
    assert not (split / "pretrain_summary.json").exists()
    resumed = subprocess.run([*DVFB, *pretrain_argv(split, 2000, "--resume")], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resuming {split} from step {step}" in resumed.stderr
    a, b = _snapshot_modules(full, 2000), _snapshot_modules(split, 2000)
    for key in a:
        for name, tensor in a[key].items():
            assert torch.equal(tensor, b[key][name]), (key, name)
    # The signal cut a metric window: its rows went into the checkpoint, so the logs are the same
    # records at the same steps (docs/methods.md, "Training loop").
    records = metric_records(full)
    assert records["train.jsonl"] and records == metric_records(split)


def test_a_resume_of_a_finished_run_that_lost_its_summary_rebuilds_it(finished_run, tmp_path):
    """Its last checkpoint is at the final step: the resume rebuilds pretrain_summary.json and trains
    nothing, where it used to fail with "--frames 1000 is not beyond the checkpoint's step 1000"."""
    run = shutil.copytree(finished_run, tmp_path / "fb")
    first = json.loads((run / "pretrain_summary.json").read_text())
    (run / "pretrain_summary.json").unlink()
    snapshot = (run / "snapshots" / "snapshot_1000.pt").read_bytes()
    done = run_cli(*pretrain_argv(run, 1000, "--resume"))
    assert done.returncode == 0, done.stderr
    assert "had lost its pretrain_summary.json; rebuilt it from the last checkpoint" in done.stderr
    rebuilt = json.loads((run / "pretrain_summary.json").read_text())
    assert rebuilt["rebuilt"] is True and (rebuilt["frames"], rebuilt["episodes"]) == (first["frames"], first["episodes"])
    assert (run / "snapshots" / "snapshot_1000.pt").read_bytes() == snapshot  # nothing trained
    # Without its final snapshot there is nothing to rebuild from: refused as before, one line.
    (run / "pretrain_summary.json").unlink()
    (run / "snapshots" / "snapshot_1000.pt").unlink()
    refused = run_cli(*pretrain_argv(run, 1000, "--resume"))
    assert refused.returncode == 2 and "is not beyond the checkpoint's step 1000" in refused.stderr
    assert not (run / "pretrain_summary.json").exists()


def _without_threads(argv: list[str]) -> list[str]:
    """``argv`` without its ``--torch-threads N``."""
    at = argv.index("--torch-threads")
    return argv[:at] + argv[at + 2:]


@pytest.mark.slow
def test_a_resume_keeps_the_runs_threads_whatever_the_shells_omp_num_threads(tmp_path):
    """A run made with --torch-threads 1, stopped, and resumed by the same command plus --resume but
    without the thread flag, from a shell whose OMP_NUM_THREADS is 2: it computes with its own one
    thread, keeps config.json's setting, says nothing, and ends as the uninterrupted run does."""
    full, split = tmp_path / "full", tmp_path / "split"
    assert main(pretrain_argv(full, 2000)) == 0  # TINY has --torch-threads 1
    process = _spawn(pretrain_argv(split, 2000))
    _wait_for(split / "metrics" / "train.jsonl", process)
    process.send_signal(signal.SIGTERM)
    _out, err = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, err
    resumed = subprocess.run([*DVFB, *_without_threads(pretrain_argv(split, 2000, "--resume"))], capture_output=True,
                             text=True, env={**os.environ, "OMP_NUM_THREADS": "2"})
    assert resumed.returncode == 0, resumed.stderr
    assert "[threads]" not in resumed.stderr
    assert json.loads((split / "meta.json").read_text())["resumes"][-1]["torch_threads"] == 1
    assert json.loads((split / "config.json").read_text())["torch_threads"] == 1
    a, b = _snapshot_modules(full, 2000), _snapshot_modules(split, 2000)
    for key in a:
        for name, tensor in a[key].items():
            assert torch.equal(tensor, b[key][name]), (key, name)


def test_a_resume_with_other_threads_says_so_in_one_line_and_records_them(tmp_path):
    run = tmp_path / "run"
    assert main(pretrain_argv(run, 1000)) == 0  # TINY has --torch-threads 1
    threads = min(2, cores())
    resumed = run_cli(*_without_threads(pretrain_argv(run, 1500, "--resume")), "--torch-threads", "2")
    assert resumed.returncode == 0, resumed.stderr
    said = [line for line in resumed.stderr.splitlines() if line.startswith("[threads]")]
    if threads == 1:  # a one-CPU machine: the flag is capped back to the run's one thread
        assert len(said) == 1 and "more than the 1 CPU(s)" in said[0]
    else:
        assert said == [f"[threads] resuming {run} with 2 torch thread(s) instead of the 1 it ran with "
                        "(--torch-threads): its numbers may differ from an uninterrupted run's"]
    assert json.loads((run / "config.json").read_text())["torch_threads"] == 2  # recorded, not silently
    assert json.loads((run / "meta.json").read_text())["resumes"][-1]["torch_threads"] == threads


def _interrupted(argv: list[str], watch: Path) -> str:
    """Run ``argv`` in a process, SIGTERM it once ``watch`` (a metrics file) exists, then resume it;
    returns what the stopped process said on stderr."""
    process = _spawn(argv)
    _wait_for(watch, process)
    process.send_signal(signal.SIGTERM)
    _out, err = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM and "SIGTERM received" in err, err
    resumed = subprocess.run([*DVFB, *argv, "--resume"], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    return err


FINETUNE = ["--task", "point_mass_maze_reach_top_left", *FAST_INFERENCE, "--finetune.frames", "2000",
            "--finetune.seed-frames", "250", "--finetune.update-every", "2", "--finetune.eval-every", "1000",
            "--finetune.eval-episodes", "1", "--finetune.checkpoint-every", "1000",
            "--no-progress"]


@pytest.mark.slow
def test_a_signal_changes_no_metric_record_of_a_group_or_a_fine_tuning(finished_run, tmp_path):
    """SIGTERM, then --resume: every member's metric records (and a fine-tuning's, and its curve)
    equal those of a run that was never stopped, fps aside; so do the learners."""
    full, split = str(tmp_path / "full_{seed}"), str(tmp_path / "split_{seed}")
    group = ["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--frames", "2500", "--no-progress", *TINY, "--seeds", "0,1"]
    assert main([*group, "--run-dir", full]) == 0
    err = _interrupted([*group, "--run-dir", split], tmp_path / "split_1" / "metrics" / "train.jsonl")
    # The message names where each member continues, not the folder they share.
    assert f"(runs {tmp_path / 'split_0'}, {tmp_path / 'split_1'})" in err.strip().splitlines()[-1]
    for seed in (0, 1):
        a, b = tmp_path / f"full_{seed}", tmp_path / f"split_{seed}"
        assert metric_records(a)["train.jsonl"] and metric_records(a) == metric_records(b), seed
        for key, modules in _snapshot_modules(a, 2500).items():
            for name, tensor in modules.items():
                assert torch.equal(tensor, _snapshot_modules(b, 2500)[key][name]), (seed, key, name)
    # On a copy: the module's run stays without fine-tunings (a later test copies it and makes its own "full").
    run = Path(shutil.copytree(finished_run, tmp_path / "fb"))
    assert main(["finetune", str(run), *FINETUNE, "--name", "full"]) == 0
    ft = run / "finetune"
    _interrupted(["finetune", str(run), *FINETUNE, "--name", "split"], ft / "split" / "metrics" / "train.jsonl")
    assert metric_records(ft / "full")["train.jsonl"] and metric_records(ft / "full") == metric_records(ft / "split")
    curve = lambda name: json.loads((ft / name / "curve.json").read_text())["curve"]  # noqa: E731
    assert [p["returns"] for p in curve("full")] == [p["returns"] for p in curve("split")]


@pytest.mark.slow
def test_a_second_writer_is_refused_with_the_holders_pid(tmp_path):
    run = tmp_path / "locked"
    first = _spawn(pretrain_argv(run, 100_000))
    _wait_for(run / "metrics" / "train.jsonl", first)
    second = subprocess.run([*DVFB, *pretrain_argv(run, 1000, "--overwrite")], capture_output=True, text=True)
    assert second.returncode == 2
    assert f"is in use by process {first.pid}" in second.stderr
    assert first.poll() is None  # the live run was not deleted under it
    first.send_signal(signal.SIGINT)
    _out, err = first.communicate(timeout=120)
    assert first.returncode == 128 + signal.SIGINT, err
    # The OS released the lock with the process: the next writer takes it over.
    third = subprocess.run([*DVFB, *pretrain_argv(run, 1000, "--overwrite")], capture_output=True, text=True)
    assert third.returncode == 0, third.stderr


# ---------------------------------------------------------------------------------------------
# Disk errors (a real tmpfs)


@pytest.mark.slow
def test_full_disk_during_a_checkpoint_is_one_line_and_keeps_the_previous_one(small_disk, capsys):
    run = small_disk / "run"
    # The first checkpoint (step 1000, small replay) fits; the one at 2000 does not.
    code = main(pretrain_argv(run, 3000, "--replay-capacity", "3000"))
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert code == 2 and "No space left on device" in err, err
    assert "resume checkpoint of step 1000 is intact" in err or "checkpoint" in err
    assert load_checkpoint(run)["step"] == 1000
    assert not any(p.name.startswith(".") and ".tmp-" in p.name for p in (run / "checkpoints").iterdir())


def test_read_only_run_fails_before_the_work(finished_run, small_disk, capsys):
    import shutil

    run = small_disk / "ro"
    shutil.copytree(finished_run, run, ignore=shutil.ignore_patterns("checkpoints", "zeroshot", "tb", "metrics",
                                                                      "finetune"))
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    started = time.monotonic()
    argv = ["zeroshot", str(run), "--task", "point_mass_maze_reach_top_left", "--inference.steps", "5000",
            "--inference.samples", "5000", "--inference.eval-episodes", "3"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "cannot write in" in err and "Read-only file system" in err
    assert time.monotonic() - started < 30  # refused before 8,000 steps of work, not after
    assert main(pretrain_argv(run, 2000, "--resume")) == 2
    assert "Read-only file system" in capsys.readouterr().err


@pytest.mark.slow
def test_read_only_outputs_of_the_report_and_the_analyses_are_one_line(finished_run, small_disk, capsys):
    import shutil

    run = small_disk / "ro"
    shutil.copytree(finished_run, run, ignore=shutil.ignore_patterns("checkpoints", "tb", "metrics", "zeroshot",
                                                                      "analysis", "finetune"))
    assert main(["zeroshot", str(run), "--task", "point_mass_maze_reach_top_left", "--inference.steps", "300",
                 "--inference.random-action-steps", "100", "--inference.samples", "300",
                 "--inference.eval-episodes", "1"]) == 0
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    capsys.readouterr()
    assert main(["report", str(run), "--out", str(small_disk / "report")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot write in" in err and "Read-only file system" in err
    assert not (small_disk / "report").exists()
    started = time.monotonic()
    assert main(["analyze-exploration", str(run), "--skills", "4", "--repeats", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Read-only file system" in err
    assert time.monotonic() - started < 30  # before the rollouts
    assert main(["analyze-value", str(run), "--task", "point_mass_maze_reach_top_left",
                 "--inference.steps", "300", "--inference.random-action-steps", "100", "--inference.samples", "300"]) == 2
    assert "Read-only file system" in capsys.readouterr().err
    sweep_file = run.parent.parent / "sweep.toml"
    sweep_file.write_text('agents = ["fb"]\ndomains = ["point_mass_maze"]\nseeds = [0]\nphases = ["pretrain"]\n')
    for argv in (["random-policy", "--domain", "point_mass_maze", "--episodes", "1", "--output",
                  str(small_disk / "random.json")],
                 ["video", str(run), "--task", "point_mass_maze_reach_top_left", "--out", str(small_disk / "v.gif")],
                 ["sweep", "run", str(sweep_file), "--dir", str(small_disk / "sweep"), "--executor", "debug"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Read-only file system" in err, (argv, err)
    assert sorted(p.name for p in small_disk.iterdir()) == ["ro"]


@pytest.mark.slow
def test_resume_of_a_damaged_run_directory_changes_nothing(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(pretrain_argv(run, 1200, "--checkpoint-every", "1000")) == 0
    import shutil

    shutil.rmtree(run / "tb")
    (run / "tb").write_text("not a directory")
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert main(pretrain_argv(run, 2200, "--checkpoint-every", "1000", "--resume")) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "tb is not a directory" in err
    after = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert {p: b for p, b in after.items() if p.name != ".lock"} == {p: b for p, b in before.items() if p.name != ".lock"}


# ---------------------------------------------------------------------------------------------
# Numerics and progress


def test_singular_covariance_names_the_step_and_the_ridge_option():
    """One output of B is 0 for every state, so Cov(B) has a zero row: the implicit reward is not
    finite, and the read-back names the update's step and the ridge option."""
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    last = agent.backward_map.net[-1]
    with torch.no_grad():
        last.weight[0].zero_()
        last.bias[0].zero_()
    g = torch.Generator().manual_seed(0)
    n = 32
    obs, next_obs = torch.randn(n, OBS, generator=g), torch.randn(n, OBS, generator=g)
    batch = Batch(obs, torch.zeros(n, ACT), torch.zeros(n, 1), torch.full((n, 1), 0.99), next_obs, next_obs, None)
    window = MetricWindow(agent.nonfinite_hint)  # as the training loops build it
    window.add(4321, agent.update(batch))
    with pytest.raises(NonFiniteLossError, match=r"at step 4321.*Cov\(B\) is singular.*--fb.cov-ridge"):
        window.flush()


@pytest.mark.slow
def test_progress_lines_without_a_terminal(tmp_path):
    run = tmp_path / "progress"
    done = subprocess.run([*DVFB, *[a for a in pretrain_argv(run, 1500) if a != "--no-progress"]],
                          capture_output=True, text=True, env={**os.environ, "DVFB_PROGRESS_SECONDS": "0"})
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.startswith("[pretrain fb point_mass_maze] ")]
    progress = [line for line in lines if "frames (" in line]
    assert progress and "frames/s, ETA" in progress[-1] and "1500/1500 frames (100%)" in progress[-1]
    assert any("memory estimate: replay" in line for line in lines)
    assert json.loads((run / "pretrain_summary.json").read_text())["frames"] == 1500


@pytest.mark.parametrize("name", ["..", "../../x", "a/b", ".hidden"])
def test_finetune_name_outside_the_finetune_folder_is_refused_and_nothing_is_deleted(finished_run, name, capsys):
    before = sorted(p.relative_to(finished_run) for p in finished_run.rglob("*"))
    code = main(["finetune", str(finished_run), "--task", "point_mass_maze_reach_top_left", "--name", name,
                 "--overwrite", "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--name" in err[0] and "plain name" in err[0]
    assert sorted(p.relative_to(finished_run) for p in finished_run.rglob("*")) == before
    assert not (finished_run.parent / "x").exists()


def test_random_policy_with_no_episodes_is_refused(tmp_path, capsys):
    out = tmp_path / "random.json"
    with pytest.raises(SystemExit) as exc:
        main(["random-policy", "--domain", "point_mass_maze", "--episodes", "0", "--output", str(out)])
    assert exc.value.code == 2
    assert "argument --episodes: invalid integer >= 1 value: '0'" in capsys.readouterr().err and not out.exists()


def test_non_finite_rewards_or_goals_never_give_a_nan_skill(finished_run):
    import numpy as np

    import dvfb
    from dvfb.core.errors import ConfigError

    model = dvfb.load(finished_run)
    obs = np.zeros((8, 4), np.float32)
    rewards = np.ones(8, np.float32)
    rewards[3] = np.nan
    with pytest.raises(ConfigError, match="non-finite"):
        model.infer_z(obs, obs, rewards)
    with pytest.raises(ConfigError, match="non-finite"):
        model.infer_z(goal=np.array([0.1, np.inf, 0.0, 0.0]))
    with pytest.raises(ConfigError, match="non-finite"):
        model.infer_z(reward_fn=lambda next_obs: np.full(next_obs.shape[0], np.nan))
    assert np.isfinite(model.infer_z(obs, obs, np.ones(8, np.float32)).numpy()).all()


@pytest.mark.parametrize("recorded", ["", None], ids=["empty protocol", "no protocol"])
def test_a_fine_tuning_run_of_the_previous_version_resumes_with_its_fine_tuner_named(finished_run, tmp_path,
                                                                                       recorded):
    """A fine-tuning run of the method's own fine-tuner whose config.json records it as older
    versions did (protocol "", or none at all) loads as that fine-tuner's, resumes, and ends where a
    run that was never stopped ends; its config then names the fine-tuner."""
    run = Path(shutil.copytree(finished_run, tmp_path / "copy"))
    schedule = [*FINETUNE[:FINETUNE.index("--finetune.frames")], *FINETUNE[FINETUNE.index("--finetune.frames") + 2:]]
    assert main(["finetune", str(run), *schedule, "--finetune.frames", "2000", "--name", "full"]) == 0
    assert main(["finetune", str(run), *schedule, "--finetune.frames", "1000", "--name", "old"]) == 0
    config_path = run / "finetune" / "old" / "config.json"
    config = json.loads(config_path.read_text())
    assert config["protocol"] == "dual_value"  # what this version records
    if recorded is None:
        del config["protocol"]
    else:
        config["protocol"] = recorded
    config_path.write_text(json.dumps(config))
    assert FinetuneRun.open(config_path.parent).config.protocol == "dual_value"
    assert main(["finetune", str(run), *schedule, "--finetune.frames", "2000", "--name", "old", "--resume"]) == 0
    assert json.loads(config_path.read_text())["protocol"] == "dual_value"
    curve = lambda name: json.loads((run / "finetune" / name / "curve.json").read_text())  # noqa: E731
    assert "protocol" not in curve("old")  # a curve names only a fine-tuner chosen instead of the method's
    assert [p["returns"] for p in curve("old")["curve"]] == [p["returns"] for p in curve("full")["curve"]]
    assert [p["frames"] for p in curve("old")["curve"]] == [0, 1000, 2000]


def test_a_pointer_to_a_missing_checkpoint_deletes_nothing_on_resume(finished_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "copy"
    shutil.copytree(finished_run, run)
    checkpoints = run / "checkpoints"
    kept = sorted(p.name for p in checkpoints.glob("*.pt"))
    assert kept
    (checkpoints / "latest").write_text("resume_999999.pt")
    assert main(pretrain_argv(run, 2000, "--resume")) == 2
    assert "resume_999999" in capsys.readouterr().err
    assert sorted(p.name for p in checkpoints.glob("*.pt")) == kept  # the good checkpoint survives


def test_a_fine_tuning_skill_option_the_method_cannot_take_is_refused_before_any_work(tmp_path, capsys):
    run = tmp_path / "diayn"
    argv = ["pretrain", "--agent", "diayn", *MAZE_SCHEDULE, "--frames", "1000", "--run-dir", str(run), "--no-progress",
            "--seed-frames", "500", "--update-every", "4", "--ddpg.hidden-dim", "32", "--ddpg.batch-size", "32",
            "--diayn.hidden-dim", "32", "--torch-threads", "1"]
    assert main(argv) == 0
    for skill, message in (("prior_mean", "needs a box prior"), ("regressed", "no task regression")):
        code = main(["finetune", str(run), "--task", "point_mass_maze_reach_top_left", "--finetune.skill", skill,
                     "--no-progress"])
        assert code == 2 and message in capsys.readouterr().err
        assert not (run / "finetune").exists()


def test_api_inputs_of_the_wrong_shape_are_named(finished_run):
    import numpy as np

    import dvfb
    from dvfb.core.errors import ConfigError

    model = dvfb.load(finished_run)
    z = model.infer_z(np.zeros((8, 4), np.float32), np.zeros((8, 4), np.float32), np.ones(8, np.float32))
    with pytest.raises(ConfigError, match="obs has shape \\(5,\\).*4 values"):
        model.act(np.zeros(5, np.float32), z)
    with pytest.raises(ConfigError, match="z has 3 values"):
        model.act(np.zeros(4, np.float32), np.zeros(3, np.float32))
    with pytest.raises(ConfigError, match="obs has shape \\(8, 5\\)"):
        model.infer_z(np.zeros((8, 5), np.float32), np.zeros((8, 5), np.float32), np.ones(8, np.float32))
    with pytest.raises(ConfigError, match="goal has 2 values but point_mass_maze observations have 4"):
        model.infer_z(goal=[0.1, 0.1])
    with pytest.raises(ConfigError, match="goal has shape \\(2, 4\\)"):
        model.infer_z(goal=np.zeros((2, 4)))
    with pytest.raises(ConfigError, match="goal must be numbers"):
        model.infer_z(goal="top left")
    assert model.infer_z(goal=np.zeros((1, 4))).shape == z.shape
    assert model.act(np.zeros(4, np.float32), z).shape == (2,)


@pytest.mark.parametrize("command", [["zeroshot", "RUN", "--task", "point_mass_maze_reach_top_left"],
                                     ["finetune", "RUN", "--task", "point_mass_maze_reach_top_left"],
                                     ["analyze-exploration", "RUN"], ["random-policy", "--domain", "point_mass_maze"]])
@pytest.mark.parametrize("seed", ["-1", "4294967296"])
def test_a_seed_outside_0_to_2_32_is_one_line_exit_2(finished_run, command, seed, capsys):
    argv = [str(finished_run) if part == "RUN" else part for part in command] + ["--seed", seed]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--seed" in err[-1] and "from 0 to 4294967295" in err[-1]


ARGPARSE_ONE_LINE = [
    (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--processes", "two"],
     "argument --processes: invalid int value: 'two'"),
    (["export", "RUN", "--out", "OUT", "--inference-size", "0"], "argument --inference-size: invalid integer >= 1"),
    (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--fbee.uncertainty", "f"],
     "--fbee.uncertainty is an option of fbee, dvfb_fbee, not of --agent fb"),
    (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--fbee.uncertainty=f"], "--fbee.uncertainty is an option of fbee"),
    (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--no-such-flag", "1"], "unrecognized arguments: --no-such-flag 1"),
    (["zeroshot", "RUN", "--task", "point_mass_maze_reach_top_left", "--seed", "x"], "argument --seed: invalid seed"),
    (["report", "RUN"], "the following arguments are required: --out"),
]


@pytest.mark.parametrize("argv,message", ARGPARSE_ONE_LINE, ids=[" ".join(a[-2:]) for a, _ in ARGPARSE_ONE_LINE])
def test_argparse_errors_are_one_line_naming_the_flag_and_create_nothing(finished_run, tmp_path, argv, message,
                                                                       capsys):
    out = tmp_path / "out"
    argv = [str(finished_run) if a == "RUN" else str(out) if a == "OUT" else a for a in argv]
    before = sorted(p.relative_to(finished_run) for p in finished_run.rglob("*"))
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--run-dir", str(out)] if argv[0] == "pretrain" else argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and err[0].startswith(f"dvfb {argv[0]}: error: "), err
    assert "--help" in err[0]  # where the options are listed, instead of argparse's usage
    assert not out.exists() and sorted(p.relative_to(finished_run) for p in finished_run.rglob("*")) == before


def test_seeds_and_integer_options_out_of_range_are_one_line_exit_2_with_nothing_created(finished_run, tmp_path,
                                                                                         capsys):
    """Every seed (flags, config fields, sweep grids) and every integer reaches numpy and torch
    only inside its range: 0 .. 2**32 - 1 for seeds, >= 1 for counts, 64 bits for any integer."""
    out = tmp_path / "out"
    argparse_cases = [
        (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--seeds", "0,4294967296", "--run-dir", str(out / "{seed}")],
         "--seeds"),
        (["report", str(finished_run), "--out", str(out), "--bootstrap-seed", "-1"], "--bootstrap-seed"),
        (["report", str(finished_run), "--out", str(out), "--bootstrap-samples", "0"], "--bootstrap-samples"),
        (["video", str(finished_run), "--task", "point_mass_maze_reach_top_left", "--out", str(out / "v.gif"),
          "--width", "0"], "--width"),
    ]
    for argv, flag in argparse_cases:
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
        assert flag in capsys.readouterr().err.strip().splitlines()[-1], argv
    config_cases = [
        (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--seed", "4294967296", "--run-dir", str(out)],
         "--seed 4294967296 is out of range: it must be >= 0 and <= 4294967295"),
        (["pretrain", "--agent", "fb", *MAZE_SCHEDULE, "--fb.hidden-dim", str(2**64), "--run-dir", str(out)],
         "must fit a 64-bit integer"),
        (["finetune", str(finished_run), "--task", "point_mass_maze_reach_top_left", "--finetune.eval-every",
          str(2**70)], "--finetune.eval-every 1180591620717411303424 is out of range: it must fit a 64-bit integer"),
    ]
    before = sorted(p.relative_to(finished_run) for p in finished_run.rglob("*"))
    for argv, message in config_cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)
    assert not out.exists()
    assert sorted(p.relative_to(finished_run) for p in finished_run.rglob("*")) == before


def test_an_n_step_longer_than_the_episodes_is_one_line_and_creates_nothing(tmp_path, capsys):
    run = tmp_path / "rnd"
    argv = ["pretrain", "--agent", "rnd", *MAZE_SCHEDULE, "--frames", "1000", "--run-dir", str(run), "--no-progress",
            "--ddpg.nstep", "5000", "--ddpg.hidden-dim", "32", "--ddpg.batch-size", "32"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "n-step n = 5000" in err[0] and "1000 steps" in err[0]
    assert not run.exists()


def test_more_bad_inputs_are_one_line_exit_2_with_nothing_written(finished_run, tmp_path, capsys):
    report_file = tmp_path / "report.txt"
    report_file.write_text("keep")
    output_dir = tmp_path / "outdir"
    output_dir.mkdir()
    cases = [
        (["zeroshot", str(finished_run), "--task", "point_mass_maze_reach_top_left", "walker_walk"],
         "belongs to domain 'walker'"),
        (["report", str(finished_run), "--out", str(report_file)], "is a file"),
        (["random-policy", "--domain", "point_mass_maze", "--output", str(output_dir), "--overwrite"],
         "is a directory"),
        (["analyze-exploration", str(finished_run), "--cell-size", "nan"], "positive finite"),
        (["pretrain", "--agent", "icm_apt", *MAZE_SCHEDULE, "--run-dir", str(tmp_path / "knn"), "--icm_apt.knn-k",
          "300", "--ddpg.batch-size", "256"],
         "--icm_apt.knn-k 300 is larger than the batch its neighbours are found in (--ddpg.batch-size 256)"),
        (["pretrain", "--agent", "dvfb", *MAZE_SCHEDULE, "--run-dir", str(tmp_path / "knn"), "--exploration.ce-k",
          "40", "--fb.batch-size", "32"], "--exploration.ce-k 40 is larger than the batch"),
    ]
    before = sorted(p.relative_to(finished_run) for p in finished_run.rglob("*"))
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)
    assert sorted(p.relative_to(finished_run) for p in finished_run.rglob("*")) == before
    assert report_file.read_text() == "keep" and list(output_dir.iterdir()) == []
    assert not (tmp_path / "knn").exists()


def test_reward_function_inference_without_a_replay_collects_states_and_says_so(finished_run, tmp_path):
    import shutil

    import numpy as np

    import dvfb
    from dvfb.cli.demo import bundled_demo_run
    from dvfb.workflows.zeroshot import zeroshot

    run = tmp_path / "no_replay"
    shutil.copytree(finished_run, run)
    shutil.rmtree(run / "checkpoints")  # as a shipped snapshot: no resume checkpoint, no replay
    fn = tmp_path / "reward.py"
    fn.write_text("def reward(next_obs):\n    return next_obs[:, 0]\n")
    result = zeroshot(run, "point_mass_maze_reach_top_left", skill_source="reward_fn", reward_fn=f"{fn}:reward",
                      inference={"steps": 1200, "random_action_steps": 200, "eval_episodes": 1}, overwrite=True,
                      progress=False)
    assert "collected" in result["inference_info"]["states"] and np.isfinite(result["z"]).all()
    with_replay = zeroshot(finished_run, "point_mass_maze_reach_top_left", skill_source="reward_fn",
                           reward_fn=f"{fn}:reward", inference={"eval_episodes": 1}, overwrite=True, progress=False)
    assert with_replay["inference_info"]["states"] == "the run's pre-training replay"
    # The README's example shape on the bundled demo agent, which ships without a replay.
    z = dvfb.load(bundled_demo_run()).infer_z(reward_fn=lambda next_obs: next_obs[:, 0], steps=1200,
                                                random_action_steps=200)
    assert z.shape == (50,) and torch.isfinite(z).all()
