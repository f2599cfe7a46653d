"""The run directory and its lock (docs in :mod:`dvfb.runs`)."""

from __future__ import annotations

import dataclasses
import fcntl
import json
import os
import platform
import re
import shutil
import uuid
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any, TypeVar

import torch

from dvfb.core.version import __version__
from dvfb.core.config import load_json, save_json, to_dict
from dvfb.core.errors import ConfigError, DvfbError, RunDirError
from dvfb.core.files import _TEMP_MARK, _atomic_write, read_json, write_json_atomic
from dvfb.runs import machine

T = TypeVar("T")

CONFIG_FILE = "config.json"
META_FILE = "meta.json"
# The config.json of an exported model (dvfb.runs.export) says so: such a directory is no run.
EXPORT_FORMAT = "dvfb-model"
LOCK_FILE = ".lock"
# Checkpoint, snapshot and metric names become file names: keep them to one safe path component.
_NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")


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

    @staticmethod
    def check_new(path: Path, overwrite: bool) -> bool:
        """Refuse what :meth:`create` would refuse, touching nothing; True if ``path`` holds a run
        that ``overwrite`` replaces (a group checks all its members' directories first)."""
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
                if is_export_config(path / CONFIG_FILE):
                    raise RunDirError(f"refusing to overwrite {path}: it is an exported model (dvfb export), not a "
                                      "run directory; choose another run name")
                return True
        return False

    @classmethod
    def create(cls, path: str | os.PathLike, config: Any, overwrite: bool = False,
               command: Sequence[str] | None = None, kind: str | None = None) -> RunDir:
        """Make a new run directory holding ``config.json`` and ``meta.json``.

        An existing non-empty directory is an error unless ``overwrite``; then its contents are
        removed first, but only if it is a run directory (has config.json or meta.json), so that a
        mistyped path cannot wipe unrelated files. ``command`` is the command line to record
        (e.g. ``sys.argv``); ``kind`` the kind of run (``pretrain``, ``finetune``) meta.json records.
        """
        if not dataclasses.is_dataclass(config) or isinstance(config, type):
            raise TypeError(f"config must be a dataclass instance, got {type(config).__name__}")
        path = Path(path)
        if cls.check_new(path, overwrite):
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
            **({"kind": kind} if kind is not None else {}),
            "config_class": type(config).__qualname__,
            "config_module": type(config).__module__,
            "dvfb_version": __version__,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": list(command) if command is not None else None,
            "python": platform.python_version(),
            "torch": torch.__version__,
            "machine": machine.describe(),
        }
        write_json_atomic(path / META_FILE, meta)
        return RunDir(path)

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
        if data.get("format") == EXPORT_FORMAT:
            raise RunDirError(f"{path} is an exported model (dvfb export), not a run directory; load it with "
                              "dvfb.load() in Python")
        run = RunDir(path)
        # A resumed run writes into these; one that is not a directory fails now, before anything
        # (config.json included) is rewritten, not halfway through the resume.
        for sub in (run.metrics_dir, run.tb_dir, run.checkpoints_dir, run.snapshots_dir):
            if sub.exists() and not sub.is_dir():
                raise RunDirError(f"{sub} is not a directory; the run directory {path} is damaged (move that file away)")
        return run

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

    def computed_threads(self) -> int:
        """The torch threads the run last computed with: its meta.json's last resume's, else those it
        was made with, else its config's ``torch_threads`` (runs made before meta.json recorded
        threads); 0 when nothing says."""
        try:
            meta = self.read_meta()
        except DvfbError:
            meta = {}
        meta = meta if isinstance(meta, dict) else {}
        for record in reversed(meta.get("resumes") or []):
            threads = record.get("torch_threads") if isinstance(record, dict) else None
            if isinstance(threads, int) and threads > 0:
                return threads
        machine_record = meta.get("machine")
        made = machine_record.get("torch_threads") if isinstance(machine_record, dict) else None
        if isinstance(made, int) and made > 0:
            return made
        configured = getattr(getattr(self, "config", None), "torch_threads", 0)
        return configured if isinstance(configured, int) and configured > 0 else 0

    def computed_processes(self) -> int:
        """The processes of the group the run last computed in (meta.json; 1 when it says nothing)."""
        try:
            meta = self.read_meta()
        except DvfbError:
            return 1
        meta = meta if isinstance(meta, dict) else {}
        for record in [*reversed(meta.get("resumes") or []), meta]:
            count = record.get("processes") if isinstance(record, dict) else None
            if isinstance(count, int) and count > 0:
                return count
        return 1

    def update_meta(self, **fields: Any) -> None:
        """Set top-level fields of meta.json (a group's schedule, once its processes are known)."""
        meta = self.read_meta() if self.meta_path.is_file() else {}
        if not isinstance(meta, dict):
            raise RunDirError(f"{self.meta_path} is corrupt: expected a JSON object")
        write_json_atomic(self.meta_path, {**meta, **fields})

    def record_resume(self, command: Sequence[str] | None, step: int, **fields: Any) -> None:
        """Add a resume to meta.json's ``resumes``: the command that continued the run, the step it
        continued from, when, and the dvfb version and torch threads it ran with (the model card's
        "Made with" lists them after the first command)."""
        meta = self.read_meta() if self.meta_path.is_file() else {}
        if not isinstance(meta, dict):
            raise RunDirError(f"{self.meta_path} is corrupt: expected a JSON object")
        meta.setdefault("resumes", []).append({
            "command": list(command) if command is not None else None, "step": int(step),
            "resumed": datetime.now(timezone.utc).isoformat(timespec="seconds"), "dvfb_version": __version__,
            "torch_threads": torch.get_num_threads(), **fields})
        write_json_atomic(self.meta_path, meta)


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

    @staticmethod
    def holder(path: str | os.PathLike) -> str | None:
        """The process id written by the live holder of ``path``'s lock, or None when nobody
        holds it (no lock file, or a stale one of a dead process)."""
        try:
            file = open(Path(path) / LOCK_FILE, encoding="utf-8")
        except OSError:
            return None
        with file:
            try:
                fcntl.flock(file.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                return file.read().strip() or "unknown"
            fcntl.flock(file.fileno(), fcntl.LOCK_UN)
            return None

    def remove_if_created(self) -> None:
        """Undo the directory this lock created (a run that failed before writing anything)."""
        if self.created_directory and {p.name for p in self.path.iterdir()} <= {LOCK_FILE}:
            shutil.rmtree(self.path, ignore_errors=True)


def is_export_config(path: Path) -> bool:
    """Whether the JSON file ``path`` is the config.json of an exported model (dvfb.runs.export)."""
    try:
        data = read_json(path)
    except (RunDirError, OSError):
        return False
    return isinstance(data, dict) and data.get("format") == EXPORT_FORMAT


def check_writable(directory: str | os.PathLike) -> None:
    """Fail early, with one line, if files cannot be written in ``directory``: a read-only file
    system, a permission problem or a full disk. Creates nothing: a directory that does not exist yet
    is probed in its nearest existing parent, where its creation would write (so a command refused
    later, before its work, leaves no empty folders behind)."""
    directory = Path(directory)
    existing = directory
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    probe = existing / f".write-probe{_TEMP_MARK}{uuid.uuid4().hex[:8]}"
    try:
        if not existing.is_dir():
            raise NotADirectoryError(20, "Not a directory", str(existing))
        with open(probe, "wb") as file:
            file.write(b"x")
            file.flush()
            os.fsync(file.fileno())
    except OSError as exc:
        raise RunDirError(f"cannot write in {existing}: {exc.strerror or exc}") from exc
    finally:
        try:
            probe.unlink(missing_ok=True)
        except OSError:
            pass  # it was never created (read-only, full)


def _as_run_dir(run: RunDir | str | os.PathLike) -> RunDir:
    return run if isinstance(run, RunDir) else RunDir(run)


def _check_name(name: str, what: str) -> str:
    if not isinstance(name, str) or not _NAME_PATTERN.fullmatch(name) or _TEMP_MARK in name:
        raise ValueError(
            f"{what} name {name!r} must be letters, digits, '_', '-' or '.', starting with a "
            "letter or digit"
        )
    return name
