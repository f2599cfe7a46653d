"""The threads a command computes with (README.md, "Threads and progress"): the CPUs a process may
use (its affinity, at most its cgroup's CPU quota), the default of half of them, the run's own
setting, and the one ``--torch-threads`` flag of every command that computes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from dvfb.cli import build_parser
from dvfb.runs.machine import cgroup_cpu_quota, cores, default_torch_threads
from dvfb.runs.directory import RunDir
from dvfb.workflows.resources import use_threads
from tiny import tiny_flags


def _cgroup_tree(root: Path, cgroup_lines: str, files: dict[str, str]) -> Path:
    """A directory laid out as ``/`` is for the cgroup files (``proc/self/cgroup``, ``sys/fs/cgroup``)."""
    (root / "proc/self").mkdir(parents=True)
    (root / "proc/self/cgroup").write_text(cgroup_lines)
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_a_cgroup_v2_quota_is_read_along_the_process_path(tmp_path):
    root = _cgroup_tree(tmp_path / "a", "0::/jobs/job7\n",
                        {"sys/fs/cgroup/cpu.max": "max 100000\n", "sys/fs/cgroup/jobs/cpu.max": "400000 100000\n",
                         "sys/fs/cgroup/jobs/job7/cpu.max": "250000 100000\n"})
    assert cgroup_cpu_quota(root) == 2.5  # the smallest of the path: the job's own
    unlimited = _cgroup_tree(tmp_path / "b", "0::/\n", {"sys/fs/cgroup/cpu.max": "max 100000\n"})
    assert cgroup_cpu_quota(unlimited) is None
    assert cgroup_cpu_quota(tmp_path / "nothing") is None  # no cgroup files: no quota


def test_a_cgroup_v1_quota_is_read_and_minus_one_is_none(tmp_path):
    limited = _cgroup_tree(tmp_path / "a", "4:memory:/x\n3:cpu,cpuacct:/docker/abc\n",
                           {"sys/fs/cgroup/cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "150000\n",
                            "sys/fs/cgroup/cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000\n"})
    assert cgroup_cpu_quota(limited) == 1.5
    free = _cgroup_tree(tmp_path / "b", "3:cpu,cpuacct:/\n",
                        {"sys/fs/cgroup/cpu,cpuacct/cpu.cfs_quota_us": "-1\n",
                         "sys/fs/cgroup/cpu,cpuacct/cpu.cfs_period_us": "100000\n"})
    assert cgroup_cpu_quota(free) is None


def test_the_default_is_omp_num_threads_else_half_the_cpus(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert default_torch_threads() == 3
    for unusable in ("0", "x", ""):
        monkeypatch.setenv("OMP_NUM_THREADS", unusable)
        assert default_torch_threads() == max(1, cores() // 2)
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert default_torch_threads() == max(1, cores() // 2)


def test_a_command_uses_its_flag_else_the_runs_setting_at_most_the_cpus_else_the_default(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    try:
        assert use_threads(1) == 1 and torch.get_num_threads() == 1  # asked for: as asked, up to the CPUs
        assert use_threads(cores()) == cores()
        assert use_threads(None, run_setting=1) == 1  # the run's own
        assert use_threads(None, run_setting=cores() + 7) == cores()  # a run made on a larger machine
        assert use_threads(None, run_setting=0) == max(1, cores() // 2)
        assert use_threads(0, run_setting=1) == max(1, cores() // 2)  # 0: the default, whatever the run says
    finally:
        torch.set_num_threads(before)


def test_threads_above_the_cpus_are_capped_with_one_line(monkeypatch, capsys):
    """OMP_NUM_THREADS=1000 or --torch-threads 10000 on a small machine: at most the CPUs, said once."""
    before = torch.get_num_threads()
    try:
        monkeypatch.setenv("OMP_NUM_THREADS", "1000")
        assert use_threads(0) == cores() and torch.get_num_threads() == cores()
        use_threads(0)
        monkeypatch.delenv("OMP_NUM_THREADS")
        assert use_threads(10000) == cores()
        lines = capsys.readouterr().err.splitlines()
        assert lines == [f"[threads] OMP_NUM_THREADS=1000 is more than the {cores()} CPU(s) this process may use; "
                         f"using {cores()} (more threads than CPUs make OpenMP crawl)",
                         f"[threads] --torch-threads 10000 is more than the {cores()} CPU(s) this process may use; "
                         f"using {cores()} (more threads than CPUs make OpenMP crawl)"]
    finally:
        torch.set_num_threads(before)


def test_the_threads_a_run_computed_with_are_its_last_resumes_else_its_own_else_its_configs(tmp_path):
    run = RunDir(tmp_path)
    (tmp_path / "meta.json").write_text(json.dumps({"machine": {"torch_threads": 3}}))
    assert run.computed_threads() == 3
    (tmp_path / "meta.json").write_text(json.dumps({"machine": {"torch_threads": 3},
                                                    "resumes": [{"torch_threads": 5}, {"torch_threads": 2}]}))
    assert run.computed_threads() == 2
    (tmp_path / "meta.json").write_text(json.dumps({"machine": {}}))  # a run made before meta.json said
    assert run.computed_threads() == 0
    (tmp_path / "meta.json").write_text("{not json")
    assert run.computed_threads() == 0
    (tmp_path / "meta.json").write_text(json.dumps({"processes": 2, "resumes": [{"processes": 3}]}))
    assert run.computed_processes() == 3


def test_a_pretraining_asking_for_more_threads_than_cpus_runs_with_the_cpus(tmp_path):
    run = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "dvfb", "pretrain", "--agent", "fb", "--domain", "point_mass_maze",
                           *tiny_flags("fb"), "--frames", "600", "--seed-frames", "500", "--update-every", "4",
                           "--run-dir", str(run), "--no-progress", "--torch-threads", "10000"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"--torch-threads 10000 is more than the {cores()} CPU(s)" in done.stderr
    assert json.loads((run / "meta.json").read_text())["machine"]["torch_threads"] == cores()


COMPUTING = {
    "zeroshot": ["zeroshot", "RUN", "--task", "walker_walk"],
    "finetune": ["finetune", "RUN", "--task", "walker_walk"],
    "video": ["video", "RUN", "--task", "walker_walk"],
    "analyze-value": ["analyze-value", "RUN", "--task", "walker_walk"],
    "analyze-exploration": ["analyze-exploration", "RUN"],
    "random-policy": ["random-policy", "--domain", "walker"],
    "supervised": ["supervised", "--task", "walker_walk"],
    "pretrain": ["pretrain"],
    "dataset export": ["dataset", "export", "RUN"],
    "dataset relabel": ["dataset", "relabel", "DATA", "--task", "walker_walk"],
}


@pytest.mark.parametrize("command", list(COMPUTING))
def test_every_command_that_computes_takes_torch_threads(command):
    args = build_parser().parse_args([*COMPUTING[command], "--torch-threads", "2"])
    assert args.torch_threads == 2


def test_a_pretraining_without_the_flag_computes_with_half_its_cpus(tmp_path):
    """As a user runs it: a process of its own, no OMP_NUM_THREADS; meta.json records what it used."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    run = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "dvfb", "pretrain", "--agent", "fb", "--domain", "point_mass_maze",
                           *tiny_flags("fb"), "--frames", "600", "--seed-frames", "500", "--update-every", "4",
                           "--run-dir", str(run), "--no-progress"], capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    machine = json.loads((run / "meta.json").read_text())["machine"]
    assert machine["cpus"] == cores()
    # torch's own default would be every CPU of the affinity (2 on the development machine).
    assert machine["torch_threads"] == max(1, cores() // 2)
    # Its train record carries the rate since the record before (an ETA's), beside the average.
    (record,) = [json.loads(line) for line in (run / "metrics" / "train.jsonl").read_text().splitlines()]
    assert record["step"] == 600 and record["fps_recent"] > 0 and record["fps"] > 0
