"""Frames/s of ``dvfb pretrain`` with the old default torch threads and the new one, with busy
single-thread processes beside it (README.md, "Threads and progress").

The old default is torch's own thread count (what a fresh ``python -c "import torch"`` reports in
this environment: the CPUs of the affinity mask, a cgroup quota not counted); the new default is
what ``dvfb`` now chooses when ``--torch-threads`` is not given (``OMP_NUM_THREADS`` when set, else
half the CPUs the process may use). Each run pre-trains from scratch in a temporary directory while
``--busy`` processes spin on one core each (``python -c "while True: pass"``, started by this script
and ended by it); the settings alternate over ``--rounds`` rounds, so that a machine whose speed
drifts affects both alike. Printed per run: the whole run's frames/s (``pretrain_summary.json``) and
the training phase's (the frames after ``--seed-frames`` over their time, from the ``train`` records'
``fps_recent``), then the medians and every command that ran.

    python scripts/threads_under_contention.py                       # 1 busy process, 2 rounds
    python scripts/threads_under_contention.py --busy 0 --rounds 1   # the quiet machine
    python scripts/threads_under_contention.py --cpus 0,1            # as a 2-CPU allocation of a larger node
    python scripts/threads_under_contention.py --frames 400 --seed-frames 200 --rounds 1   # a smoke run

It measures; it is not a test. Run it on a machine where nothing else computes, or say what did.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BUSY = [sys.executable, "-c", "while True: pass"]


def _cpus(text: str | None) -> set[int] | None:
    return None if text is None else {int(part) for part in text.split(",")}


def _pinned(cpus: set[int] | None):
    """A ``preexec_fn`` that gives the child the affinity ``cpus`` (a SLURM allocation's view)."""
    if cpus is None:
        return None
    return lambda: os.sched_setaffinity(0, cpus)


def _environment() -> dict:
    # The old default is torch's own choice: no OMP_NUM_THREADS to steer it, nor dvfb's default.
    return {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}


def _ask(code: str, cpus: set[int] | None) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env=_environment(), preexec_fn=_pinned(cpus)).stdout.strip()


def _training_rate(run: Path, seed_frames: int) -> float | None:
    """Frames/s after the seed frames: each record's interval (its step minus the previous one's)
    over its time (that interval divided by its ``fps_recent``)."""
    path = run / "metrics" / "train.jsonl"
    if not path.is_file():
        return None
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    frames = seconds = 0.0
    previous = None
    for record in records:
        if previous is not None and previous >= seed_frames and record.get("fps_recent"):
            frames += record["step"] - previous
            seconds += (record["step"] - previous) / record["fps_recent"]
        previous = record["step"]
    return frames / seconds if seconds > 0 else None


def _pretrain(args, threads: int | None, run: Path, cpus: set[int] | None) -> tuple[list[str], dict]:
    command = [sys.executable, "-m", "dvfb", "pretrain", "--agent", args.agent, "--domain", args.domain,
               "--preset", args.preset, "--frames", str(args.frames), "--seed-frames", str(args.seed_frames),
               "--log-every", str(args.log_every), "--snapshot-frames", "--checkpoint-every", str(args.frames),
               "--run-dir", str(run), "--no-progress", "--overwrite"]
    if threads is not None:
        command += ["--torch-threads", str(threads)]
    busy = [subprocess.Popen(BUSY, preexec_fn=_pinned(cpus)) for _ in range(args.busy)]
    try:
        started = time.monotonic()
        done = subprocess.run(command, capture_output=True, text=True, env=_environment(), preexec_fn=_pinned(cpus))
        wall = time.monotonic() - started
    finally:
        for process in busy:  # the processes this script started, by their own handle
            process.send_signal(signal.SIGKILL)
            process.wait()
    if done.returncode != 0:
        raise SystemExit(f"the run failed ({done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
    summary = json.loads((run / "pretrain_summary.json").read_text())
    meta = json.loads((run / "meta.json").read_text())
    return command, {"threads": meta["machine"].get("torch_threads"), "wall_s": wall,
                     "frames_per_s": summary["frames_per_s"],
                     "training_frames_per_s": _training_rate(run, args.seed_frames)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agent", default="dvfb")
    parser.add_argument("--domain", default="walker")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--frames", type=int, default=3000, help="frames per run (default: %(default)s)")
    parser.add_argument("--seed-frames", type=int, default=1000,
                        help="uniform-action frames before the first update (default: %(default)s)")
    parser.add_argument("--log-every", type=int, default=250,
                        help="frames between train records (default: %(default)s)")
    parser.add_argument("--busy", type=int, default=1, help="busy single-thread processes beside each run "
                                                             "(default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=2,
                        help="runs of each setting, alternating (default: %(default)s)")
    parser.add_argument("--cpus", default=None, help="comma-separated CPUs every process is pinned to (default: all)")
    parser.add_argument("--output", default=None, help="also write the figures as JSON to this file")
    args = parser.parse_args()
    cpus = _cpus(args.cpus)

    old = int(_ask("import torch; print(torch.get_num_threads())", cpus))
    new = int(_ask("from dvfb.runs.machine import default_torch_threads; print(default_torch_threads())", cpus))
    cores = int(_ask("from dvfb.runs.machine import cores; print(cores())", cpus))
    model = _ask("from dvfb.runs.machine import cpu; print(cpu()['model'])", cpus)
    settings = [("old default (torch's own)", old), ("new default (no --torch-threads)", None)]
    rows, commands = [], []
    with tempfile.TemporaryDirectory(prefix="dvfb_threads_") as tmp:
        for round_ in range(args.rounds):
            order = settings if round_ % 2 == 0 else settings[::-1]
            for name, threads in order:
                command, figures = _pretrain(args, threads, Path(tmp) / f"run_{len(rows)}", cpus)
                rows.append({"setting": name, "round": round_ + 1, **figures})
                commands.append(command)
                print(f"{name:<34} round {round_ + 1}: {figures['threads']} thread(s), "
                      f"{figures['frames_per_s']:.1f} frames/s whole run, "
                      + (f"{figures['training_frames_per_s']:.1f} frames/s training phase"
                         if figures["training_frames_per_s"] else "no training-phase records"), flush=True)
    print()
    print(f"machine: {model}; {cores} CPU(s) this process may use{' (pinned to ' + args.cpus + ')' if cpus else ''}; "
          f"{args.busy} busy single-thread process(es) beside each run")
    print(f"{'setting':<34} {'threads':>7} {'frames/s whole (median)':>24} {'training phase (median)':>24}")
    summary = {}
    for name, _threads in settings:
        mine = [r for r in rows if r["setting"] == name]
        whole = statistics.median(r["frames_per_s"] for r in mine)
        phase = [r["training_frames_per_s"] for r in mine if r["training_frames_per_s"]]
        summary[name] = {"threads": mine[0]["threads"], "frames_per_s": whole,
                         "training_frames_per_s": statistics.median(phase) if phase else None}
        print(f"{name:<34} {mine[0]['threads']:>7} {whole:>24.1f} "
              + (f"{statistics.median(phase):>24.1f}" if phase else f"{'-':>24}"))
    print()
    print("commands (each run, in order; busy processes: " + shlex.join(BUSY) + "):")
    for command in commands:
        print("  " + shlex.join(command))
    print("this script: " + shlex.join([sys.executable, *sys.argv]))
    if args.output:
        Path(args.output).write_text(json.dumps({"machine": {"cpu": model, "cores": cores, "pinned": args.cpus},
                                                 "busy": args.busy, "rows": rows, "summary": summary,
                                                 "commands": [shlex.join(c) for c in commands]}, indent=2) + "\n")


if __name__ == "__main__":
    main()
