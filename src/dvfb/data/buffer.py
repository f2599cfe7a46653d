"""In-memory episodic replay buffer (docs/methods.md §6; invariant 30 of section 13).

What is stored
    Every environment step of every stored episode: the observation, the action taken in it, the
    reward and environment discount returned with the next observation, the rollout skill z (as
    wide as the agent's declared skill: ``z_dim`` 0 for agents without one), and any further
    per-step columns declared by what needs them (``columns={"name": width}``, or a :class:`Column`
    with a dtype and a row). Everything is float32 except float64 columns (the physics states that
    datasets record, ``Column(width, "float64", "obs")``, :mod:`dvfb.data.datasets`), which live in a side array.

Layout
    One preallocated array ``data[num_slots, max_episode_length + 1, width]``: an episode per slot,
    a row per time step, and the fields side by side in a row::

        width = obs_dim | action_dim | 1 (reward) | 1 (env discount) | z_dim | declared columns

    Row ``t`` of an episode holds ``obs_t`` and the action, reward, discount and z of step ``t``
    (reward and discount are the ones the environment returned together with ``obs_{t+1}``).
    Row ``T`` of an episode of ``T`` steps holds only the final observation; its other fields are
    unused. So transition ``t`` is ``(obs_t, action_t, reward_t, discount_t, obs_{t+1}, obs_{t+2},
    z_t)`` and is read from rows ``t``, ``t+1`` and ``t+2`` of one slot: it can never cross an
    episode boundary. The spec's "dummy zero action at the reset step" is the same information
    shifted by one row.

    A declared column goes with the step (``row="step"``, the default: row ``t`` holds what
    :meth:`ReplayBuffer.add` got with step ``t``) or with the observation (``row="obs"``: row ``t``
    holds what came with ``obs_t``, from :meth:`ReplayBuffer.start_episode` for the reset
    observation and from ``add`` with ``next_obs``; row ``T`` is filled too). Float64 columns are
    stored in a second array ``data64[num_slots, max_episode_length + 1, width64]`` with the same
    slots and rows, allocated only when one is declared, so that buffers without one cost and run
    exactly as before.

Eviction
    Slots form a ring, oldest episode first. Capacity is counted in transitions: whenever a step
    would make the buffer hold more than ``capacity`` transitions, whole episodes are dropped,
    oldest first (the FIFO-by-episode rule of section 6). There are ``capacity //
    max_episode_length + 1`` slots, enough to hold ``capacity`` transitions of full-length
    episodes (DMC episodes always are) plus the episode in progress. With shorter episodes the
    slots run out first and the oldest episode is dropped to free one, so the buffer then holds
    fewer than ``capacity`` transitions.

Sampling
    Uniform over all stored transitions, the episode in progress included (section 6 allows it):
    a single ``randint`` over the total count, mapped to (episode, step) with ``searchsorted`` on
    the cumulative per-episode counts. This is exactly uniform even when episode lengths differ
    ([C] samples episode-then-step, which is the same for fixed-length episodes). With
    ``need_future=True`` only transitions whose ``obs_{t+2}`` is in the same episode are eligible,
    so an episode of ``T`` steps contributes ``T - 1`` (the FB sampler of [C] does the same).
    Episodes are indexed in ring order (oldest first), so a sample depends only on the stored
    content and the generator, not on which slot an episode happens to occupy: a buffer restored
    from :meth:`ReplayBuffer.state_dict` draws identical batches.

Loader shards
    A buffer built with a :class:`LoaderShards` sampler draws batches as the authors' code (and
    URLB, whose replay it inherits) receives them from its DataLoader: only finished episodes are
    sampled; episode ``g`` (counted from the first episode of the run) belongs to shard ``g mod W``;
    batch ``k`` comes from shard ``k mod W`` alone, episode-uniform among the episodes that shard
    holds, then step-uniform within the episode; and a shard looks for newly finished episodes
    only every ``refresh`` of its own samples. So a batch holds about a ``1/W`` share of the
    episodes (right after the uniform seed phase of 4 episodes: one), and data reaches the
    sampler only once its episode ends. docs/methods.md, "Replay sampling", says why this matters.

Devices
    On CPU the array is a numpy array and the sampler reads it through a zero-copy
    ``torch.from_numpy`` view, so a step costs a few small numpy writes. On an accelerator the
    array is a device tensor; steps of the episode in progress are written into a host staging
    copy of one episode and the rows not yet on the device are copied over in one transfer before
    each sample (never per step).

Memory
    ``estimate_nbytes(2_000_000, 24, 6, 50)`` (2M Walker transitions: obs 24, action 6, z 50,
    float32, episodes of 1000 steps) = 657,000,336 bytes (626.6 MiB): 2,001 slots x 1,001 rows x
    82 floats, plus 16,008 bytes of episode lengths. Declared columns add their widths to the 82
    (float32) or to the side array's row (float64, 8 bytes a value): ``estimate_nbytes(...,
    columns=...)``. The host staging copy used on an accelerator (one episode, 328 kB here) is not
    counted.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.data.batch import Batch
from dvfb.data.samplers import LoaderShards

_STATE_FORMAT = 1
_BYTES_PER_FLOAT = 4
_BYTES_PER_LENGTH = 8
_DTYPES = {"float32": (np.float32, torch.float32), "float64": (np.float64, torch.float64)}
COLUMN_ROWS = ("step", "obs")
_RESERVED_COLUMNS = ("skill", "obs", "action", "reward", "discount")


@dataclass(frozen=True)
class Column:
    """A declared per-step column of a :class:`ReplayBuffer` (module docstring, "Layout").

    ``width`` values a row; ``dtype`` "float32" (in the main array) or "float64" (in the side
    array); ``row`` "step" (written by ``add`` into the step's row) or "obs" (written with the
    observation it goes with: by ``start_episode`` and by ``add`` with ``next_obs``).
    """

    width: int
    dtype: str = "float32"
    row: str = "step"

    @classmethod
    def of(cls, name: str, spec) -> Column:
        """A column from what a caller (an int width, a Column) or a saved state (a dict) gives."""
        if isinstance(spec, dict):
            spec = cls(**spec) if "width" in spec and set(spec) <= {"width", "dtype", "row"} else None
        elif isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
            spec = cls(int(spec))
        if (not isinstance(spec, cls) or isinstance(spec.width, bool) or not isinstance(spec.width, (int, np.integer))
                or spec.width < 1 or spec.dtype not in _DTYPES or spec.row not in COLUMN_ROWS
                or name in _RESERVED_COLUMNS or name.startswith("next_")):
            raise ConfigError(f"replay column {name!r} declared as {spec!r}: names must be new (and not next_*), "
                              f"widths integers >= 1, dtypes one of {', '.join(_DTYPES)}, rows one of "
                              f"{', '.join(COLUMN_ROWS)}")
        return cls(int(spec.width), spec.dtype, spec.row)

    def saved(self) -> int | dict:
        """How a state records it: a plain float32 step column as its width (as states always did)."""
        return self.width if (self.dtype, self.row) == ("float32", "step") else dataclasses.asdict(self)


PHYSICS_COLUMN = "physics"


def physics_columns(width: int) -> dict[str, Column]:
    """The declared column of a replay that records physics states (``--replay.record-physics``):
    ``physics``, float64, with each observation (docs/methods.md, "Datasets")."""
    return {PHYSICS_COLUMN: Column(width, "float64", "obs")}


def _num_slots(capacity: int, max_episode_length: int) -> int:
    # capacity // L full episodes can be stored whole, plus one slot for the episode in progress.
    return capacity // max_episode_length + 1


class ReplayBuffer:
    """Preallocated FIFO replay buffer of whole episodes, sampled uniformly per transition (or by a
    :class:`LoaderShards` sampler).

    See the module docstring for the layout, eviction and sampling rules (docs/methods.md §6).

    Args:
        capacity: maximum number of stored transitions; at least ``max_episode_length``.
        obs_dim, action_dim, z_dim: sizes of one observation, action and task vector.
        max_episode_length: most steps one episode may have (1000 in DMC).
        device: where the storage lives and batches are returned.
        stage_on_host: write steps into a host staging episode and copy them to the storage before
            sampling. Default: only when ``device`` is not the CPU. Forcing it on CPU exercises the
            accelerator code path in tests.
        columns: declared per-step columns, by name: a width (float32, with the step) or a
            :class:`Column` (or the dict a state records for one).
        sampler: how :meth:`sample` draws; None is uniform over the stored transitions.
    """

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, z_dim: int = 0,
                 max_episode_length: int = 1000, device: str | torch.device = "cpu",
                 stage_on_host: bool | None = None, columns: dict[str, int | Column | dict] | None = None,
                 sampler: LoaderShards | None = None) -> None:
        for name, value, minimum in (("capacity", capacity, 1), ("obs_dim", obs_dim, 1),
                                     ("action_dim", action_dim, 1), ("z_dim", z_dim, 0),
                                     ("max_episode_length", max_episode_length, 1)):
            integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
            if not integer or value < minimum:
                raise ConfigError(
                    f"replay buffer {name} must be an integer >= {minimum}, got {value!r}")
        if capacity < max_episode_length:
            raise ConfigError(
                f"replay capacity ({capacity}) must be at least max_episode_length "
                f"({max_episode_length}), so that the episode in progress always fits"
            )
        self.capacity = int(capacity)
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.z_dim = int(z_dim)
        self.max_episode_length = int(max_episode_length)
        self.num_slots = _num_slots(self.capacity, self.max_episode_length)
        self.device = torch.device(device)
        self._staged = self.device.type != "cpu" if stage_on_host is None else bool(stage_on_host)
        if not self._staged and self.device.type != "cpu":
            raise ConfigError(f"a replay buffer on {self.device} needs stage_on_host")

        # Declared per-step columns after the skill (what needs them declares them: e.g. physics
        # states for datasets), float32 ones in the main row, float64 ones in the side row.
        self.column_specs = {name: Column.of(name, spec) for name, spec in (columns or {}).items()}
        self.columns = {name: c.width for name, c in self.column_specs.items()}
        self._obs_columns = {name for name, c in self.column_specs.items() if c.row == "obs"}

        # Column layout of one row.
        self._action_col = self.obs_dim
        self._reward_col = self._action_col + self.action_dim
        self._discount_col = self._reward_col + 1
        self._z_col = self._discount_col + 1
        self._column_slices: dict[str, slice] = {}
        starts = {"float32": self._z_col + self.z_dim, "float64": 0}
        for name, c in self.column_specs.items():
            self._column_slices[name] = slice(starts[c.dtype], starts[c.dtype] + c.width)
            starts[c.dtype] += c.width
        self.width, self.width64 = starts["float32"], starts["float64"]

        self._host, self._store = self._allocate(self.width, "float32")
        self._host64, self._store64 = self._allocate(self.width64, "float64") if self.width64 else (None, None)
        host = self._host
        # Field views of the array that `add` writes into (storage on CPU, staging otherwise).
        self._w_obs = host[:, :, : self.obs_dim]
        self._w_action = host[:, :, self._action_col: self._reward_col]
        self._w_reward = host[:, :, self._reward_col]
        self._w_discount = host[:, :, self._discount_col]
        self._w_z = host[:, :, self._z_col: self._z_col + self.z_dim]
        hosts = {"float32": self._host, "float64": self._host64}
        self._w_columns = {name: hosts[self.column_specs[name].dtype][:, :, cols]
                           for name, cols in self._column_slices.items()}
        # Row offset of a column's value from the step's row: 1 for those that go with next_obs.
        self._column_offsets = {name: int(c.row == "obs") for name, c in self.column_specs.items()}
        # Field views of the storage that sampling reads (torch, on `device`).
        self._s_obs = self._store[:, :, : self.obs_dim]
        self._s_action = self._store[:, :, self._action_col: self._reward_col]
        self._s_reward = self._store[:, :, self._reward_col: self._reward_col + 1]
        self._s_discount = self._store[:, :, self._discount_col: self._discount_col + 1]
        self._s_z = self._store[:, :, self._z_col: self._z_col + self.z_dim]
        stores = {"float32": self._store, "float64": self._store64}
        self._s_columns = {name: stores[self.column_specs[name].dtype][:, :, cols]
                           for name, cols in self._column_slices.items()}

        self._lengths = np.zeros(self.num_slots, dtype=np.int64)  # transitions per slot
        self.sampler = sampler
        self._reset_bookkeeping()

    def _allocate(self, width: int, dtype: str) -> tuple[np.ndarray, torch.Tensor]:
        """(host array that ``add`` writes, storage that sampling reads) of one dtype's rows."""
        np_dtype, torch_dtype = _DTYPES[dtype]
        rows = self.max_episode_length + 1
        shape = (self.num_slots, rows, width)
        if self._staged:
            return np.zeros((1, rows, width), dtype=np_dtype), torch.zeros(shape, dtype=torch_dtype, device=self.device)
        host = np.zeros(shape, dtype=np_dtype)
        return host, torch.from_numpy(host)

    def _reset_bookkeeping(self) -> None:
        self._lengths[:] = 0
        self._first = 0            # slot of the oldest stored episode
        self._num_episodes = 0     # slots in use, the episode in progress included
        self._num_transitions = 0
        self._episodes_begun = 0   # episodes ever started, evicted ones included (loader shards)
        self._open = False         # whether `add` may extend the newest episode
        self._cur_slot = 0
        self._cur_len = 0
        self._write_slot = 0       # index into the host array: the slot on CPU, 0 when staged
        self._flushed_rows = 0     # staged rows [0, _flushed_rows) are complete on the device

    # ------------------------------------------------------------------------------------------
    # sizes

    @staticmethod
    def estimate_nbytes(capacity: int, obs_dim: int, action_dim: int, z_dim: int,
                        max_episode_length: int = 1000, columns: dict[str, int | Column | dict] | None = None) -> int:
        """Bytes of preallocated storage for these sizes and declared columns (the value
        :attr:`nbytes` will have)."""
        slots = _num_slots(capacity, max_episode_length)
        specs = [Column.of(name, spec) for name, spec in (columns or {}).items()]
        row_bytes = (obs_dim + action_dim + 2 + z_dim) * _BYTES_PER_FLOAT + sum(
            c.width * np.dtype(_DTYPES[c.dtype][0]).itemsize for c in specs)
        return slots * (max_episode_length + 1) * row_bytes + slots * _BYTES_PER_LENGTH

    @property
    def nbytes(self) -> int:
        """Bytes of all preallocated storage (host staging on an accelerator excluded)."""
        side = 0 if self._store64 is None else self._store64.numel() * self._store64.element_size()
        return self._store.numel() * self._store.element_size() + side + self._lengths.nbytes

    @property
    def num_episodes(self) -> int:
        """Stored episodes, the one in progress included."""
        return self._num_episodes

    def __len__(self) -> int:
        """Stored transitions."""
        return self._num_transitions

    # ------------------------------------------------------------------------------------------
    # writing

    def start_episode(self, obs: np.ndarray, **columns) -> None:
        """Begin a new episode with its reset observation; ``columns`` are the declared columns that
        go with the observation (``row="obs"``, each required)."""
        if columns.keys() != self._obs_columns:
            raise ValueError(f"this replay buffer stores the columns {sorted(self._obs_columns)} with each "
                             f"observation; got {sorted(columns)}")
        if not (self._open and self._cur_len == 0):
            # (An episode without steps is simply restarted in its slot.)
            self._flush()
            if self._num_episodes == self.num_slots:
                self._evict_oldest()
            self._cur_slot = (self._first + self._num_episodes) % self.num_slots
            self._num_episodes += 1
            self._episodes_begun += 1
            self._cur_len = 0
            self._lengths[self._cur_slot] = 0
            self._write_slot = 0 if self._staged else self._cur_slot
            self._open = True
        self._flushed_rows = 0
        self._w_obs[self._write_slot, 0] = obs
        for name, value in columns.items():
            self._w_columns[name][self._write_slot, 0] = value

    def add(self, action, reward: float, discount: float, next_obs, z=None, **columns) -> None:
        """Record one environment step of the current episode.

        ``action`` was taken in the latest observation; ``reward`` and ``discount`` are what the
        environment returned together with ``next_obs``; ``z`` is the skill the action was chosen
        for (required when ``z_dim > 0``); ``columns`` the declared columns (each required): of the
        step's row, or, for those that go with the observation, ``next_obs``'s.
        """
        t = self._cur_len
        if t >= self.max_episode_length or not self._open:
            self._raise_cannot_add()
        w = self._write_slot
        self._w_action[w, t] = action
        self._w_reward[w, t] = reward
        self._w_discount[w, t] = discount
        self._w_obs[w, t + 1] = next_obs
        if self.z_dim:
            if z is None:
                raise ValueError(f"this replay buffer stores z (z_dim={self.z_dim}); pass z=")
            self._w_z[w, t] = z
        if self.columns:
            if columns.keys() != self.columns.keys():
                raise ValueError(f"this replay buffer stores the columns {sorted(self.columns)}; got {sorted(columns)}")
            for name, value in columns.items():
                self._w_columns[name][w, t + self._column_offsets[name]] = value
        self._cur_len = t + 1
        self._lengths[self._cur_slot] = t + 1
        self._num_transitions += 1
        while self._num_transitions > self.capacity:
            self._evict_oldest()

    def add_episode(self, obs, action, reward, discount, z=None, **columns) -> None:
        """Record a whole finished episode of ``T`` steps at once (a dataset's): ``obs`` (T+1, obs_dim),
        ``action`` (T, action_dim), ``reward`` and ``discount`` (T,), ``z`` (T, z_dim) when
        ``z_dim > 0``, and every declared column: (T, width) with the step, (T+1, width) with the
        observation. The same as ``start_episode`` then ``T`` calls of ``add``, without the loop; the
        episode is closed (finished) afterwards."""
        obs, action = np.asarray(obs), np.asarray(action)
        steps = action.shape[0] if action.ndim == 2 else -1
        if not 1 <= steps <= self.max_episode_length or obs.shape != (steps + 1, self.obs_dim):
            raise ValueError(f"an episode of {steps} steps needs obs ({steps} + 1, {self.obs_dim}) and at most "
                             f"max_episode_length={self.max_episode_length} steps; got obs {obs.shape}, "
                             f"action {action.shape}")
        if columns.keys() != self.columns.keys():
            raise ValueError(f"this replay buffer stores the columns {sorted(self.columns)}; got {sorted(columns)}")
        if self.z_dim and z is None:
            raise ValueError(f"this replay buffer stores z (z_dim={self.z_dim}); pass z=")
        self.start_episode(obs[0], **{name: columns[name][0] for name in self._obs_columns})
        w = self._write_slot
        self._w_obs[w, : steps + 1] = obs
        self._w_action[w, :steps] = action
        self._w_reward[w, :steps] = np.reshape(reward, steps)
        self._w_discount[w, :steps] = np.reshape(discount, steps)
        if self.z_dim:
            self._w_z[w, :steps] = z
        for name, value in columns.items():
            self._w_columns[name][w, : steps + self._column_offsets[name]] = value
        self._cur_len = steps
        self._lengths[self._cur_slot] = steps
        self._num_transitions += steps
        while self._num_transitions > self.capacity:
            self._evict_oldest()
        self._flush()
        self._open = False

    def _raise_cannot_add(self) -> None:
        if not self._open:
            raise RuntimeError("ReplayBuffer.add called before start_episode")
        raise ConfigError(
            f"episode already has max_episode_length={self.max_episode_length} steps; the "
            "environment's episodes are longer than the replay buffer was sized for (raise "
            "max_episode_length) or start_episode was not called at the reset"
        )

    def _evict_oldest(self) -> None:
        slot = self._first
        if self._open and slot == self._cur_slot:
            # Unreachable while capacity >= max_episode_length and num_slots >= 2.
            raise AssertionError("replay buffer tried to evict the episode in progress")
        self._num_transitions -= int(self._lengths[slot])
        self._lengths[slot] = 0
        self._first = (slot + 1) % self.num_slots
        self._num_episodes -= 1

    def _flush(self) -> None:
        """Copy the staged rows of the episode in progress that the device lacks (one transfer)."""
        if not self._staged or not self._open:
            return
        # Row `_cur_len` holds only the newest observation so far; its action fields arrive with
        # the next step, so it is copied again by the next flush.
        begin, end = self._flushed_rows, self._cur_len + 1
        if begin < end:
            self._store[self._cur_slot, begin:end].copy_(torch.from_numpy(self._host[0, begin:end]))
            if self._store64 is not None:
                self._store64[self._cur_slot, begin:end].copy_(torch.from_numpy(self._host64[0, begin:end]))
            self._flushed_rows = self._cur_len

    # ------------------------------------------------------------------------------------------
    # reading

    def _ring_slots(self) -> np.ndarray:
        return (self._first + np.arange(self._num_episodes)) % self.num_slots

    def sample(self, batch_size: int, gamma: float = 0.99, need_future: bool = False,
               generator: torch.Generator | None = None, nstep: int = 1) -> Batch:
        """Draw ``batch_size`` transitions uniformly with replacement (docs/methods.md §6).

        With ``need_future`` only transitions whose ``obs_{t+2}`` exists in the same episode are
        eligible and the batch has ``future_obs``. With ``nstep = n > 1`` only transitions whose
        ``obs_{t+n}`` exists in the same episode are eligible, and a row is
        ``(s_t, a_t, sum_i gamma^i prod_{j<i} d_{t+j} r_{t+i}, gamma^n prod_j d_{t+j}, s_{t+n})``
        (URLB's n-step tuple; docs/methods.md, "Replay"). ``generator`` makes the draw
        reproducible; the indices are drawn on its device.
        """
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if nstep < 1:
            raise ValueError(f"nstep must be >= 1, got {nstep}")
        slots = self._ring_slots()
        counts = self._lengths[slots]
        # Steps after t that must exist in the same episode: n for s_{t+n}, 2 for s_{t+2}.
        horizon = max(nstep, 2 if need_future else 1)
        if horizon > 1:
            counts = np.maximum(counts - (horizon - 1), 0)
        cumulative = np.cumsum(counts)
        total = int(cumulative[-1]) if len(cumulative) else 0
        if total == 0:
            what = f"with a {horizon}-step successor " if horizon > 1 else ""
            raise ValueError(f"cannot sample: the replay buffer holds no transition {what}yet")

        if self.sampler is not None:
            # The episode in progress, if any, is the newest in ring order.
            finished = self._num_episodes - (1 if self._open else 0)
            slot, step = self.sampler.draw(slots, counts, self._episodes_begun - self._num_episodes, finished,
                                           batch_size, generator)
        else:
            index_device = generator.device if generator is not None else torch.device("cpu")
            draws = torch.randint(total, (batch_size,), generator=generator, device=index_device)
            cumulative_t = torch.from_numpy(cumulative).to(index_device)
            episode = torch.searchsorted(cumulative_t, draws, right=True)
            step = draws - (cumulative_t[episode] - torch.from_numpy(counts).to(index_device)[episode])
            slot = torch.from_numpy(slots).to(index_device)[episode]
        self._flush()
        if nstep > 1:
            return self._gather_nstep(slot.to(self.device), step.to(self.device), gamma, need_future, nstep)
        return self._gather(slot.to(self.device), step.to(self.device), gamma, need_future)

    def transitions(self, gamma: float = 0.99, limit: int | None = None) -> Batch:
        """Every stored transition once, oldest episode first and in time order within an episode
        (``limit``: only the newest whole episodes that fit in ``limit`` transitions, at least the
        newest one; no random draw).

        Used for zero-shot task inference on reward-labelled data (docs/methods.md §8.1) and for
        the statistics a snapshot carries. ``future_obs`` is None.
        """
        slots = self._ring_slots()
        counts = self._lengths[slots].copy()
        if limit is not None and int(counts.sum()) > limit:
            kept = np.cumsum(counts[::-1])[::-1]
            first = int(np.nonzero(kept <= limit)[0][0]) if (kept <= limit).any() else len(slots) - 1
            slots, counts = slots[first:], counts[first:]
        total = int(counts.sum())
        starts = np.cumsum(counts) - counts
        slot = np.repeat(slots, counts)
        step = np.arange(total) - np.repeat(starts, counts)
        self._flush()
        return self._gather(torch.from_numpy(slot).to(self.device),
                            torch.from_numpy(step).to(self.device), gamma, need_future=False)

    def newest(self) -> tuple[tuple[int, int], torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The newest stored transition ``(key, obs, reward, next_obs)`` (tensors on the buffer's
        device, reward a scalar), or None while there is none; after a reset, the previous
        episode's last step. ``key`` = (the episode's ordinal since the buffer began, the step in
        it) names the transition for good, across evictions and resumes, so that a reader that
        takes each transition once (online task inference) can tell a new one from the last."""
        slots = self._ring_slots()
        lengths = self._lengths[slots]
        filled = np.flatnonzero(lengths)
        if filled.size == 0:
            return None
        k = int(filled[-1])
        slot, step = int(slots[k]), int(lengths[k]) - 1
        key = (int(self._episodes_begun) - int(self.num_episodes) + k, step)
        self._flush()  # an accelerator's staged rows onto the device
        return key, self._s_obs[slot, step], self._s_reward[slot, step, 0], self._s_obs[slot, step + 1]

    def episodes(self):
        """Every stored episode, oldest first (the one in progress too), as host arrays
        ``(obs (T+1, O), action (T, U), reward (T,), discount (T,))``: the environment's discounts,
        the episode boundaries as they were stored."""
        counts = self._lengths[self._ring_slots()]
        data = self.transitions(gamma=1.0)
        obs, next_obs = data.obs.cpu().numpy(), data.next_obs.cpu().numpy()
        action = data.action.cpu().numpy()
        reward, discount = data.reward.cpu().numpy()[:, 0], data.discount.cpu().numpy()[:, 0]
        start = 0
        for count in counts:
            end = start + int(count)
            if end > start:
                yield (np.concatenate([obs[start:end], next_obs[end - 1:end]]), action[start:end], reward[start:end],
                       discount[start:end])
            start = end

    def _gather(self, slot: torch.Tensor, step: torch.Tensor, gamma: float,
                need_future: bool) -> Batch:
        return Batch(
            obs=self._s_obs[slot, step],
            action=self._s_action[slot, step],
            reward=self._s_reward[slot, step],
            discount=self._s_discount[slot, step] * gamma,
            next_obs=self._s_obs[slot, step + 1],
            future_obs=self._s_obs[slot, step + 2] if need_future else None,
            z=self._s_z[slot, step] if self.z_dim else None,
            columns=self._gather_columns(slot, step, step + 1),
        )

    def _gather_columns(self, slot: torch.Tensor, step: torch.Tensor, next_step: torch.Tensor) -> dict:
        """The declared columns of rows ``step`` and, for those with the observation, ``next_<name>``
        of rows ``next_step`` (the batch's next_obs)."""
        out = {name: view[slot, step] for name, view in self._s_columns.items()}
        for name in self._obs_columns:
            out[f"next_{name}"] = self._s_columns[name][slot, next_step]
        return out

    def _gather_nstep(self, slot: torch.Tensor, step: torch.Tensor, gamma: float, need_future: bool,
                      nstep: int) -> Batch:
        rows = step.unsqueeze(1) + torch.arange(nstep, device=step.device)  # (N, n): steps t .. t+n-1
        slots = slot.unsqueeze(1)
        reward = self._s_reward[slots, rows]  # (N, n, 1)
        env_discount = self._s_discount[slots, rows]
        # Weight of r_{t+i}: gamma^i times the environment discounts of the steps before it.
        survive = torch.cumprod(env_discount, dim=1)
        powers = gamma ** torch.arange(nstep, device=step.device, dtype=reward.dtype).reshape(1, nstep, 1)
        weights = torch.cat([torch.ones_like(survive[:, :1]), survive[:, :-1]], dim=1) * powers
        return Batch(
            obs=self._s_obs[slot, step],
            action=self._s_action[slot, step],
            reward=(weights * reward).sum(1),
            discount=survive[:, -1] * gamma ** nstep,
            next_obs=self._s_obs[slot, step + nstep],
            future_obs=self._s_obs[slot, step + 2] if need_future else None,
            z=self._s_z[slot, step] if self.z_dim else None,
            columns=self._gather_columns(slot, step, step + nstep),
        )

    # ------------------------------------------------------------------------------------------
    # checkpointing

    def _shape_info(self) -> dict:
        info = {"capacity": self.capacity, "obs_dim": self.obs_dim,
                "action_dim": self.action_dim, "z_dim": self.z_dim,
                "max_episode_length": self.max_episode_length}
        if self.columns:  # only then: states of buffers without declared columns read as before
            info["columns"] = {name: c.saved() for name, c in self.column_specs.items()}
        return info

    def state_dict(self) -> dict:
        """The stored episodes, compactly (only filled rows), as CPU tensors and plain values.

        Loadable with ``torch.load(weights_only=True)``. Slot positions are not kept: episodes are
        saved in ring order, which is all that sampling depends on. ``rows`` holds the float32 rows,
        episode after episode (``lengths[i] + 1`` rows each); with float64 columns, ``rows_float64``
        their rows in the same order.
        """
        self._flush()
        slots = self._ring_slots()
        lengths = self._lengths[slots].copy()
        rows_per_episode = lengths + 1
        slot_index = torch.from_numpy(np.repeat(slots, rows_per_episode)).to(self.device)
        row_index = torch.from_numpy(np.arange(int(rows_per_episode.sum())) - np.repeat(
            np.cumsum(rows_per_episode) - rows_per_episode, rows_per_episode)).to(self.device)
        state = {"format": _STATE_FORMAT, **self._shape_info(),
                 "episode_open": self._open, "lengths": torch.from_numpy(lengths),
                 "rows": self._store[slot_index, row_index].cpu(), "episodes_begun": self._episodes_begun}
        if self._store64 is not None:
            state["rows_float64"] = self._store64[slot_index, row_index].cpu()
        if self.sampler is not None:
            state["sampler"] = self.sampler.state_dict()
        return state

    @classmethod
    def from_state(cls, state: dict, device: str | torch.device = "cpu") -> ReplayBuffer:
        """A buffer of the shape ``state`` (from :meth:`state_dict`) was saved with, holding its
        episodes: a saved replay read on its own (zero-shot from a run's replay, an export's samples)."""
        try:
            shape = [int(state[key]) for key in ("capacity", "obs_dim", "action_dim", "z_dim", "max_episode_length")]
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"replay state has no usable shape ({exc})") from exc
        buffer = cls(*shape, device=device, columns=state.get("columns"))
        buffer.load_state_dict(state)
        return buffer

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` saved; raises CheckpointError when it does not fit."""
        try:
            if state.get("format") != _STATE_FORMAT:
                raise CheckpointError(
                    f"replay state has format {state.get('format')!r}, expected {_STATE_FORMAT}")
            expected = {"columns": None, **self._shape_info()}  # no declared columns: the key is absent
            mismatched = [f"{k}: saved {state.get(k)!r}, buffer {v!r}"
                          for k, v in expected.items() if state.get(k) != v]
            if mismatched:
                raise CheckpointError("replay state does not match this buffer ("
                                      + "; ".join(mismatched) + ")")
            lengths = torch.as_tensor(state["lengths"]).to(torch.int64).numpy()
            rows = torch.as_tensor(state["rows"])
            rows64 = None if self._store64 is None else torch.as_tensor(state["rows_float64"])
            episode_open = bool(state["episode_open"])
            # States written before the count was kept: no episode had been evicted in the runs
            # that could use it (the loader shards came with it).
            episodes_begun = int(state.get("episodes_begun", len(lengths)))
            if self.sampler is not None:
                if "sampler" not in state:
                    raise CheckpointError("replay state was written without the loader-shards sampler this run uses")
                self.sampler.load_state_dict(state["sampler"])
        except CheckpointError:
            raise
        except (KeyError, TypeError, AttributeError, RuntimeError) as exc:
            raise CheckpointError(f"replay state is incomplete or malformed: {exc!r}") from exc
        num_episodes = len(lengths)
        expected_rows = int((lengths + 1).sum())
        problems = []
        if lengths.ndim != 1 or num_episodes > self.num_slots:
            problems.append(f"{num_episodes} episodes for {self.num_slots} slots")
        if num_episodes and (lengths.min() < 0 or lengths.max() > self.max_episode_length):
            problems.append("an episode length outside [0, max_episode_length]")
        if int(lengths.sum()) > self.capacity:
            problems.append(f"{int(lengths.sum())} transitions for capacity {self.capacity}")
        if tuple(rows.shape) != (expected_rows, self.width) or rows.dtype != torch.float32:
            problems.append(f"rows of shape {tuple(rows.shape)} and dtype {rows.dtype}, expected "
                            f"({expected_rows}, {self.width}) float32")
        if rows64 is not None and (tuple(rows64.shape) != (expected_rows, self.width64)
                                   or rows64.dtype != torch.float64):
            problems.append(f"float64 rows of shape {tuple(rows64.shape)} and dtype {rows64.dtype}, expected "
                            f"({expected_rows}, {self.width64}) float64")
        if episode_open and num_episodes == 0:
            problems.append("an open episode but no episodes")
        if problems:
            raise CheckpointError("replay state is inconsistent: " + "; ".join(problems))

        self._reset_bookkeeping()
        rows_per_episode = lengths + 1
        slot_index = torch.from_numpy(np.repeat(np.arange(num_episodes), rows_per_episode)).to(self.device)
        row_index = torch.from_numpy(np.arange(expected_rows) - np.repeat(
            np.cumsum(rows_per_episode) - rows_per_episode, rows_per_episode)).to(self.device)
        for store, saved in ((self._store, rows), (self._store64, rows64)):
            if store is not None:
                store.zero_()  # on CPU the host array itself
                store[slot_index, row_index] = saved.to(self.device)
        self._lengths[:num_episodes] = lengths
        self._num_episodes = num_episodes
        self._num_transitions = int(lengths.sum())
        self._episodes_begun = max(episodes_begun, num_episodes)
        self._open = episode_open
        if episode_open:
            self._cur_slot = num_episodes - 1
            self._cur_len = int(lengths[-1])
            self._write_slot = 0 if self._staged else self._cur_slot
            if self._staged:
                # The staging copy must hold the episode in progress; all of it is on the device.
                self._host[0, : self._cur_len + 1] = rows[expected_rows - self._cur_len - 1:].numpy()
                if rows64 is not None:
                    self._host64[0, : self._cur_len + 1] = rows64[expected_rows - self._cur_len - 1:].numpy()
                self._flushed_rows = self._cur_len
