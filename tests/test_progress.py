"""Where a run is and when it ends (README.md, "Threads and progress"): the ETA of progress lines
from the last minute's rate, DVFB_PROGRESS_SECONDS, ``dvfb status`` and ``dvfb sweep status`` from
the newest record's rate, and the message of a stopped group naming its members."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from dvfb.cli import main
from dvfb.core.config import to_dict
from dvfb.core.errors import RunInterrupted
from dvfb.runs import RunLock, recent_rate
from dvfb.runs.layout import PretrainRun
from dvfb.runs.presets import preset_config
from dvfb.runs.records import PretrainSummary
from dvfb.training.checkpointing import ResumeCheckpoints
from dvfb.training.metric_windows import MetricWindow
from dvfb.training.progress import Progress, format_eta


def test_the_eta_comes_from_the_last_minute_not_from_the_start(monkeypatch, capsys):
    """10 steps/s for ten minutes, then 1 step/s for two: the line says 1.0 steps/s and the time
    the remaining steps take at that rate (the average since the start, 8.5 steps/s, would promise
    an end 7.5 times too early)."""
    monkeypatch.setenv("DVFB_PROGRESS_SECONDS", "1000000")  # no line on its own: the test asks for one
    bar = Progress(10_000, 0, "pretrain x", None, unit="step")
    start = bar._samples[0][0]
    for second in range(1, 601):
        bar.update(10, now=start + second)
    for second in range(601, 721):
        bar.update(1, now=start + second)
    assert bar.rate(start + 720) == pytest.approx(1.0)
    bar.line(start + 720)
    # (10,000 - 6,120) steps at 1 step/s: 1 h 4 min 40 s.
    assert capsys.readouterr().err.strip() == "[pretrain x] 6120/10000 steps (61%), 1.0 steps/s, ETA 01:04:40"


def test_an_eta_past_a_day_shows_the_days():
    assert format_eta(2 * 86400 + 3 * 3600 + 4 * 60 + 5) == "2d 03:04:05"
    assert format_eta(59) == "00:00:59" and format_eta(float("inf")) == "?"


@pytest.mark.parametrize("value", ["abc", "-1", "inf"])
def test_a_bad_progress_interval_is_one_line_before_any_work(value, monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("DVFB_PROGRESS_SECONDS", value)
    run = tmp_path / "run"
    assert main(["pretrain", "--agent", "fb", "--domain", "point_mass_maze", "--frames", "600", "--seed-frames",
                 "500", "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "DVFB_PROGRESS_SECONDS" in err[0] and repr(value) in err[0]
    assert not run.exists()


def test_the_rate_of_a_record_is_its_recent_one():
    assert recent_rate({"step": 1000, "fps": 40.0, "fps_recent": 0.7}) == 0.7
    assert recent_rate({"step": 1000, "fps": 40.0}) == 40.0  # a record of an older version
    assert recent_rate({"step": 1000}) is None and recent_rate({"fps_recent": 0.0, "fps": 0.0}) is None


def _records(run: Path, *records: dict) -> None:
    (run / "metrics").mkdir(parents=True, exist_ok=True)
    (run / "metrics" / "train.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_sweep_status_takes_its_eta_from_the_recent_rate(tmp_path, capsys):
    """A cell whose pre-training runs (its unit's process is alive: this one) at 1 frame/s now, after
    an average of 100: the ETA is that of 1 frame/s."""
    from dvfb.sweep.spec import SweepConfig

    sweep = tmp_path / "sweep"
    config = SweepConfig(agents=["fb"], domains=["walker"], seeds=[0], phases=["pretrain"],
                         overrides={"frames": [4000], "seed_frames": [500]})
    sweep.mkdir()
    (sweep / "sweep.json").write_text(json.dumps(to_dict(config)))
    (sweep / "state" / "fb_walker_s0").mkdir(parents=True)
    (sweep / "state" / "fb_walker_s0" / "pretrain.json").write_text(json.dumps(
        {"unit": "fb_walker_s0/pretrain", "state": "running", "host": socket.gethostname(), "pid": os.getpid()}))
    _records(sweep / "runs" / "fb_walker_s0", {"step": 500, "fps": 100.0, "fps_recent": 100.0},
             {"step": 1000, "fps": 100.0, "fps_recent": 1.0})
    assert main(["sweep", "status", str(sweep)]) == 0
    row = capsys.readouterr().out.splitlines()[1].split()
    assert row[:4] == ["fb_walker_s0", "running", "1000/4000", "50m00s"]  # 3000 frames at 1 frame/s


@pytest.fixture
def made_run(tmp_path) -> PretrainRun:
    """A pre-training run directory with a config and two train records (no training: files only)."""
    config = preset_config("small", "fb", domain="point_mass_maze", frames=5000)
    run = PretrainRun.create(tmp_path / "run", config, command=["dvfb", "pretrain"])
    _records(run.path, {"step": 1000, "fps": 50.0, "fps_recent": 50.0, "fb_loss": 1.25},
             {"step": 2000, "fps": 25.0, "fps_recent": 10.0, "fb_loss": 0.5})
    return run


def test_status_of_a_running_a_stopped_and_a_finished_run(made_run, capsys):
    with RunLock(made_run.path):  # held, as a training process holds it
        assert main(["status", str(made_run.path)]) == 0
        running = capsys.readouterr().out
    assert f"running (process {os.getpid()}), 2000/5000 frames (40%), 10.0 frames/s at its newest record" in running
    assert "ETA 00:05:00" in running  # 3000 frames at 10 frames/s
    assert "newest metrics (step 2000): fb_loss 0.5" in running and "fb on point_mass_maze, small preset" in running
    assert main(["status", str(made_run.path)]) == 0
    stopped = capsys.readouterr().out
    assert "stopped, 2000/5000 frames" in stopped and "ETA" not in stopped and "--resume" in stopped
    made_run.write_summary(PretrainSummary(agent="fb", domain="point_mass_maze", frames=5000, episodes=5))
    assert main(["status", str(made_run.path)]) == 0
    assert "pre-training: finished, 5000/5000 frames (100%)" in capsys.readouterr().out


def test_status_of_what_is_not_a_run_is_one_line(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["status", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not a dvfb run directory" in err[0]


def test_a_signal_to_a_group_names_every_members_directory(tmp_path):
    members = [tmp_path / "runs" / "fb_walker_s0", tmp_path / "runs" / "fb_walker_s1"]
    saved = []
    checkpoints = ResumeCheckpoints(saved.append, MetricWindow(), 1000, 5000, "pre-training", members)
    with pytest.raises(RunInterrupted) as info:
        with checkpoints:
            os.kill(os.getpid(), signal.SIGTERM)  # a real signal: the handler records it
            checkpoints.after_step(1500, mid_episode=True)
    assert saved == [True]  # one mid-episode checkpoint before stopping
    assert f"(runs {members[0]}, {members[1]})" in str(info.value) and "(run runs)" not in str(info.value)


def test_status_into_a_reader_that_stopped_reading_ends_quietly(dvfb_maze_run):
    # dvfb status RUN | head: the reader closes the pipe before dvfb writes; no "error: Broken pipe".
    proc = subprocess.Popen([sys.executable, "-m", "dvfb", "status", str(dvfb_maze_run)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    proc.stdout.close()
    _out, err = proc.communicate()
    assert proc.returncode == 128 + signal.SIGPIPE, err
    assert err == ""


def test_a_finished_run_resumed_with_more_frames_is_not_reported_finished(dvfb_maze_run, tmp_path, capsys):
    # dvfb pretrain ... --frames 4000 --resume on a finished 2,000-frame run saves the larger budget
    # first; until it finishes again its old summary must not make dvfb status say "finished".
    from tiny import copy_run

    run = copy_run(dvfb_maze_run, tmp_path)
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "frames": 4000}))
    assert main(["status", str(run)]) == 0
    out = capsys.readouterr().out
    assert "pre-training: stopped, 2000/4000 frames (50%)" in out, out
