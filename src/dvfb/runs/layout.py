"""The kinds of run directory and where everything of a run lives (docs/architecture.md, "Run
directories"): the one place that builds a run's paths and reads its records.

A pre-training run (:class:`PretrainRun`)::

    RUN/config.json                 its PretrainConfig (dvfb.runs.run_config)
    RUN/meta.json                   kind, dvfb version, creation time, command line
    RUN/metrics/, RUN/tb/           metric records and TensorBoard events (dvfb.runs.metrics)
    RUN/checkpoints/                resume checkpoints and their ``latest`` pointer
    RUN/snapshots/snapshot_<F>.pt   the agent after F frames (dvfb.runs.snapshots)
    RUN/pretrain_summary.json       written when it finishes (PretrainSummary)
    RUN/trained_on.json             an offline run's dataset: its path, files and content digests
    RUN/exported_from.json          a run made to evaluate an exported model: which one (its path
                                    and the digest of its weights, docs/sharing.md, "Evaluate")
    RUN/zeroshot/<task>.json        a zero-shot result of the final snapshot; <task>@<F>.json of
                                    an earlier one (ZeroShotResult)
    RUN/finetune/<name>/            its fine-tuning runs
    RUN/analysis/                   what the analyses write

A fine-tuning run (:class:`FinetuneRun`)::

    RUN/finetune/<name>/config.json             its FinetuneRunConfig
    RUN/finetune/<name>/curve.json              its evaluations (Curve)
    RUN/finetune/<name>/finetune_summary.json   written when it finishes (FinetuneSummary)
    RUN/finetune/<name>/metrics/, tb/, checkpoints/

:func:`discover` finds the runs under directories (reports, sweeps).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dvfb.core.errors import ConfigError, RunDirError
from dvfb.core.files import read_json, write_json_atomic
from dvfb.runs.checkpoints import latest_checkpoint, list_snapshots, load_checkpoint
from dvfb.runs.directory import CONFIG_FILE, EXPORT_FORMAT, META_FILE, RunDir
from dvfb.runs.metrics import last_metric_record
from dvfb.runs.migrations import kind_from_config
from dvfb.runs.records import Curve, FinetuneSummary, PretrainSummary, ZeroShotResult
from dvfb.runs.run_config import FinetuneRunConfig, PretrainConfig, load_finetune_run_config, load_run_config

PRETRAIN, FINETUNE = "pretrain", "finetune"
SNAPSHOT_PREFIX = "snapshot_"
# Sub-directories of a run that never hold other runs: not walked during discovery.
_NOT_RUNS = {"snapshots", "checkpoints", "tb", "metrics", "results", "analysis", "zeroshot", "__pycache__"}


def snapshot_name(frames: int) -> str:
    """The file name (without suffix) of the snapshot after ``frames`` frames."""
    return f"{SNAPSHOT_PREFIX}{frames}"


def check_run_name(name: str) -> str:
    """A fine-tuning run's name is one path component under ``RUN/finetune/``: never ``..``, a
    path or a hidden name, which would write (or, with --overwrite, delete) outside it."""
    if not name or name in (".", "..") or "/" in name or "\\" in name or name.startswith("."):
        raise ConfigError(f"--name {name!r} must be a plain name (one path component under RUN/finetune/)")
    return name


def run_kind(path: str | os.PathLike) -> str | None:
    """``"pretrain"``, ``"finetune"`` or None (not a dvfb run) for a directory: its meta.json's
    kind, or for runs written before meta.json recorded one, its config's fields."""
    path = Path(path)
    if not (path / CONFIG_FILE).is_file():
        return None
    meta_path = path / META_FILE
    if meta_path.is_file():
        try:
            kind = read_json(meta_path).get("kind")
        except (RunDirError, AttributeError):
            kind = None
        if kind in (PRETRAIN, FINETUNE):
            return kind
    config = read_json(path / CONFIG_FILE, RunDirError)
    if isinstance(config, dict) and config.get("format") == EXPORT_FORMAT:
        return None  # an exported model (dvfb.runs.export)
    return kind_from_config(config)


def _optional_record(path: Path) -> dict | None:
    """A JSON object a run may have (None when the file is not there); anything else is corrupt."""
    if not path.is_file():
        return None
    data = read_json(path, RunDirError)
    if not isinstance(data, dict):
        raise RunDirError(f"{path} is corrupt: not a JSON object")
    return data


class PretrainRun(RunDir):
    """A pre-training run directory and its config (layout in the module docstring)."""

    kind = PRETRAIN

    def __init__(self, path: str | os.PathLike, config: PretrainConfig):
        super().__init__(path)
        self.config = config

    @classmethod
    def open(cls, path: str | os.PathLike) -> PretrainRun:
        """An existing pre-training run; its config read strictly (errors name the file)."""
        run = RunDir.open(path)
        return cls(run.path, load_run_config(run.config_path))

    @classmethod
    def create(cls, path: str | os.PathLike, config: Any, overwrite: bool = False,
               command: Sequence[str] | None = None, kind: str | None = None) -> PretrainRun:
        run = RunDir.create(path, config, overwrite=overwrite, command=command, kind=cls.kind)
        return cls(run.path, config)

    # The summary ---------------------------------------------------------------------------------
    @property
    def summary_path(self) -> Path:
        return self.path / "pretrain_summary.json"

    def summary(self) -> PretrainSummary | None:
        """The summary of a finished pre-training; None before it finished."""
        return PretrainSummary.read(self.summary_path) if self.summary_path.is_file() else None

    def finished_frames(self) -> int | None:
        """The frames a finished pre-training reached; None when it has not finished."""
        if not self.summary_path.is_file():
            return None
        data = read_json(self.summary_path, RunDirError)
        frames = data.get("frames") if isinstance(data, dict) else None
        return frames if isinstance(frames, int) and not isinstance(frames, bool) else None

    def is_finished(self, frames: int | None = None) -> bool:
        """Whether pre-training finished (at ``frames`` or beyond; default: the config's frames)."""
        done = self.finished_frames()
        return done is not None and done >= (self.config.frames if frames is None else frames)

    def recovered_summary(self) -> PretrainSummary | None:
        """The summary of a run that finished but lost its pretrain_summary.json (deleted by hand, a
        half-copied run), rebuilt from what its end left: a train record at its last step, and its
        final snapshot or a zero-shot result of that snapshot (a study's committed cell keeps no
        snapshot); None when that is not all there."""
        frames = self.config.frames
        last = last_metric_record(self, "train")
        if last is None or last["step"] != frames:
            return None
        evaluated = self.zeroshot_dir.is_dir() and any("@" not in p.stem for p in self.zeroshot_dir.glob("*.json"))
        if frames not in self.snapshot_frames() and not evaluated:
            return None
        episode = last_metric_record(self, "episode")  # none before the first episode ends, none offline
        count = episode.get("episode") if episode is not None else 0
        return PretrainSummary(agent=self.config.agent, domain=self.config.domain, frames=frames,
                               episodes=int(count) if isinstance(count, (int, float)) else None, rebuilt=True)

    def write_summary(self, summary: PretrainSummary) -> None:
        summary.write(self.summary_path)

    # An offline run's data ---------------------------------------------------------------------------
    @property
    def trained_on_path(self) -> Path:
        return self.path / "trained_on.json"

    def trained_on(self) -> dict | None:
        """The fingerprint of the dataset an offline run trained on (``DatasetInfo.fingerprint``);
        None for an online run, or one made before dvfb recorded it."""
        return _optional_record(self.trained_on_path)

    def write_trained_on(self, fingerprint: dict) -> None:
        write_json_atomic(self.trained_on_path, fingerprint)

    # An exported model's evaluation ------------------------------------------------------------------
    @property
    def exported_from_path(self) -> Path:
        return self.path / "exported_from.json"

    def exported_from(self) -> dict | None:
        """Which exported model this run was made from to evaluate it (docs/sharing.md, "Evaluate");
        None for a run that was trained."""
        return _optional_record(self.exported_from_path)

    def write_exported_from(self, record: dict) -> None:
        write_json_atomic(self.exported_from_path, record)

    # Snapshots -----------------------------------------------------------------------------------
    def snapshot_frames(self) -> list[int]:
        """Frames of the run's agent snapshots, ascending."""
        return sorted(int(n[len(SNAPSHOT_PREFIX):]) for n in list_snapshots(self)
                      if n.startswith(SNAPSHOT_PREFIX) and n[len(SNAPSHOT_PREFIX):].isdigit())

    def snapshot_path(self, frames: int) -> Path:
        return self.snapshots_dir / f"{snapshot_name(frames)}.pt"

    # Resume checkpoints ----------------------------------------------------------------------------
    def resume_state(self, mmap: bool = False) -> dict | None:
        """The latest resume checkpoint of the pre-training (the final one of a finished run: its
        whole replay), None when the run has none (a shipped snapshot); ``mmap`` maps its tensors
        from the file instead of reading them. A corrupt checkpoint is a CheckpointError."""
        if latest_checkpoint(self) is None:
            return None
        return load_checkpoint(self, None, map_location="cpu", mmap=mmap)

    # Zero-shot results ---------------------------------------------------------------------------
    @property
    def zeroshot_dir(self) -> Path:
        return self.path / "zeroshot"

    def zeroshot_result(self, task: str, snapshot: int | None = None) -> Path:
        """Where the zero-shot result of ``task`` with the snapshot of ``snapshot`` frames lives
        (default: the newest snapshot, or the config's frames when there is none yet): ``<task>.json``
        for the final snapshot, ``<task>@<frames>.json`` for an earlier one."""
        if snapshot is None:
            frames = self.snapshot_frames()
            snapshot = frames[-1] if frames else self.config.frames
        name = task if snapshot >= self.config.frames else f"{task}@{snapshot}"
        return self.zeroshot_dir / f"{name}.json"

    def write_zeroshot_result(self, result: ZeroShotResult) -> Path:
        path = self.zeroshot_result(result.task, result.snapshot_frames)
        result.write(path)
        return path

    def read_zeroshot_result(self, task: str, snapshot: int | None = None,
                             error: type[Exception] = RunDirError) -> ZeroShotResult | None:
        path = self.zeroshot_result(task, snapshot)
        return self._read_result(path, error) if path.is_file() else None

    def damaged_zeroshot_result(self, task: str, snapshot: int | None = None) -> str | None:
        """Why the result file of ``task`` at ``snapshot`` cannot be trusted (cut short by a full disk or
        an editor, another task's or snapshot's result moved there, no return), None when it is
        missing or whole."""
        try:
            self.read_zeroshot_result(task, snapshot)
        except RunDirError as exc:
            return str(exc)
        return None

    def _read_result(self, path: Path, error: type[Exception]) -> ZeroShotResult:
        """A result file, which must be what its name says: its task's, of its snapshot."""
        result = ZeroShotResult.read(path, error)
        task, _, frames = path.stem.partition("@")
        if result.task != task:
            raise error(f"{path} holds a result of {result.task!r}, not of {task!r} as its name says (moved or "
                        "edited by hand?)")
        if frames and frames.isdigit() and result.snapshot_frames is not None and result.snapshot_frames != int(frames):
            raise error(f"{path} holds the result of the snapshot after {result.snapshot_frames} frames, not {frames} "
                        "as its name says (moved or edited by hand?)")
        return result

    def zeroshot_results(self, error: type[Exception] = RunDirError) -> list[tuple[Path, ZeroShotResult]]:
        """The results of the final snapshot (``<task>.json``), by file name; earlier snapshots'
        ``<task>@<frames>.json`` are not among them. A damaged file is an ``error`` naming it."""
        if not self.zeroshot_dir.is_dir():
            return []
        return [(path, self._read_result(path, error)) for path in sorted(self.zeroshot_dir.glob("*.json"))
                if "@" not in path.stem and not path.name.startswith(".")]

    def snapshot_zeroshot_results(self, error: type[Exception] = RunDirError) -> list[tuple[Path, ZeroShotResult]]:
        """The results of every snapshot, final and earlier (``<task>.json`` and
        ``<task>@<frames>.json``; each result records its snapshot's frames), by file name."""
        if not self.zeroshot_dir.is_dir():
            return []
        return [(path, self._read_result(path, error)) for path in sorted(self.zeroshot_dir.glob("*.json"))
                if not path.name.startswith(".")]

    # Fine-tuning runs ----------------------------------------------------------------------------
    @property
    def finetune_dir(self) -> Path:
        return self.path / "finetune"

    def finetune_path(self, name: str) -> Path:
        """The directory of the fine-tuning run ``name`` (checked to be one plain name)."""
        return self.finetune_dir / check_run_name(name)

    def finetune_runs(self) -> list[FinetuneRun]:
        """Its fine-tuning runs, by name."""
        if not self.finetune_dir.is_dir():
            return []
        return [FinetuneRun.open(child) for child in sorted(self.finetune_dir.iterdir())
                if run_kind(child) == FINETUNE]

    # Analyses ------------------------------------------------------------------------------------
    @property
    def analysis_dir(self) -> Path:
        return self.path / "analysis"


class FinetuneRun(RunDir):
    """A fine-tuning run directory and its config (layout in the module docstring)."""

    kind = FINETUNE

    def __init__(self, path: str | os.PathLike, config: FinetuneRunConfig):
        super().__init__(path)
        self.config = config

    @classmethod
    def open(cls, path: str | os.PathLike) -> FinetuneRun:
        run = RunDir.open(path)
        return cls(run.path, load_finetune_run_config(run.config_path))

    @classmethod
    def create(cls, path: str | os.PathLike, config: Any, overwrite: bool = False,
               command: Sequence[str] | None = None, kind: str | None = None) -> FinetuneRun:
        run = RunDir.create(path, config, overwrite=overwrite, command=command, kind=cls.kind)
        return cls(run.path, config)

    def parent(self) -> PretrainRun | None:
        """The pre-training run it fine-tunes: the directory two levels up when it is one, else the
        one its config names; None when neither is there."""
        for candidate in (self.path.parent.parent if self.path.parent.name == "finetune" else None,
                          Path(self.config.pretrain_run) if self.config.pretrain_run else None):
            if candidate is not None and run_kind(candidate) == PRETRAIN:
                return PretrainRun.open(candidate)
        return None

    @property
    def curve_path(self) -> Path:
        return self.path / "curve.json"

    def curve(self, error: type[Exception] = RunDirError) -> Curve | None:
        return Curve.read(self.curve_path, error) if self.curve_path.is_file() else None

    def write_curve(self, curve: Curve) -> None:
        curve.write(self.curve_path)

    @property
    def summary_path(self) -> Path:
        return self.path / "finetune_summary.json"

    def summary(self) -> FinetuneSummary | None:
        return FinetuneSummary.read(self.summary_path) if self.summary_path.is_file() else None

    def finished_frames(self) -> int | None:
        if not self.summary_path.is_file():
            return None
        data = read_json(self.summary_path, RunDirError)
        frames = data.get("frames") if isinstance(data, dict) else None
        return frames if isinstance(frames, int) and not isinstance(frames, bool) else None

    def is_finished(self, frames: int | None = None) -> bool:
        """Whether fine-tuning finished (at ``frames`` or beyond; default: any summary)."""
        done = self.finished_frames()
        return done is not None and (frames is None or done >= frames)

    def write_summary(self, summary: FinetuneSummary) -> None:
        summary.write(self.summary_path)


def discover(paths: Sequence[str | os.PathLike],
             error: type[Exception] = RunDirError) -> tuple[list[PretrainRun], list[tuple[FinetuneRun, PretrainRun | None]]]:
    """Every pre-training and fine-tuning run in or under ``paths`` (each visited once), with each
    fine-tuning run's pre-training run where it can be found.

    A pre-training run's ``finetune/*`` sub-directories are its fine-tuning runs; other directories
    are searched recursively. A path that does not exist or is not a directory is an ``error``.
    """
    pretrain: list[PretrainRun] = []
    finetune: list[tuple[FinetuneRun, PretrainRun | None]] = []
    seen: set[Path] = set()

    def add_finetune(run: FinetuneRun, parent: PretrainRun | None) -> None:
        key = run.path.resolve()
        if key not in seen:
            seen.add(key)
            finetune.append((run, parent))

    def visit(directory: Path) -> None:
        kind = run_kind(directory)
        if kind == PRETRAIN:
            key = directory.resolve()
            if key in seen:
                return
            seen.add(key)
            run = PretrainRun.open(directory)
            pretrain.append(run)
            for child in run.finetune_runs():
                add_finetune(child, run)
            return
        if kind == FINETUNE:
            run = FinetuneRun.open(directory)
            add_finetune(run, run.parent())
            return
        for child in sorted(directory.iterdir()):
            if child.is_dir() and not child.name.startswith(".") and child.name not in _NOT_RUNS:
                visit(child)

    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise error(f"{path} does not exist")
        if not path.is_dir():
            raise error(f"{path} is not a directory (expected a run directory or a directory of runs)")
        visit(path)
    pretrain.sort(key=lambda r: str(r.path))
    finetune.sort(key=lambda pair: str(pair[0].path))
    return pretrain, finetune


__all__ = ["FINETUNE", "PRETRAIN", "FinetuneRun", "PretrainRun", "check_run_name", "discover", "run_kind",
           "snapshot_name"]
