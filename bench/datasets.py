"""Throughput and size of dvfb's datasets (docs/methods.md, "Datasets") on a walker run.

1. Pre-trains FB on walker for ``--frames`` frames with ``--replay.record-physics true`` (tiny
   networks, uniform actions for all but the last 1000 frames: the data, not the agent, is what is
   measured), into ``--dir``.
2. Times ``export_run`` (replay checkpoint -> one .npz per episode), ``relabel`` to walker_run
   (physics states -> rewards) and ``read_dataset`` (files -> ReplayBuffer, with and without the
   physics column), each in transitions per second (building the task's env included), the median
   of ``--repeats`` runs.
3. Reports the dataset's size on disk, the replay checkpoint's, and the buffer's in memory; and the
   cost of recording: microseconds per ``physics_state()`` call next to a walker env step.

Usage: python bench/datasets.py [--frames 20000] [--repeats 5] [--dir /tmp/dvfb_bench_datasets]
Writes bench/results/datasets.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shutil
import statistics
import time
import timeit
from pathlib import Path

# isort: off
import dvfb.envs as envs  # before dm_control: sets the headless MUJOCO_GL default
# isort: on

import numpy as np
import torch

from dvfb.core.config import merge
from dvfb.data.datasets import read_dataset, relabel
from dvfb.runs import latest_checkpoint
from dvfb.runs.presets import preset_config
from dvfb.workflows.dataset_export import export_run
from dvfb.workflows.pretrain import pretrain

RESULTS = Path(__file__).resolve().parent / "results" / "datasets.json"


def du(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def timed(fn, repeats: int):
    """``fn(i)``'s last result and the median seconds of ``repeats`` calls."""
    seconds = []
    for i in range(repeats):
        start = time.perf_counter()
        out = fn(i)
        seconds.append(time.perf_counter() - start)
    return out, statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dir", default="/tmp/dvfb_bench_datasets")
    args = parser.parse_args()
    torch.set_num_threads(1)
    root = Path(args.dir)
    shutil.rmtree(root, ignore_errors=True)
    run = root / "fb_walker"
    config = merge(preset_config("small", "fb", domain="walker", frames=args.frames, seed_frames=args.frames - 1000,
                                 replay_capacity=max(args.frames, 1000), checkpoint_every=args.frames, torch_threads=1),
                   {"fb": {"z_dim": 8, "hidden_dim": 32, "feature_dim": 16, "backward_hidden_dim": 32,
                           "batch_size": 32},
                    "replay": {"record_physics": True}})
    _, pretrain_s = timed(lambda i: pretrain(config, run, progress=None), 1)

    k = args.repeats
    info, export_s = timed(lambda i: export_run(run, root / f"dataset{i}", progress=None), k)
    n = info.transitions
    _, relabel_s = timed(lambda i: relabel(root / "dataset0", "walker_run", root / f"dataset_walker_run{i}",
                                           progress=None), k)
    (buffer, _), read_s = timed(lambda i: read_dataset(root / "dataset0"), k)
    (buffer_physics, _), read_physics_s = timed(lambda i: read_dataset(root / "dataset0", columns=("physics",)), k)

    env = envs.make("walker_walk", seed=0).unwrapped
    env.reset(seed=0)
    action = np.zeros(env.action_space.shape, np.float32)
    step_us = min(timeit.repeat(lambda: env.step(action), number=200, repeat=5)) / 200 * 1e6
    physics_us = min(timeit.repeat(env.physics_state, number=2000, repeat=5)) / 2000 * 1e6

    result = {
        "date": datetime.date.today().isoformat(), "frames": args.frames, "repeats": k, "transitions": n,
        "episodes": info.episodes, "physics_width": info.physics_width, "pretrain_s": pretrain_s,
        "export_transitions_per_s": n / export_s, "relabel_transitions_per_s": n / relabel_s,
        "read_transitions_per_s": n / read_s, "read_with_physics_transitions_per_s": n / read_physics_s,
        "dataset_bytes_on_disk": du(root / "dataset0"), "relabelled_bytes_on_disk": du(root / "dataset_walker_run0"),
        "checkpoint_bytes": latest_checkpoint(run).stat().st_size,
        "buffer_bytes": buffer.nbytes, "buffer_with_physics_bytes": buffer_physics.nbytes,
        "walker_step_us": step_us, "physics_state_us": physics_us,
    }
    for key, value in result.items():
        print(f"{key:40s} {value:,.1f}" if isinstance(value, float) else f"{key:40s} {value}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
