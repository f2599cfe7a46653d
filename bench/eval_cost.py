"""The cost of the zero-shot evaluations while pre-training (``--eval-every``; docs/health.md).

For each method, a small-preset pre-training on one torch thread with an evaluation every
``--every`` frames after the seed frames; the cost is the evaluations' own seconds (each record of
``metrics/eval.jsonl``) against the wall clock of the frames between two evaluations at the
steady rate (``fps_recent`` of the train records after the seed frames). The share printed is that
of the preset's default interval (10,000 frames at the small preset):

    python bench/eval_cost.py                                  # dvfb, fb, cic, rnd on walker
    python bench/eval_cost.py --agents dvfb --domains walker,quadruped --frames 8000 --every 4000

Writes ``bench/results/eval_cost.json``. A figure measured beside another busy process is an upper
bound of both parts; compare rows of one run only.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import torch

from dvfb.cli import main
from dvfb.runs.machine import describe
from dvfb.runs.presets import preset_config

RESULTS = Path(__file__).resolve().parent / "results" / "eval_cost.json"


def measure(agent: str, domain: str, frames: int, every: int, root: Path) -> dict:
    run = root / f"{agent}_{domain}"
    seed_frames = preset_config("small", agent, domain=domain).seed_frames
    started = time.time()
    code = main(["pretrain", "--agent", agent, "--domain", domain, "--preset", "small", "--frames", str(frames),
                 "--eval-every", str(every), "--torch-threads", "1", "--run-dir", str(run), "--no-progress",
                 "--log-every", "500", "--snapshot-frames", str(frames)])
    wall = time.time() - started
    if code != 0:
        raise SystemExit(f"{agent} on {domain}: dvfb pretrain exited {code}")
    evaluations = {}
    for line in (run / "metrics" / "eval.jsonl").read_text().splitlines():
        row = json.loads(line)
        evaluations[row["step"]] = row["seconds"]  # one figure per evaluation (all its tasks)
    rates = [json.loads(line)["fps_recent"] for line in (run / "metrics" / "train.jsonl").read_text().splitlines()
             if json.loads(line)["step"] > seed_frames + 500]
    steady = sorted(rates)[len(rates) // 2]  # the median rate of the update phase
    interval = preset_config("small", agent, domain=domain).eval_every
    seconds = sum(evaluations.values()) / len(evaluations)
    return {"agent": agent, "domain": domain, "frames": frames, "evaluations": len(evaluations),
            "eval_seconds": seconds, "steady_frames_per_s": steady, "default_interval": interval,
            "share_at_default": seconds / (seconds + interval / steady), "wall_s": wall}


def main_(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--agents", default="dvfb,fb,cic,rnd", help="methods (default: %(default)s)")
    p.add_argument("--domains", default="walker", help="domains (default: %(default)s)")
    p.add_argument("--frames", type=int, default=8000, help="pre-training frames of each run (default: %(default)s)")
    p.add_argument("--every", type=int, default=4000, help="frames between evaluations (default: %(default)s)")
    p.add_argument("--out", default=str(RESULTS), help="JSON results (default: bench/results/eval_cost.json)")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for domain in args.domains.split(","):
            for agent in args.agents.split(","):
                rows.append(measure(agent, domain, args.frames, args.every, Path(tmp)))
                r = rows[-1]
                print(f"{agent:>6} {domain:<10} evaluation {r['eval_seconds']:6.1f} s, steady {r['steady_frames_per_s']:6.1f} "
                      f"frames/s, {100 * r['share_at_default']:4.1f}% of the wall clock at --eval-every "
                      f"{r['default_interval']:,}", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"command": " ".join(["python", "bench/eval_cost.py", *(argv or sys.argv[1:])]),
                                          "machine": describe(), "python": platform.python_version(),
                                          "torch": torch.__version__, "rows": rows}, indent=2) + "\n")
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main_())
