"""Milliseconds per ``ReplayBuffer.sample`` with uniform sampling and with the authors' loader shards
(docs/methods.md, "Replay sampling"), on a buffer of walker-sized episodes.

The buffer holds ``--episodes`` finished episodes of 1000 steps (obs 24, action 6, z 50: walker
with DVFB's skill) and one episode in progress; both samplers draw FB-style batches (one step, with
``s_{t+2}``). Each figure is the median over ``--repeats`` timed draws after a warm-up, measured
alternately so that load from other processes favours neither side.

Usage: python bench/replay_sampling.py [--episodes 200] [--batches 256,1024] [--repeats 200]
Writes bench/results/replay_sampling.json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dvfb.data import LoaderShards, ReplayBuffer

OBS, ACT, Z, LENGTH = 24, 6, 50, 1000


def filled(episodes: int, sampler) -> ReplayBuffer:
    rng = np.random.default_rng(0)
    replay = ReplayBuffer((episodes + 1) * LENGTH, OBS, ACT, Z, max_episode_length=LENGTH, sampler=sampler)
    obs = rng.standard_normal((LENGTH + 1, OBS)).astype(np.float32)
    action = rng.uniform(-1, 1, (LENGTH, ACT)).astype(np.float32)
    z = rng.standard_normal(Z).astype(np.float32)
    for e in range(episodes + 1):
        replay.start_episode(obs[0])
        for t in range(LENGTH if e < episodes else LENGTH // 2):
            replay.add(action[t], 0.0, 1.0, obs[t + 1], z)
    return replay


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200, help="finished episodes in the buffer")
    parser.add_argument("--batches", default="256,1024", help="batch sizes")
    parser.add_argument("--repeats", type=int, default=200, help="timed draws per sampler and batch size")
    parser.add_argument("--output", type=Path, default=Path(__file__).resolve().parent / "results" / "replay_sampling.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    buffers = {"uniform": filled(args.episodes, None), "loader_shards": filled(args.episodes, LoaderShards(4, 1000))}
    rows = []
    for batch in (int(b) for b in args.batches.split(",")):
        times: dict[str, list[float]] = {name: [] for name in buffers}
        generators = {name: torch.Generator().manual_seed(0) for name in buffers}
        for _ in range(10):
            for name, replay in buffers.items():
                replay.sample(batch, need_future=True, generator=generators[name])
        for _ in range(args.repeats):
            for name, replay in buffers.items():
                t0 = time.perf_counter()
                replay.sample(batch, need_future=True, generator=generators[name])
                times[name].append(time.perf_counter() - t0)
        for name in buffers:
            row = {"sampler": name, "batch": batch, "ms_per_sample": 1e3 * statistics.median(times[name])}
            rows.append(row)
            print(f"{name:>14}  batch {batch:>5}  {row['ms_per_sample']:.3f} ms per sample")
    result = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": platform.processor() or
              platform.machine(), "cpus": os.cpu_count(), "torch": torch.__version__, "python": sys.version.split()[0],
              "episodes": args.episodes, "repeats": args.repeats, "threads": 1, "rows": rows,
              "command": "python bench/replay_sampling.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
