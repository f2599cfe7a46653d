"""Run directories, metrics, results and checkpoints.

Every run (pre-training, fine-tuning, zero-shot evaluation, ...) owns one directory::

    <run>/
      config.json              the full resolved typed config (dvfb.config.save_json)
      meta.json                config class, dvfb version, creation time, command line
      metrics/<prefix>.jsonl   one JSON object per MetricsLogger.log call: {"step": 1000, "x": 0.5}
      tb/                      TensorBoard event files, scalar tags "<prefix>/<name>"
      checkpoints/<name>.pt    resume checkpoints (torch.save of a state dict)
      checkpoints/latest       text file holding the file name of the current resume checkpoint
      snapshots/<name>.pt      checkpoints kept for good (e.g. the model after N steps)
      results/                 machine-readable results, written with write_json_atomic

Writes that a crash must not leave half done (checkpoints, the ``latest`` pointer, results, meta)
go to a temporary file in the same directory, are flushed and fsync'ed, and then renamed over the
target with ``os.replace``, which is atomic on POSIX and Windows: a reader sees the old file or the
new one, never a mixture. ``save_checkpoint`` moves ``latest`` only after the new checkpoint is
complete, and deletes the checkpoint it replaced only after that, so at every instant ``latest``
names a complete file. One process writes a run directory at a time.

Checkpoints are read with ``torch.load(weights_only=True)`` by default, so a state should hold
only tensors, numbers, strings, ``None`` and lists/tuples/dicts of these (``torch.get_rng_state()``
and ``numpy.random.Generator.bit_generator.state`` qualify; legacy ``np.random.get_state()``
does not).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pickle
import platform
import re
import shutil
import uuid
import zipfile
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
import torch

from dvfb import __version__
from dvfb.config import load_json, save_json, to_dict
from dvfb.errors import CheckpointError, ConfigError, RunDirError

T = TypeVar("T")

CONFIG_FILE = "config.json"
META_FILE = "meta.json"
LOCK_FILE = ".lock"
LATEST_POINTER = "latest"
CHECKPOINT_SUFFIX = ".pt"
_TEMP_MARK = ".tmp-"
# Checkpoint, snapshot and metric names become file names: keep them to one safe path component.
_NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")


# ---------------------------------------------------------------------------------------------
# atomic files


def _fsync_directory(directory: Path) -> None:
    # Makes the rename itself durable; not possible on every platform, where it is skipped.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _atomic_write(path: Path, write: Callable[[IO[bytes]], None]) -> None:
    """Write ``path`` through ``write(file)`` so that it is either complete or untouched.

    Whatever goes wrong (an exception in ``write``, a full disk, an interrupt), the temporary file
    is removed and the exception propagates.
    """
    path = Path(path)
    temp = path.with_name(f".{path.name}{_TEMP_MARK}{uuid.uuid4().hex[:12]}")
    try:
        with open(temp, "wb") as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temp, path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
    _fsync_directory(path.parent)


def _remove_stale_temp_files(directory: Path) -> None:
    """Delete temporary files a killed process left behind (they can be as big as a checkpoint)."""
    for stale in directory.glob(f".*{_TEMP_MARK}*"):
        stale.unlink(missing_ok=True)


def _json_default(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.tolist()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def read_json(path: str | os.PathLike, error: type[Exception] = RunDirError) -> Any:
    """The parsed contents of the JSON file ``path``; an unreadable or malformed file raises
    ``error`` (the caller's error type) with the path and the reason."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise error(f"{path} is corrupt or unreadable: {exc}") from exc


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically, creating parent directories.

    Tensors, numpy values, paths and dataclasses are converted. Non-finite floats are written as
    ``NaN``/``Infinity``, which Python's json module reads back.
    """
    path = Path(path)
    text = json.dumps(obj, indent=2, default=_json_default) + "\n"  # fails before touching disk
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, lambda file: file.write(text.encode("utf-8")))


# ---------------------------------------------------------------------------------------------
# run directory


class RunDir:
    """One run's directory (layout in the module docstring). Make it with create or open."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunDir({str(self.path)!r})"

    def __fspath__(self) -> str:
        return str(self.path)

    @property
    def config_path(self) -> Path:
        return self.path / CONFIG_FILE

    @property
    def meta_path(self) -> Path:
        return self.path / META_FILE

    @property
    def metrics_dir(self) -> Path:
        return self.path / "metrics"

    @property
    def tb_dir(self) -> Path:
        return self.path / "tb"

    @property
    def checkpoints_dir(self) -> Path:
        return self.path / "checkpoints"

    @property
    def snapshots_dir(self) -> Path:
        return self.path / "snapshots"

    @property
    def results_dir(self) -> Path:
        return self.path / "results"

    @classmethod
    def create(cls, path: str | os.PathLike, config: Any, overwrite: bool = False,
               command: Sequence[str] | None = None) -> RunDir:
        """Make a new run directory holding ``config.json`` and ``meta.json``.

        An existing non-empty directory is an error unless ``overwrite``; then its contents are
        removed first, but only if it is a run directory (has config.json or meta.json), so that a
        mistyped path cannot wipe unrelated files. ``command`` is the command line to record
        (e.g. ``sys.argv``).
        """
        if not dataclasses.is_dataclass(config) or isinstance(config, type):
            raise TypeError(f"config must be a dataclass instance, got {type(config).__name__}")
        path = Path(path)
        if path.exists() or path.is_symlink():
            if not path.is_dir():
                raise RunDirError(f"{path} exists and is not a directory; choose another run name")
            if any(child.name != LOCK_FILE for child in path.iterdir()):
                if not overwrite:
                    raise RunDirError(
                        f"run directory {path} already exists and is not empty; pass --overwrite "
                        "to replace it, or choose another run name"
                    )
                if not ((path / CONFIG_FILE).exists() or (path / META_FILE).exists()):
                    raise RunDirError(
                        f"refusing to overwrite {path}: it does not look like a dvfb run directory "
                        f"(no {CONFIG_FILE} or {META_FILE}); remove it yourself or choose another "
                        "run name"
                    )
                try:
                    # Everything but the lock file, which the overwriting process holds.
                    for child in path.iterdir():
                        if child.name == LOCK_FILE:
                            continue
                        if child.is_dir() and not child.is_symlink():
                            shutil.rmtree(child)
                        else:
                            child.unlink()
                except OSError as exc:
                    raise RunDirError(f"cannot remove {path} to overwrite it: {exc}") from exc
        try:
            path.mkdir(parents=True, exist_ok=True)
            save_json(config, path / CONFIG_FILE)
        except OSError as exc:
            raise RunDirError(f"cannot create run directory {path}: {exc}") from exc
        meta = {
            "config_class": type(config).__qualname__,
            "config_module": type(config).__module__,
            "dvfb_version": __version__,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": list(command) if command is not None else None,
            "python": platform.python_version(),
            "torch": torch.__version__,
        }
        write_json_atomic(path / META_FILE, meta)
        return cls(path)

    @classmethod
    def open(cls, path: str | os.PathLike) -> RunDir:
        """Open an existing run; RunDirError when it is missing or its config.json is unusable."""
        path = Path(path)
        if not path.exists():
            raise RunDirError(f"run directory {path} does not exist")
        if not path.is_dir():
            raise RunDirError(f"{path} is not a directory, so not a run directory")
        config_path = path / CONFIG_FILE
        if not config_path.is_file():
            raise RunDirError(f"{path} is not a dvfb run directory: it has no {CONFIG_FILE}")
        data = read_json(config_path, RunDirError)
        if not isinstance(data, dict):
            raise RunDirError(f"{config_path} is corrupt: expected a JSON object")
        return cls(path)

    def load_config(self, cls: type[T]) -> T:
        """The run's config as ``cls``; unknown keys or wrong types raise ConfigError."""
        try:
            return load_json(cls, self.config_path)
        except ConfigError as exc:
            if str(self.config_path) in str(exc):
                raise
            raise ConfigError(f"{self.config_path}: {exc}") from exc

    def save_config(self, config: Any) -> None:
        """Replace ``config.json`` atomically (a resumed run may extend its frame budget)."""
        text = json.dumps(to_dict(config), indent=2, sort_keys=True) + "\n"
        _atomic_write(self.config_path, lambda file: file.write(text.encode("utf-8")))

    def read_meta(self) -> dict:
        """The contents of meta.json."""
        return read_json(self.meta_path, RunDirError)


class RunLock:
    """One writer per run directory: an exclusive OS lock (``flock``) on ``<run>/.lock``.

    The lock file holds the holder's process id, which the refusal names. The OS releases the
    lock when its process dies, so a stale lock file of a dead process is simply taken over.
    Entering creates the run directory if needed (after the caller has validated its inputs).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._file: IO[str] | None = None
        self.created_directory = False

    def __enter__(self) -> RunLock:
        import fcntl

        try:
            if not self.path.exists():
                self.path.mkdir(parents=True)
                self.created_directory = True
            file = open(self.path / LOCK_FILE, "a+", encoding="utf-8")
        except OSError as exc:
            raise RunDirError(f"cannot use run directory {self.path}: {exc.strerror or exc}") from exc
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            file.seek(0)
            holder = file.read().strip() or "unknown"
            file.close()
            raise RunDirError(f"run directory {self.path} is in use by process {holder}; wait for it to "
                              "finish or stop it (kill -TERM checkpoints a pre-training run)") from None
        file.seek(0)
        file.truncate()
        file.write(f"{os.getpid()}\n")
        file.flush()
        self._file = file
        return self

    def __exit__(self, *exc_info: Any) -> None:
        if self._file is not None:
            self._file.close()  # closing releases the flock
            self._file = None

    def remove_if_created(self) -> None:
        """Undo the directory this lock created (a run that failed before writing anything)."""
        if self.created_directory and {p.name for p in self.path.iterdir()} <= {LOCK_FILE}:
            shutil.rmtree(self.path, ignore_errors=True)


def check_writable(directory: str | os.PathLike) -> None:
    """Fail early, with one line, if files cannot be written in ``directory`` (created if needed):
    a read-only file system, a permission problem or a full disk."""
    directory = Path(directory)
    probe = directory / f".write-probe{_TEMP_MARK}{uuid.uuid4().hex[:8]}"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as file:
            file.write(b"x")
            file.flush()
            os.fsync(file.fileno())
    except OSError as exc:
        raise RunDirError(f"cannot write in {directory}: {exc.strerror or exc}") from exc
    finally:
        try:
            probe.unlink(missing_ok=True)
        except OSError:
            pass  # it was never created (read-only, full)


def remove_orphaned_checkpoints(run: RunDir | str | os.PathLike) -> list[Path]:
    """Delete resume checkpoints that ``latest`` does not name, and stale temporary files: what a
    process killed between moving the pointer and deleting the old checkpoint leaves behind."""
    checkpoints_dir = _as_run_dir(run).checkpoints_dir
    if not checkpoints_dir.is_dir():
        return []
    _remove_stale_temp_files(checkpoints_dir)
    try:
        current = _read_pointer(checkpoints_dir)
    except CheckpointError:
        return []  # nothing is deleted on the word of a corrupt pointer
    if current is None:
        return []
    removed = [p for p in checkpoints_dir.glob(f"*{CHECKPOINT_SUFFIX}") if p.name != current]
    for path in removed:
        path.unlink(missing_ok=True)
    return removed


def _as_run_dir(run: RunDir | str | os.PathLike) -> RunDir:
    return run if isinstance(run, RunDir) else RunDir(run)


def _check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not _NAME_PATTERN.fullmatch(name) or _TEMP_MARK in name:
        raise ValueError(
            f"{what} name {name!r} must be letters, digits, '_', '-' or '.', starting with a "
            "letter or digit"
        )
    return name


# ---------------------------------------------------------------------------------------------
# metrics


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
    """

    def __init__(self, run: RunDir | str | os.PathLike, tensorboard: bool = True,
                 purge_step: int | None = None) -> None:
        self.run = _as_run_dir(run)
        self.run.metrics_dir.mkdir(parents=True, exist_ok=True)
        self._purge_step = purge_step
        self._files: dict[str, IO[str]] = {}
        self._writer = None
        if tensorboard:
            # Imported here: tensorboard is slow to import and not every caller needs it.
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
        if "step" in metrics:
            raise ValueError("'step' is reserved in metrics records; pass it as the step argument")
        values = {str(name): _scalar(name, value) for name, value in metrics.items()}
        step = int(step)
        file = self._file(prefix)
        file.write(json.dumps({"step": step, **values}) + "\n")
        # Flushed per call so that a crash loses at most the line being written.
        file.flush()
        if self._writer is not None:
            for name, value in values.items():
                self._writer.add_scalar(f"{prefix}/{name}", value, global_step=step)

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


# ---------------------------------------------------------------------------------------------
# checkpoints


def _torch_save_atomic(path: Path, state: Mapping[str, Any], what: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temp_files(path.parent)
    try:
        _atomic_write(path, lambda file: torch.save(state, file))
    except (OSError, RuntimeError) as exc:
        # A full disk or a permission problem: the user's to fix. (torch.save's zip writer turns a
        # failed write, e.g. ENOSPC, into a RuntimeError raised while handling the OSError.) Other
        # exceptions (e.g. an object that cannot be pickled) are bugs and keep their traceback.
        os_error = _os_error_in(exc)
        if os_error is None:
            raise
        raise CheckpointError(f"cannot write {what} {path}: {os_error.strerror or os_error}") from exc


def _os_error_in(exc: BaseException | None) -> OSError | None:
    """The OSError behind ``exc``, following the chain of causes and contexts."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, OSError):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _read_pointer(checkpoints_dir: Path) -> str | None:
    """The file name ``latest`` names, None without a pointer; CheckpointError when corrupt."""
    pointer = checkpoints_dir / LATEST_POINTER
    try:
        content = pointer.read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"cannot read checkpoint pointer {pointer}: {exc}") from exc
    stem = content[: -len(CHECKPOINT_SUFFIX)] if content.endswith(CHECKPOINT_SUFFIX) else ""
    if not stem or not _NAME_PATTERN.fullmatch(stem):
        raise CheckpointError(f"checkpoint pointer {pointer} is corrupt (it holds {content!r})")
    return content


def _file_name(name: str, what: str) -> str:
    if isinstance(name, str) and name.endswith(CHECKPOINT_SUFFIX):
        name = name[: -len(CHECKPOINT_SUFFIX)]
    return _check_name(name, what) + CHECKPOINT_SUFFIX


def save_checkpoint(run: RunDir | str | os.PathLike, state: Mapping[str, Any], name: str,
                    keep_previous: bool = False) -> Path:
    """Save a resume checkpoint ``checkpoints/<name>.pt`` atomically and point ``latest`` at it.

    Unless ``keep_previous``, the checkpoint ``latest`` named before is deleted once the pointer
    has moved (snapshots live in ``snapshots/`` and are never touched). If writing fails, the
    previous checkpoint and pointer are unchanged and no temporary file remains.
    """
    checkpoints_dir = _as_run_dir(run).checkpoints_dir
    file_name = _file_name(name, "checkpoint")
    try:
        previous = _read_pointer(checkpoints_dir)
    except CheckpointError:
        previous = None  # a corrupt pointer is simply replaced; nothing is deleted on its word
    path = checkpoints_dir / file_name
    _torch_save_atomic(path, state, "checkpoint")
    pointer = checkpoints_dir / LATEST_POINTER
    try:
        _atomic_write(pointer, lambda file: file.write(f"{file_name}\n".encode("utf-8")))
    except OSError as exc:
        raise CheckpointError(f"cannot update checkpoint pointer {pointer}: {exc}") from exc
    if not keep_previous and previous is not None and previous != file_name:
        (checkpoints_dir / previous).unlink(missing_ok=True)
    return path


def save_snapshot(run: RunDir | str | os.PathLike, state: Mapping[str, Any], name: str) -> Path:
    """Save ``snapshots/<name>.pt`` atomically; dvfb never deletes it and ``latest`` stays."""
    path = _as_run_dir(run).snapshots_dir / _file_name(name, "snapshot")
    _torch_save_atomic(path, state, "snapshot")
    return path


def latest_checkpoint(run: RunDir | str | os.PathLike) -> Path | None:
    """The path ``checkpoints/latest`` names, or None when no checkpoint was saved yet."""
    checkpoints_dir = _as_run_dir(run).checkpoints_dir
    file_name = _read_pointer(checkpoints_dir)
    return None if file_name is None else checkpoints_dir / file_name


def list_snapshots(run: RunDir | str | os.PathLike) -> list[str]:
    """Names of the saved snapshots, sorted."""
    directory = _as_run_dir(run).snapshots_dir
    return sorted(p.name[: -len(CHECKPOINT_SUFFIX)] for p in directory.glob(f"*{CHECKPOINT_SUFFIX}")
                  if not p.name.startswith("."))


def _load_state(path: Path, map_location: Any, weights_only: bool) -> dict:
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    # torch.save writes a zip archive: anything else (random bytes, a truncated head) is corrupt,
    # whatever the unpickler would make of it.
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"checkpoint {path} is truncated or corrupt: it is not a torch checkpoint archive")
    try:
        state = torch.load(path, map_location=map_location, weights_only=weights_only)
    except pickle.UnpicklingError as exc:
        if weights_only and "weights only" in str(exc).lower():
            raise CheckpointError(
                f"checkpoint {path} holds objects other than tensors and plain containers, which "
                f"a weights-only load refuses ({str(exc).splitlines()[0]})"
            ) from exc
        raise CheckpointError(f"checkpoint {path} is corrupt and cannot be read: {exc}") from exc
    except Exception as exc:  # torch reports truncation/corruption with assorted exception types
        raise CheckpointError(
            f"checkpoint {path} is truncated or corrupt and cannot be read "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {path} does not hold a state dict "
                              f"(found {type(state).__name__})")
    return state


def load_checkpoint(run: RunDir | str | os.PathLike, name: str | None = None,
                    map_location: Any = "cpu", weights_only: bool = True) -> dict:
    """Load ``checkpoints/<name>.pt``, or with ``name=None`` the one ``latest`` points at.

    A missing pointer or file, or a truncated or corrupt file, raises CheckpointError naming it.
    """
    checkpoints_dir = _as_run_dir(run).checkpoints_dir
    if name is None:
        file_name = _read_pointer(checkpoints_dir)
        if file_name is None:
            raise CheckpointError(
                f"no checkpoint to resume from: {checkpoints_dir / LATEST_POINTER} does not exist")
    else:
        file_name = _file_name(name, "checkpoint")
    return _load_state(checkpoints_dir / file_name, map_location, weights_only)


def load_snapshot(run: RunDir | str | os.PathLike, name: str, map_location: Any = "cpu",
                  weights_only: bool = True) -> dict:
    """Load ``snapshots/<name>.pt``; CheckpointError when it is missing or unreadable."""
    path = _as_run_dir(run).snapshots_dir / _file_name(name, "snapshot")
    return _load_state(path, map_location, weights_only)
