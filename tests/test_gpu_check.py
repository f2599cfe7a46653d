"""bench/gpu_check.py, the GPU acceptance command, on the CPU (``--device cpu --quick``): the same
code path a GPU runs, so that it is known to work before a GPU is seen (bench/README.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dvfb.agents import agent_names

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_gpu_check_runs_every_method_and_the_groups_on_the_cpu(tmp_path):
    # One thread: the suite's other workers share the cores (OpenMP threads that wait for a busy
    # core slow a run down many times over).
    output = tmp_path / "gpu_check.json"
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "gpu_check.py"), "--device", "cpu", "--quick",
                           "--threads", "1", "--output", str(output)], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads(output.read_text())
    assert report["failed"] == [] and report["peak"]["gflops"] > 0
    assert report["machine"]["versions"]["torch"] and report["machine"]["cpu"]["torch_capability"]
    eager = {row["agent"]: row for row in report["methods"] if row["variant"] == "eager"}
    assert sorted(eager) == sorted(agent_names())
    for agent, row in eager.items():
        assert row["status"] == "ok" and row["ms_per_update"] > 0 and row["gflop_per_update"] > 0, agent
        assert 0 < row["percent_of_peak"] and row["memory_mb"] is None, agent  # no device memory on the CPU
    # On the CPU the CUDA-graph rows say why they did not run; --quick skips the compiled ones.
    skipped = {(row["variant"], row["error"]) for row in report["methods"] if row["status"] == "skipped"}
    assert ("cuda_graphs", "CUDA graphs exist on CUDA only") in skipped and ("compile", "--quick") in skipped
    for group in report["groups"]:
        assert group["status"] == "ok" and group["members"] == 2 and group["frames"] == 400, group
        assert group["frames_per_s"] > 0 and group["member_updates_per_s"] > 0
        assert group["steady_frames_per_s"] > 0 and group["projection"]["hours"] > 0
    assert [g["agent"] for g in report["groups"]] == ["dvfb", "fb"]
    assert "2M frames x 2 seeds" in done.stdout


def test_the_gpu_check_without_cuda_is_one_line_exit_2(tmp_path):
    # No GPU visible (so the refusal is checked on a GPU machine as well).
    done = subprocess.run([sys.executable, str(ROOT / "bench" / "gpu_check.py"), "--output", str(tmp_path / "x.json")],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "--device cpu --quick" in done.stderr
    assert not (tmp_path / "x.json").exists()
