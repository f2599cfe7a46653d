"""A group split over several processes (docs/members.md, "A group over several processes"): each
process trains its share of the members exactly as a group of that share does in one process; a
SIGTERM to the command checkpoints every member and the split group resumes exactly; a child's
error is the command's one line."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.runs import RunDir, load_snapshot
from dvfb.runs.machine import cores
from dvfb.workflows.pretrain import pretrain
from dvfb.workflows.processes import shares, threads_per_process
from tiny import start_cli, tiny_flags, tiny_run_config, tree_bytes

# `dvfb pretrain` of FB on the maze (the processes' commands add seeds, run directory and frames).
PRETRAIN = ["pretrain", "--agent", "fb", "--domain", "point_mass_maze", *tiny_flags("fb"), "--seed-frames", "500",
            "--update-every", "4", "--replay-capacity", "4000", "--torch-threads", "1", "--log-every", "100"]


def _modules(path, frames):
    return load_snapshot(RunDir(path), f"snapshot_{frames}")["modules"]


def _assert_same_snapshots(paths_a, paths_b, frames):
    for a_path, b_path in zip(paths_a, paths_b):
        a, b = _modules(a_path, frames), _modules(b_path, frames)
        assert a.keys() == b.keys()
        for key in a:
            for name, tensor in a[key].items():
                assert torch.equal(tensor, b[key][name]), (a_path.name, key, name)


def test_shares_are_contiguous_and_even():
    assert shares(5, 2) == [range(0, 3), range(3, 5)]
    assert shares(4, 2) == [range(0, 2), range(2, 4)]
    assert shares(2, 8) == [range(0, 1), range(1, 2)]  # at most one process per member
    assert shares(3, 1) == [range(0, 3)]
    assert threads_per_process(4, 2) == 2 and threads_per_process(1, 2) == 1  # the command's threads, shared
    assert threads_per_process(0, 2) >= 1


@pytest.mark.slow
def test_a_split_group_trains_each_share_as_its_own_group(tmp_path):
    seeds = [0, 1, 2]
    config = tiny_run_config("fb", frames=1500, processes=2)
    split = [tmp_path / f"split_s{s}" for s in seeds]
    runs = pretrain(config, split, seeds=seeds, progress=False)
    assert [r.path for r in runs] == split and [r.config.seed for r in runs] == seeds
    # The same shares in this process: seeds 0 and 1 as a group, seed 2 alone.
    one = dataclasses.replace(config, processes=1)
    pretrain(one, [tmp_path / "ref_s0", tmp_path / "ref_s1"], seeds=[0, 1], progress=False)
    pretrain(dataclasses.replace(one, seed=2), tmp_path / "ref_s2", progress=False)
    _assert_same_snapshots(split, [tmp_path / f"ref_s{s}" for s in seeds], 1500)
    # Each member is an ordinary run whose config says how it was scheduled.
    assert all(RunDir.open(p).path == p for p in split)
    assert runs[2].config.processes == 2 and not (split[0] / ".lock").read_text().strip() == ""


def _logged(path) -> bool:
    metrics = path / "metrics" / "train.jsonl"
    return metrics.is_file() and metrics.stat().st_size > 0


def _started_split(template: str, paths, flags) -> subprocess.Popen:
    """``dvfb pretrain`` of one member per path split over 2 processes, once every child is updating."""
    seeds = ",".join(str(k) for k in range(len(paths)))
    proc = start_cli(*PRETRAIN, "--seeds", seeds, "--run-dir", template, "--processes", "2", *flags)
    deadline = time.monotonic() + 300
    while not all(_logged(p) for p in paths):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    return proc


def _split_pair(tmp_path):
    """Seeds 0 and 1 pre-trained for 1,000 frames as a group split over 2 processes: the config and
    the two run directories."""
    config = tiny_run_config("fb", frames=1000, processes=2)
    paths = [tmp_path / f"r_s{s}" for s in (0, 1)]
    pretrain(config, paths, seeds=[0, 1], progress=False)
    return config, paths


@pytest.mark.slow
def test_a_childs_error_is_the_commands_one_line_and_no_share_starts(tmp_path):
    config, paths = _split_pair(tmp_path)
    checkpoint = next((paths[1] / "checkpoints").glob("resume_*.pt"))
    checkpoint.write_bytes(b"not a checkpoint")  # a real file the child of seed 1 cannot read
    before = tree_bytes(tmp_path)
    with pytest.raises(CheckpointError) as failure:
        pretrain(dataclasses.replace(config, frames=1500), paths, seeds=[0, 1], resume=True, progress=False)
    message = str(failure.value)
    assert message.startswith("seeds 1: cannot resume ") and str(paths[1]) in message and "\n" not in message
    # Seed 0's share had read its checkpoint and waited: it stopped without writing, as a group does.
    assert tree_bytes(tmp_path) == before


@pytest.mark.slow
def test_shares_finished_and_unfinished_are_refused_together_and_change_nothing(tmp_path):
    config, paths = _split_pair(tmp_path)
    pretrain(dataclasses.replace(config, frames=1500), paths[0], resume=True, progress=False)  # seed 0 alone
    before = tree_bytes(tmp_path)
    with pytest.raises(ConfigError, match="some members of the group have finished and others not"):
        pretrain(dataclasses.replace(config, frames=1500), paths, seeds=[0, 1], resume=True, progress=False)
    assert tree_bytes(tmp_path) == before


def _children(pid: int) -> list[int]:
    """The process ids whose parent is ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
def test_children_of_a_killed_command_checkpoint_and_stop(tmp_path):
    paths = [tmp_path / f"k_s{s}" for s in (0, 1)]
    proc = _started_split(str(tmp_path / "k_s{seed}"), paths, ["--frames", "20000", "--checkpoint-every", "1000"])
    children = [pid for pid in _children(proc.pid) if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
    assert len(children) == 2, children
    killed = time.time()
    os.kill(proc.pid, signal.SIGKILL)  # no forwarding: the kernel tells the children
    proc.communicate(timeout=60)
    deadline = time.monotonic() + 120
    while any(_alive(pid) for pid in children):
        assert time.monotonic() < deadline, "a child of the killed command trains on"
        time.sleep(0.2)
    for path in paths:  # each stopped with a checkpoint written after the kill, long before its end
        written = {p.name: p.stat().st_mtime for p in (path / "checkpoints").glob("resume_*.pt")}
        assert any(t >= killed for t in written.values()), (path, written, killed)
        assert not (path / "pretrain_summary.json").exists()


def _holds_a_file_in(pid: int, path: Path) -> bool:
    """Whether process ``pid`` has a file under ``path`` open (a share's metrics logs)."""
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            if str(path) in os.readlink(fd):
                return True
        except OSError:  # closed meanwhile
            continue
    return False


@pytest.mark.slow
def test_a_killed_share_stops_the_group_in_one_line_and_the_group_resumes_exactly(tmp_path):
    template = str(tmp_path / "cut_s{seed}")
    cut = [tmp_path / f"cut_s{s}" for s in (0, 1)]
    frames = ["--frames", "3000", "--checkpoint-every", "1000"]
    proc = _started_split(template, cut, frames)
    children = [pid for pid in _children(proc.pid) if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
    (victim,) = [pid for pid in children if _holds_a_file_in(pid, cut[1])]
    deadline = time.monotonic() + 300
    # It has something to resume from once `latest` names a checkpoint: the checkpoint file is
    # complete an instant before the pointer is written, and a kill in between leaves nothing to resume.
    while not (cut[1] / "checkpoints" / "latest").exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    os.kill(victim, signal.SIGKILL)  # what the out-of-memory killer sends: no checkpoint, no word
    _out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGKILL, err
    lines = err.strip().splitlines()
    last = lines[-1]
    assert "Traceback" not in err and last.startswith("dvfb pretrain: seeds 1: its process was killed by SIGKILL"), err
    assert "seeds 0: SIGTERM received" in last and "--resume" in last
    # The other share stopped at once with a checkpoint, long before its end; nothing finished.
    assert not any((path / "pretrain_summary.json").exists() for path in cut)
    assert list((cut[0] / "checkpoints").glob("resume_*.pt"))
    resumed = start_cli(*PRETRAIN, "--seeds", "0,1", "--run-dir", template, "--processes", "2", *frames,
                        "--resume")
    _out, err = resumed.communicate(timeout=600)
    assert resumed.returncode == 0, err
    whole = start_cli(*PRETRAIN, "--seeds", "0,1", "--run-dir", str(tmp_path / "whole_s{seed}"), "--processes", "2",
                      *frames)
    _out, err = whole.communicate(timeout=600)
    assert whole.returncode == 0, err
    _assert_same_snapshots(cut, [tmp_path / f"whole_s{s}" for s in (0, 1)], 3000)


def test_a_groups_default_schedule_is_single_thread_shares_one_per_cpu_up_to_one_per_member(monkeypatch):
    from dvfb.workflows import processes

    monkeypatch.setattr(processes, "cores", lambda: 2)
    assert processes.group_schedule(4, 0, 0) == (2, 1)  # no flag: one single-thread share per CPU
    assert processes.group_schedule(1, 0, 0) == (1, 0)  # a run: in this process
    monkeypatch.setattr(processes, "cores", lambda: 16)
    assert processes.group_schedule(4, 0, 0) == (4, 1)  # up to one per member
    assert processes.group_schedule(4, 0, 0, cuda=True) == (1, 0)  # one process on a GPU
    assert processes.group_schedule(4, 0, 2) == (1, 0)  # --torch-threads alone: one process with them
    assert processes.group_schedule(4, 2, 8) == (2, 4)  # --processes: they share the threads


# The same command without a thread flag: what a user who trusts the defaults types.
DEFAULTS = [arg for k, arg in enumerate(PRETRAIN) if arg != "--torch-threads" and PRETRAIN[k - 1] != "--torch-threads"]


@pytest.mark.slow
def test_a_default_group_records_its_schedule_and_resumes_bit_identical_from_another_shell(tmp_path):
    """No --processes, no --torch-threads, no OMP_NUM_THREADS: the group splits into single-thread
    shares. A SIGTERM to the command (it forwards the signal to its children) checkpoints every
    share; resumed from a shell whose OMP_NUM_THREADS is 2, the group ends as the uninterrupted
    default group does."""
    expected = min(3, cores())
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    template, cut = str(tmp_path / "cut_s{seed}"), [tmp_path / f"cut_s{s}" for s in (0, 1, 2)]
    frames = ["--frames", "3000", "--checkpoint-every", "1000"]
    proc = subprocess.Popen([sys.executable, "-m", "dvfb", *DEFAULTS, "--seeds", "0,1,2", "--run-dir", template,
                             *frames], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 300
    while not all(_logged(p) for p in cut):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGTERM)
    _out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, err
    last = err.strip().splitlines()[-1]
    assert "SIGTERM received" in last and "--resume" in last, err
    if expected > 1:  # the line names every share
        assert all(f"seeds {','.join(map(str, share))}:" in last for share in shares(3, expected)), last
    for path in cut:
        assert list((path / "checkpoints").glob("resume_*.pt")), path
        assert not (path / "pretrain_summary.json").exists()
        config, meta = (json.loads((path / name).read_text()) for name in ("config.json", "meta.json"))
        assert config["processes"] == expected and meta["processes"] == expected
        assert meta["machine"]["torch_threads"] == (1 if expected > 1 else max(1, cores() // 2))
    resumed = subprocess.run([sys.executable, "-m", "dvfb", *DEFAULTS, "--seeds", "0,1,2", "--run-dir", template,
                              *frames, "--resume"], capture_output=True, text=True, timeout=600,
                             env={**env, "OMP_NUM_THREADS": "2"})
    assert resumed.returncode == 0, resumed.stderr
    assert json.loads((cut[0] / "meta.json").read_text())["resumes"][-1]["processes"] == expected
    whole = subprocess.run([sys.executable, "-m", "dvfb", *DEFAULTS, "--seeds", "0,1,2", "--run-dir",
                            str(tmp_path / "whole_s{seed}"), *frames], capture_output=True, text=True, timeout=600,
                           env=env)
    assert whole.returncode == 0, whole.stderr
    _assert_same_snapshots(cut, [tmp_path / f"whole_s{s}" for s in (0, 1, 2)], 3000)
