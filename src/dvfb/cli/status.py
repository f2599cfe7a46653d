"""``dvfb status``: where a run is (frames, rate, ETA, newest metrics, finished or not)."""

from __future__ import annotations

import argparse

from dvfb.cli.common import Formatter
from dvfb.runs.status import run_status
from dvfb.training.progress import format_eta


def _duration(seconds: float) -> str:
    return format_eta(seconds)


def _progress_line(status: dict) -> str:
    state = status["state"] + (f" (process {status['process']})" if status["process"] else "")
    done = f"{status['frames']}/{status['target']} frames ({100 * status['frames'] / max(status['target'], 1):.0f}%)"
    parts = [state, done]
    if status["rate"] is not None:
        parts.append(f"{status['rate']:.1f} frames/s at its newest record")
    if status["record_age_s"] is not None:
        parts.append(f"newest record {_duration(status['record_age_s'])} ago")
    if status["eta_s"] is not None:
        parts.append(f"ETA {_duration(status['eta_s'])}")
    if status["state"] == "stopped":
        parts.append("continue it with its command plus --resume")
    return ", ".join(parts)


def _metrics_line(status: dict) -> str | None:
    metrics = {k: v for k, v in status["metrics"].items() if not k.startswith("fps")}
    if not metrics:
        return None
    shown = ", ".join(f"{name} {value:.4g}" for name, value in sorted(metrics.items()))
    return f"newest metrics (step {status['metrics_step']}): {shown}"


def _print(status: dict) -> None:
    if status["kind"] == "export":
        print(f"{status['description']}: an exported model (dvfb zeroshot and dvfb video evaluate it)")
        return
    if status["kind"] == "finetune":
        print(f"  fine-tuning {status['name']} ({status['task']}): {_progress_line(status)}")
        return
    origin = f", made from the exported model {status['exported_from']}" if status["exported_from"] else ""
    print(f"{status['path']}: {status['agent']} on {status['domain']}, {status['preset']} preset, seed "
          f"{status['seed']}{origin}")
    if status["unpacked"]:
        frames = ", ".join(str(f) for f in status["snapshots"])
        what = ("the evaluation directory of that exported model (dvfb zeroshot and dvfb video write its results "
                "here)" if status["exported_from"] else "an exported model unpacked into a run directory")
        print(f"  pre-training: none here; {what}, holding its snapshot after {frames} frames")
    else:
        print(f"  pre-training: {_progress_line(status)}")
    metrics = _metrics_line(status)
    if metrics:
        print(f"  {metrics}")
    snapshots = ", ".join(str(f) for f in status["snapshots"]) or "none"
    checkpoint = status["checkpoint"] if status["checkpoint"] is not None else "none"
    print(f"  resume checkpoint: {checkpoint}; snapshots: {snapshots}")
    if status["zero_shot"]:
        print("  zero-shot: " + ", ".join(f"{task} {r['mean_return']:.1f} ({r['eval_episodes']} episodes)"
                                          for task, r in sorted(status["zero_shot"].items())))
    for child in status["finetune"]:
        _print(child)


def cmd_status(args: argparse.Namespace) -> int:
    statuses = [run_status(path) for path in args.run]  # every path checked before anything is printed
    for status in statuses:
        _print(status)
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "status", help="where a run is: frames, rate, ETA, newest metrics, finished or not", formatter_class=Formatter,
        description="Read a run directory (while it trains in another process, or after it stopped) and print its "
                    "state (finished, running, stopped, not started), the frames it reached of its budget, the rate "
                    "of its newest training record (frames/s since the record before it) and an ETA while it runs, "
                    "its newest metrics, its resume checkpoint and snapshots, its zero-shot results and its "
                    "fine-tuning runs. Reads only; a sweep's cells: dvfb sweep status.")
    p.add_argument("run", nargs="+", help="run directory (pre-training or fine-tuning), or an exported model")
    p.set_defaults(func=cmd_status)
