"""``dvfb status``: where a run is (frames, rate, ETA, newest metrics, finished or not)."""

from __future__ import annotations

import argparse

from pathlib import Path

from dvfb.analysis import bands
from dvfb.analysis.common import method_name
from dvfb.cli.common import Formatter
from dvfb.core.errors import ConfigError
from dvfb.runs.layout import PretrainRun
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


def _health(status: dict, reference) -> list[str]:
    """The verdict lines of a pre-training run's newest evaluation while pre-training (docs/health.md)."""
    run = PretrainRun.open(status["path"])
    found = bands.run_verdicts(run, reference)
    if found:
        return [f"  health: {v.line()}" for v in found]
    if not run.config.eval_every:
        return ["  health: no evaluations while pre-training (--eval-every 0); dvfb zeroshot evaluates its snapshots"]
    return [f"  health: no evaluation yet (the first at {run.config.eval_every:,} frames, --eval-every)"]


def _print(status: dict, reference=None) -> None:
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
        if status["threads"]:
            group = (f", in one of the {status['processes']} processes its group was split over"
                     if status["processes"] > 1 else "")
            print(f"  computed with {status['threads']} torch thread(s){group} (meta.json; a --resume keeps them)")
    metrics = _metrics_line(status)
    if metrics:
        print(f"  {metrics}")
    snapshots = ", ".join(str(f) for f in status["snapshots"]) or "none"
    checkpoint = status["checkpoint"] if status["checkpoint"] is not None else "none"
    print(f"  resume checkpoint: {checkpoint}; snapshots: {snapshots}")
    if not status["unpacked"]:
        for line in _health(status, reference):
            print(line)
    if status["zero_shot"]:
        print("  zero-shot: " + ", ".join(f"{task} {r['mean_return']:.1f} ({r['eval_episodes']} episodes)"
                                          for task, r in sorted(status["zero_shot"].items())))
    for child in status["finetune"]:
        _print(child, reference)


def cmd_status(args: argparse.Namespace) -> int:
    statuses = [run_status(path) for path in args.run]  # every path checked before anything is printed
    reference = bands.load_bands(args.bands)
    if args.plot is not None:
        pretraining = [s for s in statuses if s["kind"] == "pretrain"]
        if len(pretraining) != 1:
            raise ConfigError("--plot draws one pre-training run: give one run directory")
        plot_path = Path(args.plot)
        if plot_path.suffix.lower() != ".png":
            raise ConfigError(f"--plot {plot_path}: give a .png file")
        if plot_path.exists() and not args.overwrite:
            raise ConfigError(f"{plot_path} exists; pass --overwrite to replace it")
    for status in statuses:
        _print(status, reference)
    if args.plot is not None:
        run = PretrainRun.open(pretraining[0]["path"])
        config = run.config
        out = bands.plot(str(run.path), method_name(config), config.domain, config.preset,
                         bands.read_eval_records(run.path), reference, plot_path)
        print(f"evaluations over the reference bands: {out}")
    return 0


def register(sub, agent: str) -> None:
    p = sub.add_parser(
        "status", help="where a run is: frames, rate, ETA, newest metrics, finished or not", formatter_class=Formatter,
        description="Read a run directory (while it trains in another process, or after it stopped) and print its "
                    "state (finished, running, stopped, not started), the frames it reached of its budget, the rate "
                    "of its newest training record (frames/s since the record before it) and an ETA while it runs, "
                    "its newest metrics, its resume checkpoint and snapshots, its zero-shot results and its "
                    "fine-tuning runs, and the health of its newest evaluation while pre-training against its method's "
                    "reference band (docs/health.md). Reads only; a sweep's cells: dvfb sweep status.")
    p.add_argument("run", nargs="+", help="run directory (pre-training or fine-tuning), or an exported model")
    p.add_argument("--bands", default=None, metavar="FILE.json",
                   help="reference bands to read the evaluations against (dvfb bands; default: the package's, from "
                        "docs/results/cpu_100k)")
    p.add_argument("--plot", default=None, metavar="OUT.png",
                   help="draw the run's evaluations while pre-training per task over its band")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --plot file")
    p.set_defaults(func=cmd_status)
