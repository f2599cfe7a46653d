"""Atomic files: writes that a crash cannot leave half done, and JSON in and out.

The run directory (:mod:`dvfb.runs`), datasets, reports and sweeps write through these.
"""

from __future__ import annotations

import dataclasses
import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from dvfb.core.errors import RunDirError


_TEMP_MARK = ".tmp-"


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
