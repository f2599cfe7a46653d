"""Where a run is (``dvfb status RUN``; README.md, "Using it"): read from its directory alone, so
that it works while the run trains in another process, after it was killed, and on a copy.

For a pre-training or fine-tuning run: its state (``finished``, ``running`` while a process holds
its lock, ``stopped`` when neither, ``not started``), the frames it reached and its budget, the rate
of its newest training record (frames/s since the record before it) with an ETA while it runs, the
age of that record, its newest metrics, its latest resume checkpoint, and, for a pre-training run,
its snapshots, zero-shot results and fine-tuning runs. An exported model is described as such.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from dvfb.core.errors import RunDirError
from dvfb.runs.checkpoints import latest_checkpoint
from dvfb.runs.directory import RunLock
from dvfb.runs.export import describe_export, is_export
from dvfb.runs.layout import FINETUNE, PRETRAIN, FinetuneRun, PretrainRun, run_kind
from dvfb.runs.metrics import last_metric_record, recent_rate


def _checkpoint_step(run) -> int | None:
    path = latest_checkpoint(run)
    if path is None:
        return None
    digits = path.stem.rpartition("_")[2]
    return int(digits) if digits.isdigit() else None


def _progress(run, target: int, finished: int | None) -> dict:
    """What pre-training and fine-tuning runs share: state, frames, rate, ETA, newest metrics."""
    record = last_metric_record(run, "train") or {}
    checkpoint = _checkpoint_step(run)
    holder = RunLock.holder(run.path)
    # A finished run resumed with a larger --frames keeps its old summary until it finishes again:
    # it is finished only when its summary reaches the budget its config now asks for.
    done = finished is not None and finished >= target
    frames = finished if done else max(record.get("step", 0), checkpoint or 0, finished or 0)
    if done:
        state = "finished"
    elif holder is not None:
        state = "running"
    elif record or checkpoint is not None:
        state = "stopped"
    else:
        state = "not started"
    rate = recent_rate(record)
    metrics_file = run.metrics_dir / "train.jsonl"
    age = time.time() - metrics_file.stat().st_mtime if record and metrics_file.is_file() else None
    eta = (target - frames) / rate if state == "running" and rate and target > frames else None
    return {"state": state, "process": holder, "frames": frames, "target": target, "rate": rate, "eta_s": eta,
            "record_age_s": age, "checkpoint": checkpoint,
            "metrics": {k: v for k, v in record.items() if k != "step"}, "metrics_step": record.get("step")}


def run_status(path: str | os.PathLike) -> dict:
    """The status of the run (or exported model) at ``path`` (module docstring); a directory that is
    neither is a :class:`~dvfb.core.errors.RunDirError`."""
    path = Path(path)
    if is_export(path):
        return {"kind": "export", "path": str(path), "description": describe_export(path)}
    kind = run_kind(path) if path.is_dir() else None
    if kind == PRETRAIN:
        run = PretrainRun.open(path)
        config = run.config
        status = {"kind": PRETRAIN, "path": str(path), "agent": config.agent, "domain": config.domain,
                  "preset": config.preset, "seed": config.seed,
                  **_progress(run, config.frames, run.finished_frames()),
                  "snapshots": run.snapshot_frames(),
                  "zero_shot": {result.task: {"mean_return": result.mean_return, "eval_episodes": result.eval_episodes}
                                for _, result in run.zeroshot_results()},
                  "finetune": [run_status(child.path) for child in run.finetune_runs()],
                  "exported_from": (run.exported_from() or {}).get("export"),
                  "threads": run.computed_threads(), "processes": run.computed_processes(),
                  # Made from an exported model (dvfb demo's agent, an EXPORT.eval directory): a
                  # snapshot and nothing trained here.
                  "unpacked": (run.finished_frames() is None and not run.metrics_dir.exists()
                               and latest_checkpoint(run) is None and bool(run.snapshot_frames()))}
        return status
    if kind == FINETUNE:
        run = FinetuneRun.open(path)
        config = run.config
        return {"kind": FINETUNE, "path": str(path), "name": path.name, "agent": config.agent, "task": config.task,
                **_progress(run, config.finetune.frames, run.finished_frames())}
    if not path.exists():
        raise RunDirError(f"{path} does not exist")
    raise RunDirError(f"{path} is not a dvfb run directory (no config.json of a run) nor an exported model")
