"""Checkpoints and snapshots: atomic saves, the ``latest`` pointer, safe loading (docs in :mod:`dvfb.runs`)."""

from __future__ import annotations

import os
import pickle
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from dvfb.core.errors import CheckpointError
from dvfb.core.files import _atomic_write, _remove_stale_temp_files
from dvfb.runs.directory import _NAME_PATTERN, RunDir, _as_run_dir, _check_name

LATEST_POINTER = "latest"
CHECKPOINT_SUFFIX = ".pt"
# The ``kind`` of a pre-training run's resume checkpoints: what pre-training writes and what the
# readers of a run's replay (zero-shot's reward functions, dataset export) look for.
PRETRAIN_RESUME_KIND = "pretrain_resume"


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
    if current is None or not (checkpoints_dir / current).is_file():
        return []  # a pointer to a missing file: the others may be all that is left
    removed = [p for p in checkpoints_dir.glob(f"*{CHECKPOINT_SUFFIX}") if p.name != current]
    for path in removed:
        path.unlink(missing_ok=True)
    return removed


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


def _load_state(path: Path, map_location: Any, weights_only: bool, mmap: bool = False) -> dict:
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    # torch.save writes a zip archive: anything else (random bytes, a truncated head) is corrupt,
    # whatever the unpickler would make of it.
    if not zipfile.is_zipfile(path):
        raise CheckpointError(f"checkpoint {path} is truncated or corrupt: it is not a torch checkpoint archive")
    try:
        state = torch.load(path, map_location=map_location, weights_only=weights_only, mmap=mmap)
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
                    map_location: Any = "cpu", weights_only: bool = True, mmap: bool = False) -> dict:
    """Load ``checkpoints/<name>.pt``, or with ``name=None`` the one ``latest`` points at.

    A missing pointer or file, or a truncated or corrupt file, raises CheckpointError naming it.
    ``mmap`` maps the tensors' storage from the file instead of reading it (torch.load's ``mmap``):
    what a reader of one part of a large checkpoint at a time (a dataset export) wants.
    """
    checkpoints_dir = _as_run_dir(run).checkpoints_dir
    if name is None:
        file_name = _read_pointer(checkpoints_dir)
        if file_name is None:
            raise CheckpointError(
                f"no checkpoint to resume from: {checkpoints_dir / LATEST_POINTER} does not exist")
    else:
        file_name = _file_name(name, "checkpoint")
    return _load_state(checkpoints_dir / file_name, map_location, weights_only, mmap)


def load_snapshot(run: RunDir | str | os.PathLike, name: str, map_location: Any = "cpu",
                  weights_only: bool = True) -> dict:
    """Load ``snapshots/<name>.pt``; CheckpointError when it is missing or unreadable."""
    path = _as_run_dir(run).snapshots_dir / _file_name(name, "snapshot")
    return _load_state(path, map_location, weights_only)
