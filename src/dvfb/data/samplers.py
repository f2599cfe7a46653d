"""How batches are drawn from a replay: the sampling config and the authors' loader shards
(docs/methods.md, "Replay sampling"; the rules are in :mod:`dvfb.data.buffer`'s docstring)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dvfb.core.config import param
from dvfb.core.errors import CheckpointError, ConfigError

REPLAY_SAMPLINGS = ("uniform", "loader_shards")


@dataclass
class ReplaySamplingConfig:
    """How pre-training batches are drawn from the replay (docs/methods.md, "Replay sampling"), and
    whether the replay records physics states (docs/methods.md, "Datasets")."""

    sampling: str = param("uniform", "uniform: every stored transition equally likely, the episode in progress "
                          "included; loader_shards: as the authors' (URLB's) DataLoader delivers them, finished "
                          "episodes only, each batch from one of --replay.loader-workers shards of the episodes.",
                          REPLAY_SAMPLINGS)
    loader_workers: int = param(4, "loader_shards: number of shards W (their replay_buffer_num_workers); episode g "
                                "belongs to shard g mod W and batch k comes from shard k mod W.", at_least=1)
    loader_refresh: int = param(1000, "loader_shards: a shard looks for newly finished episodes every this many of "
                                "its own samples (their fetch_every).", at_least=1)
    record_physics: bool = param(False, "Pre-training also stores the environment's physics state (float64) with "
                                 "every observation, the reset one included, so that `dvfb dataset export` can write "
                                 "the run's replay as a dataset that `dvfb dataset relabel` relabels exactly for any "
                                 "task of the domain (docs/methods.md, \"Datasets\").")

    def sampler(self) -> LoaderShards | None:
        """The replay's sampler: None for uniform sampling."""
        if self.sampling == "uniform":
            return None
        return LoaderShards(self.loader_workers, self.loader_refresh)


class LoaderShards:
    """The authors' DataLoader sampling, as a sampler of a :class:`ReplayBuffer` (module docstring,
    "Loader shards").

    Per shard ``w`` it keeps how many episodes had finished when ``w`` last looked
    (``visible[w]``) and how many samples it has drawn since (``since_refresh[w]``); a shard looks
    before a sample once ``refresh`` samples have passed, so a look can fall inside a batch, as it
    does in a DataLoader worker. Eviction stays the buffer's (oldest episode first, globally), where
    each of their workers evicts its own oldest episode beyond ``capacity / W``: the same episodes
    for runs that never fill the buffer, and nearly the same otherwise.
    """

    def __init__(self, workers: int, refresh: int):
        if workers < 1 or refresh < 1:
            raise ConfigError(f"loader shards need workers >= 1 and refresh >= 1, got {workers} and {refresh}")
        self.workers, self.refresh = int(workers), int(refresh)
        self.visible = np.zeros(self.workers, dtype=np.int64)
        self.since_refresh = np.full(self.workers, self.refresh, dtype=np.int64)  # the first sample looks
        self.batches = 0

    def _pool(self, shard: int, first_index: int, finished: int, counts: np.ndarray) -> np.ndarray:
        """Ring positions the shard samples from: its finished episodes that it has seen and that
        still have an eligible step; if it holds none (too few episodes for the shards), every
        finished episode; if none has finished yet, every stored episode."""
        index = first_index + np.arange(finished)
        eligible = counts[:finished] > 0
        mine = eligible & (index % self.workers == shard) & (index < self.visible[shard])
        for pool in (mine, eligible):
            if pool.any():
                return np.flatnonzero(pool)
        return np.flatnonzero(counts > 0)

    def draw(self, slots: np.ndarray, counts: np.ndarray, first_index: int, finished: int, batch_size: int,
             generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
        """(slot, step) of ``batch_size`` transitions. ``slots`` and ``counts`` (eligible steps) are
        in ring order, whose position ``i`` is episode ``first_index + i`` of the run; the first
        ``finished`` positions are finished episodes."""
        device = generator.device if generator is not None else torch.device("cpu")
        shard = self.batches % self.workers
        self.batches += 1
        slots_t, counts_t = torch.from_numpy(slots).to(device), torch.from_numpy(counts).to(device)
        slot_parts, step_parts = [], []
        done = 0
        while done < batch_size:
            if self.since_refresh[shard] >= self.refresh:
                self.since_refresh[shard] = 0
                self.visible[shard] = first_index + finished
            n = int(min(batch_size - done, self.refresh - self.since_refresh[shard]))
            self.since_refresh[shard] += n
            pool = torch.from_numpy(self._pool(shard, first_index, finished, counts)).to(device)
            episode = pool[torch.randint(len(pool), (n,), generator=generator, device=device)]
            length = counts_t[episode]
            uniform = torch.rand(n, generator=generator, device=device, dtype=torch.float64)
            step_parts.append((uniform * length).floor().long().minimum(length - 1))
            slot_parts.append(slots_t[episode])
            done += n
        return torch.cat(slot_parts), torch.cat(step_parts)

    def state_dict(self) -> dict:
        return {"workers": self.workers, "refresh": self.refresh, "visible": torch.from_numpy(self.visible.copy()),
                "since_refresh": torch.from_numpy(self.since_refresh.copy()), "batches": self.batches}

    def load_state_dict(self, state: dict) -> None:
        if (state.get("workers"), state.get("refresh")) != (self.workers, self.refresh):
            raise CheckpointError(f"replay sampler state is for {state.get('workers')} shards refreshed every "
                                  f"{state.get('refresh')} samples; this run has {self.workers} and {self.refresh}")
        self.visible = torch.as_tensor(state["visible"]).to(torch.int64).numpy().copy()
        self.since_refresh = torch.as_tensor(state["since_refresh"]).to(torch.int64).numpy().copy()
        self.batches = int(state["batches"])
