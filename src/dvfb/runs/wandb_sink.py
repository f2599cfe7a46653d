"""Optional Weights & Biases logging of a run's metrics (docs/methods.md, "Logging to Weights & Biases").

The ``log`` section of a run config (:class:`LogConfig`, flags ``--log.*``) turns it on. A run that
logs to W&B keeps its JSON lines and TensorBoard events as before; :class:`WandbSink` only observes
what :class:`~dvfb.runs.metrics.MetricsLogger` writes and sends the same scalars, named as the
TensorBoard tags (``<prefix>/<name>``), at the same steps. It reads no random stream and changes no
number of the run.

* The W&B run is named after the run directory and has a stable id, kept in ``RUN/wandb_id.txt``:
  a resumed run (``--resume``) continues the same W&B run. The run config is logged once, as the
  W&B run's config.
* W&B's own files go to ``RUN/wandb/``. Offline (``--log.wandb-mode offline``, or ``auto`` without
  network or credentials), they stay there, one ``offline-run-*`` directory per process, and
  ``wandb sync RUN/wandb/offline-run-*`` uploads them later.
* ``wandb`` is imported only when the section is on; without it installed, a run that asks for it
  stops with one line before anything is created (:func:`require_wandb`).
"""

from __future__ import annotations

import netrc
import os
import secrets
import socket
import string
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from dvfb.core.config import param
from dvfb.core.errors import ConfigError, RunDirError
from dvfb.core.files import _atomic_write
from dvfb.runs.directory import RunDir

WANDB_MODES = ("auto", "online", "offline")
ID_FILE = "wandb_id.txt"
INSTALL_HINT = "pip install 'dvfb[wandb]'"
_ID_ALPHABET = string.ascii_lowercase + string.digits
_DEFAULT_HOST = "https://api.wandb.ai"


@dataclass
class LogConfig:
    """Where a run's metrics go besides metrics/*.jsonl and TensorBoard: Weights & Biases, optionally."""

    wandb: bool = param(False, "Also log the run's metrics to Weights & Biases (needs pip install 'dvfb[wandb]'): "
                               "the same scalars at the same steps as TensorBoard, and the run config.")
    wandb_project: str = param("dvfb", "W&B project.")
    wandb_entity: str = param("", "W&B entity (user or team); empty: the account's default.")
    wandb_group: str = param("", "W&B group of the run (e.g. one per sweep); empty: none.")
    wandb_tags: list[str] = param([], "W&B tags of the run.")
    wandb_mode: str = param("auto", "auto: online when the W&B server is reachable and credentials are found "
                                    "(WANDB_API_KEY or `wandb login`), otherwise offline; online; offline: W&B's "
                                    "files stay in RUN/wandb/ for a later `wandb sync`.", WANDB_MODES)


def require_wandb(log: LogConfig) -> None:
    """Refuse, with one line, a run that asks for W&B where it cannot log: wandb not installed, or
    ``--log.wandb-mode online`` without credentials. Called before anything is created."""
    if not log.wandb:
        return
    try:
        # lazy: wandb is optional and slow to import (~0.4 s); only a run that logs to it needs it
        import wandb  # noqa: F401
    except ImportError:
        raise ConfigError(f"--log.wandb true needs the wandb package, which is not installed: {INSTALL_HINT}") \
            from None
    if log.wandb_mode == "online" and not _has_credentials():
        raise ConfigError("--log.wandb-mode online needs W&B credentials (WANDB_API_KEY or `wandb login`); "
                          "pass --log.wandb-mode offline to log locally and `wandb sync` later")
    # An unreachable server would fail wandb.init only after the run directory exists (and after
    # W&B's own timeout): refused here, before anything is created.
    if log.wandb_mode == "online" and not _reachable():
        raise ConfigError(f"--log.wandb-mode online: the W&B server {_host()} cannot be reached; pass "
                          "--log.wandb-mode offline to log locally and `wandb sync` later")


def _host() -> str:
    return urlparse(os.environ.get("WANDB_BASE_URL") or _DEFAULT_HOST).hostname or "api.wandb.ai"


def _has_credentials() -> bool:
    """Whether W&B finds an API key: ``WANDB_API_KEY``, or a netrc entry for its host (what
    ``wandb login`` writes)."""
    if os.environ.get("WANDB_API_KEY"):
        return True
    path = os.environ.get("NETRC") or os.path.expanduser("~/.netrc")
    try:
        return netrc.netrc(path).authenticators(_host()) is not None
    except (OSError, netrc.NetrcParseError):
        return False


def _reachable(timeout: float = 3.0) -> bool:
    url = urlparse(os.environ.get("WANDB_BASE_URL") or _DEFAULT_HOST)
    port = url.port or (80 if url.scheme == "http" else 443)
    try:
        with socket.create_connection((_host(), port), timeout=timeout):
            return True
    except OSError:
        return False


def resolve_mode(mode: str) -> str | None:
    """The mode handed to ``wandb.init``: ``auto`` follows ``WANDB_MODE`` when it is set (None: W&B
    reads it), else is online with credentials and a reachable server, offline otherwise."""
    if mode != "auto":
        return mode
    if os.environ.get("WANDB_MODE"):
        return None
    return "online" if _has_credentials() and _reachable() else "offline"


def stored_wandb_id(run: RunDir) -> str | None:
    """The W&B id in ``RUN/wandb_id.txt`` (None: no such file); a damaged file is refused in one line.
    Writes nothing: a resume checks it with everything else before it changes any file."""
    path = Path(run.path) / ID_FILE
    if not path.exists():
        return None
    try:
        run_id = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise RunDirError(f"cannot read {path}: {exc}") from exc
    if run_id and all(c in _ID_ALPHABET for c in run_id):
        return run_id
    raise RunDirError(f"{path} does not hold a W&B run id ({run_id[:40]!r}); remove it to start a new W&B run")


def wandb_run_id(run: RunDir) -> str:
    """The run's W&B id: the one in ``RUN/wandb_id.txt``, or a new random one written there (from the
    operating system's entropy, so that no random stream of the run is touched)."""
    run_id = stored_wandb_id(run)
    if run_id is not None:
        return run_id
    path = Path(run.path) / ID_FILE
    run_id = "".join(secrets.choice(_ID_ALPHABET) for _ in range(12))
    _atomic_write(path, lambda file: file.write((run_id + "\n").encode("utf-8")))
    return run_id


class WandbSink:
    """One W&B run that receives a :class:`~dvfb.runs.metrics.MetricsLogger`'s scalars (module
    docstring). ``config``: the run config as a dict, logged once; ``name``: the W&B run's name
    (default: the run directory's); ``job_type``: ``pretrain`` or ``finetune``."""

    def __init__(self, run: RunDir, log: LogConfig, config: Mapping[str, Any] | None = None, name: str | None = None,
                 job_type: str | None = None) -> None:
        # lazy: wandb is optional and slow to import (~0.4 s); only a run that logs to it needs it
        import wandb

        require_wandb(log)
        self.run_id = wandb_run_id(run)
        try:
            self._run = self._init(wandb, run, log, config, name, job_type)
        except wandb.errors.Error as exc:
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ConfigError(f"cannot start the W&B run of {run.path}: {reason} (--log.wandb-mode offline logs "
                              "locally for a later `wandb sync`)") from exc
        # W&B's steps only increase: a resumed W&B run starts past the steps it holds.
        self._last = int(getattr(self._run, "step", 0) or 0)

    def _init(self, wandb, run, log, config, name, job_type):
        return wandb.init(
            project=log.wandb_project or None, entity=log.wandb_entity or None, group=log.wandb_group or None,
            tags=list(log.wandb_tags) or None, name=name or Path(run.path).name, id=self.run_id, resume="allow",
            dir=str(run.path), config=dict(config or {}), job_type=job_type, mode=resolve_mode(log.wandb_mode),
            reinit="create_new",  # a group (docs/members.md) has one W&B run per member, all open at once
            settings=wandb.Settings(console="off"))  # the run's terminal output stays the terminal's

    def log(self, step: int, prefix: str, values: Mapping[str, float]) -> None:
        """The scalars ``values`` of ``prefix`` at ``step``, as ``<prefix>/<name>`` (records of one step
        make one W&B row). A step below one W&B holds is dropped: after a resume, W&B keeps what the
        interrupted process logged past the checkpoint, which the exact resume logs again."""
        if step < self._last:
            return
        self._run.log({f"{prefix}/{name}": value for name, value in values.items()}, step=step)
        self._last = step

    def close(self) -> None:
        if self._run is None:
            return
        self._run.finish()
        self._run = None
