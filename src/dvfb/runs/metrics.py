"""Metrics: JSON lines and TensorBoard events per prefix, purged past a resume point (docs in :mod:`dvfb.runs`)."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from dvfb.core.errors import RunDirError
from dvfb.core.files import _atomic_write
from dvfb.runs.directory import RunDir, _as_run_dir, _check_name


def _scalar(name: str, value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise TypeError(f"metric {name!r} is not a scalar: {value!r}") from exc


def _step_of(record: dict) -> float:
    step = record.get("step")
    return step if isinstance(step, (int, float)) else math.inf


def _prepare_jsonl_for_append(path: Path, purge_step: int | None) -> None:
    """Drop a torn last line (a crash mid-write) and, with ``purge_step``, lines at or after it."""
    if not path.exists():
        return
    with open(path, "rb") as file:
        file.seek(0, os.SEEK_END)
        size = file.tell()
        if size == 0:
            return
        file.seek(size - 1)
        torn = file.read(1) != b"\n"
    if not torn and purge_step is None:
        return
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    if torn:
        lines = lines[:-1]
    if purge_step is not None:
        kept = []
        for line in lines:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                kept.append(line)  # not ours to judge here; read_metrics reports it
                continue
            if not (isinstance(record, dict) and _step_of(record) >= purge_step):
                kept.append(line)
        lines = kept
    text = "".join(lines)
    _atomic_write(path, lambda file: file.write(text.encode("utf-8")))


class MetricsLogger:
    """Scalar metrics to ``metrics/<prefix>.jsonl`` and to TensorBoard (``tb/``).

    Files are opened in append mode, so a resumed run continues its curves. ``purge_step``
    (typically the step of the checkpoint being resumed) drops records with ``step >=
    purge_step`` that the interrupted process logged after that checkpoint, in the JSONL files
    and, through SummaryWriter's own ``purge_step``, in TensorBoard.

    ``sink``: an optional observer of every record, e.g. a :class:`~dvfb.runs.wandb_sink.WandbSink`
    (``sink.log(step, prefix, values)`` after the files are written, ``sink.close()`` on close).
    """

    def __init__(self, run: RunDir | str | os.PathLike, tensorboard: bool = True,
                 purge_step: int | None = None, sink: Any = None) -> None:
        self.run = _as_run_dir(run)
        self._sink = sink
        self.run.metrics_dir.mkdir(parents=True, exist_ok=True)
        self._purge_step = purge_step
        self._files: dict[str, IO[str]] = {}
        self._writer = None
        if tensorboard:
            # Imported here: tensorboard takes ~0.12 s to import and not every caller needs it.
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(log_dir=str(self.run.tb_dir), purge_step=purge_step)

    def _file(self, prefix: str) -> IO[str]:
        file = self._files.get(prefix)
        if file is None:
            path = self.run.metrics_dir / f"{_check_name(prefix, 'metrics prefix')}.jsonl"
            _prepare_jsonl_for_append(path, self._purge_step)
            file = self._files[prefix] = open(path, "a", encoding="utf-8")
        return file

    def log(self, step: int, metrics: Mapping[str, Any], prefix: str = "train") -> None:
        """Record ``metrics`` (floats or 0-d tensors) at ``step`` under ``prefix``."""
        values = {str(name): _scalar(name, value) for name, value in metrics.items()}
        self._write(step, values, values, prefix)

    def log_row(self, step: int, row: Mapping[str, Any], scalars: Mapping[str, Any], prefix: str) -> None:
        """Record ``row`` (any JSON fields: a task's name, a skill vector) at ``step`` in
        ``metrics/<prefix>.jsonl``, and its ``scalars`` in TensorBoard and the sink as
        ``<prefix>/<name>`` (the evaluations while pre-training: ``eval/<task>/return``)."""
        self._write(step, row, {str(name): _scalar(name, value) for name, value in scalars.items()}, prefix)

    def _write(self, step: int, row: Mapping[str, Any], values: dict[str, float], prefix: str) -> None:
        if "step" in row:
            raise ValueError("'step' is reserved in metrics records; pass it as the step argument")
        step = int(step)
        file = self._file(prefix)
        file.write(json.dumps({"step": step, **row}) + "\n")
        # Flushed per call so that a crash loses at most the line being written.
        file.flush()
        if self._writer is not None:
            for name, value in values.items():
                self._writer.add_scalar(f"{prefix}/{name}", value, global_step=step)
        if self._sink is not None and values:
            self._sink.log(step, prefix, values)

    def flush(self) -> None:
        for file in self._files.values():
            file.flush()
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        for file in self._files.values():
            file.close()
        self._files.clear()
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._sink is not None:
            sink, self._sink = self._sink, None
            sink.close()

    def __enter__(self) -> MetricsLogger:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()


def read_metrics(run: RunDir | str | os.PathLike, prefix: str = "train") -> list[dict]:
    """The records of ``metrics/<prefix>.jsonl`` in order ([] when nothing was logged).

    A torn last line (the process died mid-write) is skipped; any other bad line is an error.
    """
    path = _as_run_dir(run).metrics_dir / f"{_check_name(prefix, 'metrics prefix')}.jsonl"
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8")
    lines = text.split("\n")
    records = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as exc:
            if number == len(lines):  # no newline after it: torn by a crash
                break
            raise RunDirError(f"{path}:{number} is not valid JSON: {exc}") from exc
    return records


def recent_rate(record: dict) -> float | None:
    """The frames per second of a pre-training's ``train`` record: ``fps_recent``, the rate since
    the record before it, or in the records of older versions ``fps``, the average since the process
    started (README.md, "Threads and progress"); None when it has neither or the rate is not positive."""
    for key in ("fps_recent", "fps"):
        value = record.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0:
            return float(value)
    return None


def last_metric_record(run: RunDir | str | os.PathLike, prefix: str = "train") -> dict | None:
    """The newest whole record of ``metrics/<prefix>.jsonl``, None when there is none. For progress
    reports: any line that is not a whole record (torn by a crash or a full disk, with or without
    its newline) is passed over rather than hiding the records before it."""
    path = _as_run_dir(run).metrics_dir / f"{_check_name(prefix, 'metrics prefix')}.jsonl"
    if not path.exists():
        return None
    for line in reversed(path.read_text(encoding="utf-8").splitlines()):
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and isinstance(record.get("step"), int):
            return record
    return None
