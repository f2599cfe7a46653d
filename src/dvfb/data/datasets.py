"""Datasets that dvfb makes from its own pre-training runs and relabels itself, in ExORL's layout
(docs/methods.md, "Datasets").

A dataset is a directory::

    DIR/dataset.json                         what it holds (:class:`DatasetInfo`)
    DIR/buffer/episode_<index>_<T>.npz       one finished episode of T steps (index: 6 digits)

Each episode file holds ExORL's keys, row ``i`` for observation ``i`` (``T + 1`` rows):

    observation  (T+1, obs_dim)     float32  obs_i
    action       (T+1, action_dim)  float32  the action that led to obs_i; row 0 zero (a dummy)
    reward       (T+1, 1)           float32  its reward; row 0 zero
    discount     (T+1, 1)           float32  its environment discount; row 0 one
    physics      (T+1, width)       float64  the physics state of obs_i: after the step whose
                                             reward is row i's; row 0 the reset state

The physics vector is the environment's ``physics_state()`` (dvfb.envs): MuJoCo's qpos, qvel, act,
(actuator history), ctrl and mocap poses, whichever the model has, then on Meta-World the task's
``rand_vec``; ``dataset.json`` gives its layout. Its first ``nq + nv + na`` values are dm_control's
``physics.get_state()``, ExORL's physics column.

* ``dvfb dataset export`` (:func:`dvfb.workflows.dataset_export.export_run`) writes a pre-training run's
  replay (its final resume checkpoint) as a dataset with :func:`write_dataset`; the run must have
  recorded physics (``--replay.record-physics true``). Only finished episodes are written; the
  episode in progress, if any, is left out.
* :func:`relabel` recomputes every step's reward for another task of the domain from the physics
  states, with the task's own reward function as its environment computes it (bit for bit the
  reward an online environment of that task returns for the step), into a new dataset.
* :func:`read_dataset` loads a dataset into a :class:`~dvfb.data.buffer.ReplayBuffer` for offline
  training. Any unreadable, truncated or inconsistent episode file is an error naming the file:
  a dataset is read whole or not at all.

**Identity.** ``dataset.json`` records the SHA-256 of every episode file as it was written
(``digests``), and :attr:`DatasetInfo.identity` digests those: two datasets with the same files
of the same contents have the same identity, a re-export with the same names and shapes but other
contents does not. Every read checks each file's bytes against its recorded digest (the bytes are
read anyway, so the check costs one hash), so a run that recorded the identity of its data can
refuse other data with one line naming the file (docs/methods.md, "Datasets"). Datasets written
before dvfb recorded digests have none; they are read as before, and the runs made from them are
compared by their file names.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import re
import shutil
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dvfb import envs
from dvfb.core.errors import ConfigError, DvfbError, RunDirError
from dvfb.core.files import read_json, write_json_atomic
from dvfb.core.version import __version__
from dvfb.data.buffer import PHYSICS_COLUMN, Column, ReplayBuffer, physics_columns

DATASET_FORMAT = 1
INFO_FILE = "dataset.json"
EPISODES_DIR = "buffer"
KEYS = {"observation": np.float32, "action": np.float32, "reward": np.float32, "discount": np.float32,
        PHYSICS_COLUMN: np.float64}
_EPISODE_NAME = re.compile(r"episode_(\d+)_(\d+)\.npz")


@dataclass
class DatasetInfo:
    """What ``dataset.json`` says about a dataset (module docstring)."""

    domain: str
    task: str  # the task whose rewards the files hold
    pretrain_task: str  # the environment the data was collected in
    source_run: str
    agent: str
    seed: int
    frames: int  # the pre-training step of the checkpoint that was exported
    obs_dim: int
    action_dim: int
    physics_width: int
    physics_layout: list[list]  # [part, size] in order (dvfb.envs: physics_layout)
    episode_length: int  # the domain's episode length: the most steps a file may hold
    episodes: int
    transitions: int
    files: list[str]  # the episode files in buffer/, oldest first
    relabelled_from: str | None = None
    # SHA-256 of each episode file's bytes, by name (module docstring, "Identity"); None: written
    # by a dvfb that did not record them.
    digests: dict[str, str] | None = None
    dvfb_version: str = __version__
    format: int = DATASET_FORMAT
    created: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))

    @property
    def lengths(self) -> list[int]:
        """Steps of each episode file (from its name)."""
        return [int(_EPISODE_NAME.fullmatch(name).group(2)) for name in self.files]

    @property
    def identity(self) -> str | None:
        """The digest of the dataset's contents: of its files' names and digests, in order (None
        when ``dataset.json`` records no digests)."""
        if self.digests is None:
            return None
        text = "\n".join(f"{name} {self.digests[name]}" for name in self.files)
        return hashlib.sha256(text.encode()).hexdigest()

    def fingerprint(self, path: str | Path) -> dict:
        """What a run records about the data it trained on, to refuse other data later
        (:func:`check_same_data`)."""
        return {"path": str(Path(path).resolve()), "episodes": self.episodes, "transitions": self.transitions,
                "files": list(self.files), "identity": self.identity, "digests": self.digests}


def check_same_data(recorded: dict, info: DatasetInfo, path: str | Path, what: str) -> None:
    """ConfigError (one line naming the first file that differs) unless ``info`` holds the data that
    ``recorded`` (a :meth:`DatasetInfo.fingerprint`) describes: the same files with the same
    digests, or, where either side has no digests (written before dvfb recorded them), the same
    file names."""
    now = info.fingerprint(path)
    if recorded.get("identity") is not None and now["identity"] is not None:
        if recorded["identity"] == now["identity"]:
            return
        old, new = recorded.get("digests") or {}, now["digests"]
        changed = [n for n in now["files"] if old.get(n) != new.get(n)] + [n for n in old if n not in new]
        first = changed[0] if changed else INFO_FILE
        raise ConfigError(f"{what} was made from other data than {path} holds now: {Path(path) / EPISODES_DIR / first} "
                          f"differs from the file it was made from ({len(changed)} of {len(now['files'])} files differ)")
    if recorded.get("identity") is not None and now["identity"] is None:
        raise ConfigError(f"{what} was made from a dataset whose files had recorded digests, but {Path(path) / INFO_FILE} "
                          "records none: it is not the data the run was made from")
    if recorded.get("files") != now["files"]:
        raise ConfigError(f"{what} was made from other data than {path} holds now (its episode files differ)")


def episode_file_name(index: int, steps: int) -> str:
    """ExORL's name of an episode file: ``episode_<index>_<steps>.npz``."""
    return f"episode_{index:06d}_{steps}.npz"


def read_info(path: str | Path) -> DatasetInfo:
    """The metadata of the dataset in ``path``; ConfigError (one line) when it is not one."""
    path = Path(path)
    info_path = path / INFO_FILE
    if not path.is_dir():
        raise ConfigError(f"dataset {path} does not exist or is not a directory")
    if not info_path.is_file():
        raise ConfigError(f"{path} is not a dvfb dataset: it has no {INFO_FILE} (an interrupted export leaves none)")
    data = read_json(info_path, ConfigError)
    names = {f.name for f in dataclasses.fields(DatasetInfo)}
    if not isinstance(data, dict) or data.get("format") != DATASET_FORMAT or not set(data) <= names:
        raise ConfigError(f"{info_path} is not a dvfb dataset description of format {DATASET_FORMAT}")
    try:
        info = DatasetInfo(**data)
    except TypeError as exc:
        raise ConfigError(f"{info_path} is incomplete: {exc}") from exc
    counts = ("seed", "frames", "obs_dim", "action_dim", "physics_width", "episode_length", "episodes", "transitions")
    wrong = [name for name in counts if isinstance(data[name], bool) or not isinstance(data[name], int)]
    wrong += [name for name in ("files", "physics_layout") if not isinstance(data[name], list)]
    if wrong:
        raise ConfigError(f"{info_path} is corrupt: {', '.join(wrong)} of the wrong type")
    bad = [name for name in info.files if not isinstance(name, str) or not _EPISODE_NAME.fullmatch(name)]
    if bad or len(info.files) != info.episodes or sum(info.lengths) != info.transitions:
        raise ConfigError(f"{info_path} is inconsistent: {info.episodes} episodes and {info.transitions} transitions, "
                          f"but it lists {len(info.files)} files of {sum(info.lengths) if not bad else '?'} steps")
    for name, steps in zip(info.files, info.lengths):
        if not 0 < steps <= info.episode_length:
            raise ConfigError(f"episode file {path / EPISODES_DIR / name} holds {steps} steps; an episode of "
                              f"{info.domain} has 1 to {info.episode_length} (listed in {info_path})")
    if info.digests is not None and (not isinstance(info.digests, dict) or set(info.digests) != set(info.files)
                                     or not all(isinstance(d, str) for d in info.digests.values())):
        raise ConfigError(f"{info_path} is corrupt: its digests do not name exactly the files it lists")
    return info


# ------------------------------------------------------------------------------------------------
# episode files


def check_files(path: Path, info: DatasetInfo) -> None:
    """ConfigError naming the file when one that ``dataset.json`` lists is missing from
    ``buffer/``, or ``buffer/`` holds one it does not list (none is ever skipped silently)."""
    for name in info.files:
        if not (path / EPISODES_DIR / name).is_file():
            raise ConfigError(f"episode file {path / EPISODES_DIR / name} is missing (listed in {INFO_FILE})")
    unlisted = sorted({p.name for p in (path / EPISODES_DIR).glob("*.npz")} - set(info.files))
    if unlisted:
        raise ConfigError(f"{path / EPISODES_DIR} holds episode files that {INFO_FILE} does not list: "
                          f"{', '.join(unlisted[:3])}{' ...' if len(unlisted) > 3 else ''}")


def _problem(exc: BaseException) -> str:
    text = str(exc).splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def load_episode(path: Path, info: DatasetInfo) -> dict[str, np.ndarray]:
    """The arrays of one episode file, every key checked against ``info`` (present, dtype, shape,
    the step count of the file's name, finite values) and its bytes against the digest
    ``dataset.json`` recorded; ConfigError naming the file otherwise."""
    steps = int(_EPISODE_NAME.fullmatch(path.name).group(2))
    widths = {"observation": info.obs_dim, "action": info.action_dim, "reward": 1, "discount": 1,
              PHYSICS_COLUMN: info.physics_width}
    if not path.is_file():
        raise ConfigError(f"episode file {path} is missing (listed in {INFO_FILE})")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"episode file {path} cannot be read ({_problem(exc)})") from exc
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as file:
            missing = sorted(set(KEYS) - set(file.files))
            if missing:
                raise ConfigError(f"episode file {path} lacks the key(s) {', '.join(missing)}")
            arrays = {key: file[key] for key in KEYS}
    except DvfbError:
        raise
    except Exception as exc:  # noqa: BLE001  whatever a damaged zip or .npy header makes numpy raise
        # (BadZipFile, zlib.error, EOFError, OSError, ValueError, even SyntaxError from a mangled header)
        raise ConfigError(f"episode file {path} is truncated or corrupt ({_problem(exc)})") from exc
    for key, array in arrays.items():
        if array.dtype != KEYS[key] or array.shape != (steps + 1, widths[key]):
            raise ConfigError(f"episode file {path}: {key} is {array.dtype} of shape {array.shape}, expected "
                              f"{np.dtype(KEYS[key])} of shape ({steps + 1}, {widths[key]}) for its {steps} steps")
        if not np.isfinite(array).all():
            raise ConfigError(f"episode file {path}: {key} holds non-finite values")
    # Last, so that a damaged file is named for its damage; a well-formed file of other contents
    # (a re-export under the same names) is named here.
    if info.digests is not None and hashlib.sha256(data).hexdigest() != info.digests[path.name]:
        raise ConfigError(f"episode file {path} is not the file {INFO_FILE} recorded: its contents changed")
    return arrays


def check_output_dir(out: Path) -> None:
    """ConfigError unless ``out`` is absent or an empty directory (what a dataset is written to)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"output directory {out} exists and is not an empty directory; give another --out "
                          "(nothing was written)")


# What the readers and writers report progress to: ``progress(total, what)`` makes an object with
# ``update(n)`` and ``close()`` (a progress bar of the layers above); None reports nothing.
ProgressFactory = Callable[[int, str], Any]


class _Silent:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _bar(progress: ProgressFactory | None, total: int, what: str):
    return _Silent() if progress is None else progress(total, what)


def write_dataset(out: str | Path, info: DatasetInfo, episodes: Iterable[tuple[int, dict[str, np.ndarray]]],
                  progress: ProgressFactory | None = None, desc: str = "dataset") -> DatasetInfo:
    """Write ``episodes``, (index, arrays of the module docstring's keys) pairs, one file each,
    then ``dataset.json``: ``info`` with the files, episodes and transitions written. ``out`` must
    be absent or empty; if writing fails, what was written is removed again. Memory: one episode
    at a time (``episodes`` may be a generator)."""
    out = Path(out)
    check_output_dir(out)
    # The topmost folder this call creates (a nested --out creates its parents too): what a failure
    # removes again, so that nothing is left behind.
    created = out if not out.exists() else None
    while created is not None and not created.parent.exists():
        created = created.parent
    bar = _bar(progress, info.transitions, desc)
    files, digests, transitions = [], {}, 0
    try:
        (out / EPISODES_DIR).mkdir(parents=True)
        for index, arrays in episodes:
            steps = len(arrays["reward"]) - 1
            name = episode_file_name(index, steps)
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            data = buffer.getvalue()
            with open(out / EPISODES_DIR / name, "wb") as file:
                file.write(data)
            files.append(name)
            digests[name] = hashlib.sha256(data).hexdigest()
            transitions += steps
            bar.update(steps)
        info = dataclasses.replace(info, files=files, episodes=len(files), transitions=transitions, digests=digests)
        write_json_atomic(out / INFO_FILE, dataclasses.asdict(info))
    except BaseException as exc:
        shutil.rmtree(created or out / EPISODES_DIR, ignore_errors=True)
        if created is None:
            (out / INFO_FILE).unlink(missing_ok=True)
        if isinstance(exc, OSError):  # a read-only or full disk, a permission: one line naming the path
            where = exc.filename or out
            raise RunDirError(f"cannot write the dataset in {out} ({where}): {exc.strerror or exc}; "
                              "nothing was left behind") from exc
        raise
    finally:
        bar.close()
    return info


# ------------------------------------------------------------------------------------------------
# export


def physics_slice(columns: dict) -> slice | None:
    """Where the physics column lies in a replay state's float64 rows (the float64 columns side by
    side, in declaration order); None when the replay has no physics column of a dataset."""
    start = 0
    for name, spec in columns.items():
        column = Column.of(name, spec)
        if name == PHYSICS_COLUMN:
            ok = column == physics_columns(column.width)[PHYSICS_COLUMN]
            return slice(start, start + column.width) if ok else None
        if column.dtype == "float64":
            start += column.width
    return None


# ------------------------------------------------------------------------------------------------
# relabelling


def default_relabel_dir(dataset: Path, task: str) -> Path:
    """Where ``relabel`` writes by default: beside the dataset, ``<dataset>_<task>``."""
    return dataset.parent / f"{dataset.name}_{task}"


def relabel(dataset: str | Path, task: str, out: str | Path | None = None,
            progress: ProgressFactory | None = None) -> DatasetInfo:
    """Recompute every step's reward of ``dataset`` for ``task`` (a task of its domain) from the
    physics states, and write the relabelled dataset to ``out`` (default: ``<dataset>_<task>``
    beside it; never the source itself). The reward of each step is what ``task``'s environment
    returns for it (``rewards_from_physics`` of dvfb.envs), one episode at a time."""
    dataset = Path(dataset)
    info = read_info(dataset)
    spec = envs.resolve_task(task)
    if spec.domain != info.domain:
        raise ConfigError(f"task {task} is not a task of the dataset's domain {info.domain} "
                          f"(its tasks: {', '.join(envs.tasks_of_domain(info.domain))})")
    out = Path(out) if out is not None else default_relabel_dir(dataset, task)
    if out.resolve() == dataset.resolve() or dataset.resolve() in out.resolve().parents:
        raise ConfigError(f"--out {out} is the dataset {dataset} or inside it; relabelled files go to a new directory")
    check_output_dir(out)
    env = envs.make(task, seed=0).unwrapped
    if [list(part) for part in env.physics_layout] != [list(part) for part in info.physics_layout]:
        raise ConfigError(f"{dataset}: its physics layout {info.physics_layout} is not {task}'s "
                          f"{env.physics_layout} (made by another version?)")
    check_files(dataset, info)

    def episodes():
        for name in info.files:
            arrays = load_episode(dataset / EPISODES_DIR / name, info)
            reward = np.zeros_like(arrays["reward"])
            reward[1:, 0] = env.rewards_from_physics(arrays[PHYSICS_COLUMN][1:])
            yield int(_EPISODE_NAME.fullmatch(name).group(1)), {**arrays, "reward": reward}

    relabelled = dataclasses.replace(info, task=task, relabelled_from=str(dataset.resolve()), dvfb_version=__version__,
                                     created=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    return write_dataset(out, relabelled, episodes(), progress, f"relabel {task}")


# ------------------------------------------------------------------------------------------------
# loading


def read_dataset(path: str | Path, device: str | torch.device = "cpu", z_dim: int = 0,
                 columns: tuple[str, ...] = (), progress: ProgressFactory | None = None
                 ) -> tuple[ReplayBuffer, DatasetInfo]:
    """Every episode of the dataset in ``path`` in a :class:`~dvfb.data.buffer.ReplayBuffer` (oldest
    first), and its metadata.

    The buffer holds exactly the dataset's transitions (capacity: their number; more only where
    short episodes need more episode slots), its rewards those of the files (``info.task``'s).
    ``z_dim > 0`` adds a skill column of zeros for an offline learner to fill; ``columns`` may
    name ``"physics"`` to load the physics states too (a float64 column with each observation:
    batches carry ``physics`` and ``next_physics``). Every file is checked; a missing, truncated,
    corrupt or inconsistent one, or one in ``buffer/`` that ``dataset.json`` does not list, is a
    ConfigError naming it, and nothing is returned.
    """
    path = Path(path)
    info = read_info(path)
    unknown = sorted(set(columns) - {PHYSICS_COLUMN})
    if unknown:
        raise ConfigError(f"read_dataset columns may only be {PHYSICS_COLUMN!r}; got {', '.join(unknown)}")
    check_files(path, info)
    lengths = info.lengths
    if not lengths:
        raise ConfigError(f"dataset {path} holds no episode")
    longest = max(lengths)
    # Slots are capacity // longest + 1: enough for every episode, also when some are shorter.
    capacity = max(info.transitions, (len(lengths) - 1) * longest)
    buffer = ReplayBuffer(capacity, info.obs_dim, info.action_dim, z_dim, max_episode_length=longest, device=device,
                          columns=physics_columns(info.physics_width) if columns else None)
    bar = _bar(progress, info.transitions, "read dataset")
    try:
        for name, steps in zip(info.files, lengths):
            arrays = load_episode(path / EPISODES_DIR / name, info)  # all of it checked, physics too
            extra = {PHYSICS_COLUMN: arrays[PHYSICS_COLUMN]} if columns else {}
            buffer.add_episode(arrays["observation"], arrays["action"][1:], arrays["reward"][1:, 0],
                               arrays["discount"][1:, 0], np.zeros((steps, z_dim), np.float32) if z_dim else None,
                               **extra)
            bar.update(steps)
    finally:
        bar.close()
    return buffer, info


def describe(info: DatasetInfo, path: Path) -> str:
    """One line about a dataset (what the CLI prints)."""
    episodes = f"{info.episodes} episode{'' if info.episodes == 1 else 's'}"
    return (f"{path}: {episodes}, {info.transitions} transitions of {info.domain} "
            f"(rewards of {info.task}; physics {info.physics_width} values a row)")


__all__ = ["DATASET_FORMAT", "DatasetInfo", "check_same_data", "describe", "load_episode", "physics_slice", "read_dataset", "read_info",
           "relabel", "write_dataset"]
