"""The replay's loader-shards sampling (docs/methods.md, "Replay sampling"): the distribution of
the authors' DataLoader batches, which the ``code`` preset selects for every method.

These are the properties that made the authors' agent score higher than dvfb's on walker when dvfb
sampled uniformly (docs/results/crosscheck_walker.md): a batch never holds the episode in progress,
holds only one shard's episodes (right after the seed phase: one episode), and sees a finished
episode only after its shard's next look. Each is checked against an independent model of the
loader written here from its description, on fixed seeds, with exact counts where the rule is exact.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dvfb.agents.registry import agent_names
from dvfb.data import LoaderShards, ReplayBuffer
from dvfb.runs.presets import preset_config

OBS, ACT = 3, 2


def add_episode(replay: ReplayBuffer, index: int, steps: int, finish: bool = True) -> None:
    """An episode whose observations carry its index (column 0) and the time step (column 1)."""
    replay.start_episode(np.array([index, 0, 0], np.float32))
    for t in range(steps):
        replay.add(np.zeros(ACT, np.float32), 0.0, 1.0, np.array([index, t + 1, 0], np.float32))


def episodes_of(batch) -> set[int]:
    return set(batch.obs[:, 0].long().tolist())


def shard_replay(workers: int = 4, refresh: int = 1000, capacity: int = 100_000, length: int = 50) -> ReplayBuffer:
    return ReplayBuffer(capacity, OBS, ACT, 0, max_episode_length=length, sampler=LoaderShards(workers, refresh))


def test_the_code_preset_samples_like_the_authors_loader_for_every_method():
    for agent in agent_names():
        code = preset_config("code", agent).replay
        assert (code.sampling, code.loader_workers, code.loader_refresh) == ("loader_shards", 4, 1000), agent
        assert isinstance(code.sampler(), LoaderShards)
        for preset in ("small", "paper"):
            assert preset_config(preset, agent).replay.sampler() is None, (agent, preset)


def test_after_the_seed_phase_each_batch_is_one_episode_in_shard_order():
    # 4 finished episodes (the 4,000 seed frames of walker) and one in progress.
    replay = shard_replay()
    for g in range(4):
        add_episode(replay, g, 50)
    add_episode(replay, 99, 20)
    generator = torch.Generator().manual_seed(0)
    seen = [episodes_of(replay.sample(256, need_future=True, generator=generator)) for _ in range(8)]
    assert seen == [{0}, {1}, {2}, {3}, {0}, {1}, {2}, {3}]


def test_uniform_sampling_mixes_every_episode_and_the_one_in_progress():
    replay = ReplayBuffer(100_000, OBS, ACT, 0, max_episode_length=50)
    for g in range(4):
        add_episode(replay, g, 50)
    add_episode(replay, 99, 20)
    batch = replay.sample(256, need_future=True, generator=torch.Generator().manual_seed(0))
    assert episodes_of(batch) == {0, 1, 2, 3, 99}


def test_a_shard_holds_the_episodes_of_its_residue_and_never_the_episode_in_progress():
    replay = shard_replay(workers=4)
    for g in range(11):
        add_episode(replay, g, 50)
    add_episode(replay, 99, 30)
    generator = torch.Generator().manual_seed(1)
    for k in range(12):
        seen = episodes_of(replay.sample(512, need_future=True, generator=generator))
        assert seen == {g for g in range(11) if g % 4 == k % 4}, k


def test_within_a_shard_episodes_are_equally_likely_and_steps_uniform():
    # One shard with a short and a long episode: episode-uniform gives each about half of the draws
    # (uniform over transitions would give the short one 1/5).
    replay = shard_replay(workers=1, length=40)
    add_episode(replay, 0, 10)
    add_episode(replay, 1, 40)
    replay.start_episode(np.zeros(OBS, np.float32))
    batch = replay.sample(20_000, need_future=True, generator=torch.Generator().manual_seed(2))
    short = (batch.obs[:, 0] == 0)
    assert 0.47 < short.float().mean().item() < 0.53
    # Steps: t = 0 .. T-2 with s_{t+2} in the episode (the last transition is never drawn), evenly.
    steps = batch.obs[short, 1].long()
    counts = torch.bincount(steps, minlength=9)
    assert steps.max().item() == 8 and (batch.future_obs[:, 1] - batch.obs[:, 1] == 2).all()
    assert counts.min().item() > 0.8 * counts.float().mean().item()


class ReferenceLoader:
    """The loader as described (not as implemented in dvfb): W workers; worker w holds the finished
    episodes g with g mod W == w that it had seen at its last look; it looks before a sample
    whenever `refresh` of its samples have passed since the last look (and before its first);
    batch k comes from worker k mod W."""

    def __init__(self, workers: int, refresh: int):
        self.workers, self.refresh = workers, refresh
        self.held = [set() for _ in range(workers)]
        self.since = [refresh] * workers
        self.batches = 0

    def pools(self, finished: list[int], batch_size: int) -> list[set[int]]:
        """The set each sample of the next batch is drawn from."""
        w = self.batches % self.workers
        self.batches += 1
        out = []
        for _ in range(batch_size):
            if self.since[w] >= self.refresh:
                self.since[w] = 0
                self.held[w] = {g for g in finished if g % self.workers == w}
            self.since[w] += 1
            out.append(set(self.held[w]))
        return out


def test_new_episodes_reach_a_shard_only_at_its_next_look_as_the_reference_loader():
    workers, refresh, batch_size = 2, 100, 30
    replay = shard_replay(workers=workers, refresh=refresh, length=20)
    reference = ReferenceLoader(workers, refresh)
    generator = torch.Generator().manual_seed(3)
    for g in range(3):  # episodes 0 and 1 finished, 2 in progress
        add_episode(replay, g, 20)
    finished, newest = [0, 1], 2
    lagged = 0
    for k in range(40):
        if k % 3 == 2:  # the episode in progress ends and the next one starts
            newest += 1
            add_episode(replay, newest, 20)
            finished.append(newest - 1)
        batch = replay.sample(batch_size, need_future=True, generator=generator)
        drawn = batch.obs[:, 0].long().tolist()
        pools = reference.pools(finished, batch_size)
        assert all(e in pool for e, pool in zip(drawn, pools)), k
        # The shard holds what the reference worker holds, and looks when it looks: a sampler that
        # never looked again would still draw inside the pools above.
        shard = replay.sampler
        for w in range(workers):
            held = {f for f in finished if f % workers == w and f < shard.visible[w]}
            assert held == reference.held[w] and shard.since_refresh[w] == reference.since[w], (k, w)
        assert all(e < newest for e in drawn), k  # never the episode in progress
        # Samples drawn while a finished episode of the shard was not yet seen by it.
        lagged += sum(len({f for f in finished if f % workers == (k % workers)} - pool) > 0 for pool in pools)
    assert lagged > 0  # the look-ahead lag was exercised, not only the steady state


def test_loader_state_round_trip_continues_the_same_draws():
    def fill(replay):
        for g in range(6):
            add_episode(replay, g, 30)
        add_episode(replay, 99, 10)

    a, b = shard_replay(refresh=70, length=30), shard_replay(refresh=70, length=30)
    fill(a)
    ga = torch.Generator().manual_seed(4)
    for _ in range(5):
        a.sample(40, generator=ga)
    fill(b)
    b.load_state_dict(a.state_dict())
    gb = torch.Generator().manual_seed(0)
    gb.set_state(ga.get_state())
    for _ in range(6):
        x, y = a.sample(40, generator=ga), b.sample(40, generator=gb)
        assert torch.equal(x.obs, y.obs) and torch.equal(x.next_obs, y.next_obs)


def test_a_uniform_replay_state_does_not_resume_a_sharded_one():
    from dvfb.core.errors import CheckpointError

    uniform = ReplayBuffer(1000, OBS, ACT, 0, max_episode_length=50)
    add_episode(uniform, 0, 50)
    with pytest.raises(CheckpointError, match="loader-shards"):
        shard_replay(capacity=1000).load_state_dict(uniform.state_dict())
    other = ReplayBuffer(1000, OBS, ACT, 0, max_episode_length=50, sampler=LoaderShards(2, 1000))
    add_episode(other, 0, 50)
    with pytest.raises(CheckpointError, match="2 shards"):
        shard_replay(capacity=1000).load_state_dict(other.state_dict())


def test_too_few_finished_episodes_fall_back_instead_of_failing():
    # Fewer finished episodes than shards (short test runs): an empty shard samples every finished
    # episode; before any episode has finished, the episode in progress.
    replay = shard_replay(workers=4, length=50)
    add_episode(replay, 7, 20)
    generator = torch.Generator().manual_seed(5)
    assert episodes_of(replay.sample(64, generator=generator)) == {7}
    replay.start_episode(np.array([8, 0, 0], np.float32))
    replay.add(np.zeros(ACT, np.float32), 0.0, 1.0, np.array([8, 1, 0], np.float32))
    for _ in range(4):
        assert episodes_of(replay.sample(64, generator=generator)) == {7}


def test_the_sampling_section_is_checked_like_every_option():
    from dvfb.core.errors import ConfigError
    from dvfb.runs.run_config import run_config_from_dict

    with pytest.raises(ConfigError, match="sampling"):
        run_config_from_dict({"agent": "fb", "replay": {"sampling": "episodes"}})
    with pytest.raises(ConfigError, match="--replay.loader-workers 0"):
        run_config_from_dict({"agent": "fb", "replay": {"loader_workers": 0}})
    # Configs written before the section existed read as uniform sampling.
    assert run_config_from_dict({"agent": "fb"}).replay.sampler() is None
