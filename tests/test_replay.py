"""Tests for dvfb.data.buffer (docs/methods.md §6; section 13 invariant 30)."""

import io
import re

import numpy as np
import pytest
import torch
from scipy import stats

import dvfb.data.buffer as replay_module
from dvfb.core.errors import CheckpointError, ConfigError
from dvfb.data import ReplayBuffer

OBS_DIM, ACTION_DIM, Z_DIM = 3, 2, 2


# Every field encodes (episode, t) so that a sampled row can be traced back to where it came from.
def obs_of(episode: int, t: int) -> np.ndarray:
    return np.array([episode, t, 1000 * episode + t], dtype=np.float32)


def action_of(episode: int, t: int) -> np.ndarray:
    return np.array([episode, t], dtype=np.float32) + 0.25


def reward_of(episode: int, t: int) -> float:
    """The reward the env returns together with obs_{t+1}, i.e. for the step taken at t."""
    return 1000.0 * episode + t + 0.5


def z_of(episode: int, t: int) -> np.ndarray:
    return np.array([-episode, -t], dtype=np.float32)


def run_episode(buffer: ReplayBuffer, episode: int, length: int) -> None:
    buffer.start_episode(obs_of(episode, 0))
    for t in range(length):
        z = z_of(episode, t) if buffer.z_dim else None
        buffer.add(action_of(episode, t), reward_of(episode, t), 1.0, obs_of(episode, t + 1), z)


def make_buffer(capacity=200, max_episode_length=10, z_dim=Z_DIM, **kwargs) -> ReplayBuffer:
    return ReplayBuffer(capacity, OBS_DIM, ACTION_DIM, z_dim=z_dim,
                        max_episode_length=max_episode_length, **kwargs)


def fill(buffer: ReplayBuffer, lengths, first_episode: int = 0) -> None:
    for i, length in enumerate(lengths):
        run_episode(buffer, first_episode + i, length)


def check_batch(batch, gamma=0.99, need_future=False, lengths=None):
    """Every row of ``batch`` is a genuine transition of one episode."""
    episode = batch.obs[:, 0]
    t = batch.obs[:, 1]
    assert torch.equal(batch.next_obs[:, 0], episode), "next_obs from another episode"
    assert torch.equal(batch.next_obs[:, 1], t + 1), "next_obs is not obs_{t+1}"
    assert torch.equal(batch.action, torch.stack([episode, t], 1) + 0.25), \
        "action is not the one taken in obs (the one that produced next_obs)"
    assert torch.equal(batch.reward[:, 0], 1000 * episode + t + 0.5), \
        "reward is not the one returned with next_obs"
    assert batch.reward.shape == (len(batch), 1) and batch.discount.shape == (len(batch), 1)
    assert torch.allclose(batch.discount, torch.full_like(batch.discount, gamma))
    if batch.z is not None:
        assert torch.equal(batch.z, torch.stack([-episode, -t], 1))
    if need_future:
        assert torch.equal(batch.future_obs[:, 0], episode), "future_obs from another episode"
        assert torch.equal(batch.future_obs[:, 1], t + 2), "future_obs is not obs_{t+2}"
    else:
        assert batch.future_obs is None
    if lengths is not None:
        # t + 1 (or t + 2) never runs past the end of its episode.
        limit = torch.tensor([lengths[int(e)] for e in episode])
        assert torch.all(t + (2 if need_future else 1) <= limit)


@pytest.mark.parametrize("stage_on_host", [False, True])
@pytest.mark.parametrize("need_future", [False, True])
def test_transitions_stay_inside_episodes(stage_on_host, need_future):
    lengths = [5, 1, 7, 10, 2, 3]
    buffer = make_buffer(stage_on_host=stage_on_host)
    fill(buffer, lengths)
    # An episode in progress may be sampled too.
    buffer.start_episode(obs_of(len(lengths), 0))
    for t in range(4):
        buffer.add(action_of(6, t), reward_of(6, t), 1.0, obs_of(6, t + 1), z_of(6, t))
    lengths = lengths + [4]
    g = torch.Generator().manual_seed(0)
    batch = buffer.sample(4096, need_future=need_future, generator=g)
    check_batch(batch, need_future=need_future, lengths=lengths)
    seen = set(zip(batch.obs[:, 0].int().tolist(), batch.obs[:, 1].int().tolist()))
    eligible = {(e, t) for e, n in enumerate(lengths) for t in range(n - int(need_future))}
    assert seen == eligible  # all eligible transitions drawn, nothing else


def test_discount_is_gamma_times_env_discount():
    buffer = make_buffer()
    buffer.start_episode(obs_of(0, 0))
    buffer.add(action_of(0, 0), 0.0, 1.0, obs_of(0, 1), z_of(0, 0))
    buffer.add(action_of(0, 1), 0.0, 0.0, obs_of(0, 2), z_of(0, 1))
    batch = buffer.transitions()
    assert batch.discount[:, 0].tolist() == pytest.approx([0.99, 0.0])
    assert buffer.transitions(gamma=0.9).discount[0, 0].item() == pytest.approx(0.9)
    assert buffer.sample(64, gamma=0.5).discount.max().item() == pytest.approx(0.5)


def test_transitions_returns_everything_in_order():
    lengths = [3, 1, 4]
    buffer = make_buffer()
    fill(buffer, lengths)
    batch = buffer.transitions()
    expected = [(e, t) for e, n in enumerate(lengths) for t in range(n)]
    assert list(zip(batch.obs[:, 0].int().tolist(), batch.obs[:, 1].int().tolist())) == expected
    check_batch(batch, lengths=lengths)
    assert len(buffer) == len(batch) == 8
    assert buffer.num_episodes == 3


def test_z_is_none_without_z_dim():
    buffer = make_buffer(z_dim=0)
    fill(buffer, [4])
    batch = buffer.sample(8)
    assert batch.z is None
    check_batch(batch)


def test_fifo_eviction_by_whole_episodes():
    # capacity 30, episodes of up to 10 steps: 4 slots.
    buffer = make_buffer(capacity=30, max_episode_length=10)
    assert buffer.num_slots == 4
    rng = np.random.default_rng(0)
    lengths = []
    for episode in range(40):
        length = int(rng.integers(1, 11))
        lengths.append(length)
        buffer.start_episode(obs_of(episode, 0))
        for t in range(length):
            buffer.add(action_of(episode, t), reward_of(episode, t), 1.0, obs_of(episode, t + 1),
                       z_of(episode, t))
            assert len(buffer) <= buffer.capacity
            stored = buffer.transitions()
            episodes = sorted(set(stored.obs[:, 0].int().tolist()))
            # The stored episodes are the most recent ones, contiguous, each one complete
            # (except the one in progress).
            assert episodes == list(range(episodes[0], episode + 1))
            for e in episodes[:-1]:
                assert int((stored.obs[:, 0] == e).sum()) == lengths[e]
            # Eviction happens only when needed: the oldest dropped episode did not fit.
            dropped = episodes[0] - 1
            if dropped >= 0 and buffer.num_episodes < buffer.num_slots:
                assert len(buffer) + lengths[dropped] > buffer.capacity
            check_batch(stored, lengths=lengths)


def test_full_length_episodes_fill_capacity():
    buffer = make_buffer(capacity=30, max_episode_length=10)
    fill(buffer, [10] * 7)
    assert len(buffer) == 30
    assert sorted(set(buffer.transitions().obs[:, 0].int().tolist())) == [4, 5, 6]
    run_episode(buffer, 7, 1)  # one more step evicts the oldest whole episode
    assert len(buffer) == 21
    assert sorted(set(buffer.transitions().obs[:, 0].int().tolist())) == [5, 6, 7]


@pytest.mark.parametrize("need_future", [False, True])
def test_sampling_is_uniform_over_transitions(need_future):
    lengths = [1, 3, 9, 2, 6, 10, 4]
    buffer = make_buffer(capacity=100)
    fill(buffer, lengths[:-1])
    buffer.start_episode(obs_of(len(lengths) - 1, 0))  # the last episode is in progress
    for t in range(lengths[-1]):
        e = len(lengths) - 1
        buffer.add(action_of(e, t), reward_of(e, t), 1.0, obs_of(e, t + 1), z_of(e, t))
    cells = [(e, t) for e, n in enumerate(lengths) for t in range(n - int(need_future))]
    index = {cell: i for i, cell in enumerate(cells)}
    g = torch.Generator().manual_seed(1234)
    counts = np.zeros(len(cells))
    draws_per_cell = 2000
    for _ in range(5):
        batch = buffer.sample(draws_per_cell * len(cells) // 5, need_future=need_future,
                              generator=g)
        for e, t in zip(batch.obs[:, 0].int().tolist(), batch.obs[:, 1].int().tolist()):
            counts[index[(e, t)]] += 1
    result = stats.chisquare(counts)
    assert result.pvalue > 1e-3, (result, counts)
    # And per-cell: within 5 standard deviations of the uniform expectation.
    expected = counts.sum() / len(cells)
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))


def test_generator_makes_sampling_reproducible():
    buffer = make_buffer()
    fill(buffer, [5, 7, 3])
    a = buffer.sample(256, need_future=True, generator=torch.Generator().manual_seed(7))
    b = buffer.sample(256, need_future=True, generator=torch.Generator().manual_seed(7))
    c = buffer.sample(256, need_future=True, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a.obs, b.obs) and torch.equal(a.future_obs, b.future_obs)
    assert not torch.equal(a.obs, c.obs)


def seeded(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def assert_batches_equal(a, b):
    for name in ("obs", "action", "reward", "discount", "next_obs", "future_obs", "z"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or torch.equal(x, y), name


@pytest.mark.parametrize("stage_on_host", [False, True])
def test_state_dict_round_trip_gives_identical_samples(stage_on_host):
    original = make_buffer(capacity=30, max_episode_length=10, stage_on_host=stage_on_host)
    fill(original, [10, 4, 9, 8, 10, 7])  # wraps the slot ring
    original.start_episode(obs_of(6, 0))
    for t in range(3):  # leave an episode in progress
        original.add(action_of(6, t), reward_of(6, t), 1.0, obs_of(6, t + 1), z_of(6, t))

    state = original.state_dict()
    assert state["rows"].shape[0] == len(original) + original.num_episodes  # compact
    blob = io.BytesIO()
    torch.save(state, blob)  # goes into checkpoints: must load with weights_only=True
    blob.seek(0)
    state = torch.load(blob, weights_only=True)

    restored = make_buffer(capacity=30, max_episode_length=10, stage_on_host=stage_on_host)
    fill(restored, [2, 3])  # whatever was there before is replaced
    restored.load_state_dict(state)
    assert len(restored) == len(original) and restored.num_episodes == original.num_episodes
    assert_batches_equal(original.transitions(), restored.transitions())
    for need_future in (False, True):
        a = original.sample(512, need_future=need_future, generator=seeded(3))
        b = restored.sample(512, need_future=need_future, generator=seeded(3))
        assert_batches_equal(a, b)

    # Both continue the episode in progress and evict identically afterwards.
    for buffer in (original, restored):
        for t in range(3, 6):
            buffer.add(action_of(6, t), reward_of(6, t), 1.0, obs_of(6, t + 1), z_of(6, t))
        fill(buffer, [9, 10], first_episode=7)
    assert_batches_equal(original.transitions(), restored.transitions())
    check_batch(original.transitions())
    a = original.sample(512, need_future=True, generator=torch.Generator().manual_seed(4))
    b = restored.sample(512, need_future=True, generator=torch.Generator().manual_seed(4))
    assert_batches_equal(a, b)


def test_state_dict_of_empty_buffer():
    state = make_buffer().state_dict()
    restored = make_buffer()
    restored.load_state_dict(state)
    assert len(restored) == 0 and restored.num_episodes == 0
    fill(restored, [3])
    assert len(restored) == 3


def test_load_state_dict_mismatch_raises_checkpoint_error():
    source = make_buffer()
    fill(source, [4, 5])
    state = source.state_dict()
    with pytest.raises(CheckpointError, match="obs_dim"):
        wider = ReplayBuffer(200, OBS_DIM + 1, ACTION_DIM, Z_DIM, max_episode_length=10)
        wider.load_state_dict(state)
    with pytest.raises(CheckpointError, match="z_dim"):
        make_buffer(z_dim=0).load_state_dict(state)
    with pytest.raises(CheckpointError, match="capacity"):
        make_buffer(capacity=100).load_state_dict(state)
    with pytest.raises(CheckpointError, match="malformed"):
        make_buffer().load_state_dict({k: v for k, v in state.items() if k != "rows"})
    with pytest.raises(CheckpointError, match="inconsistent"):
        make_buffer().load_state_dict({**state, "rows": state["rows"][:-1]})
    target = make_buffer()
    fill(target, [2])
    with pytest.raises(CheckpointError):
        target.load_state_dict({**state, "lengths": torch.tensor([4, 50])})
    assert len(target) == 2  # a rejected state leaves the buffer as it was


def test_errors_are_clear():
    with pytest.raises(ConfigError, match="at least max_episode_length"):
        ReplayBuffer(5, OBS_DIM, ACTION_DIM, max_episode_length=10)
    buffer = make_buffer(max_episode_length=3)
    with pytest.raises(RuntimeError, match="start_episode"):
        buffer.add(action_of(0, 0), 0.0, 1.0, obs_of(0, 1), z_of(0, 0))
    with pytest.raises(ValueError, match="no transition"):
        buffer.sample(4)
    run_episode(buffer, 0, 3)
    with pytest.raises(ConfigError, match="max_episode_length=3"):
        buffer.add(action_of(0, 3), 0.0, 1.0, obs_of(0, 4), z_of(0, 3))
    buffer.start_episode(obs_of(1, 0))
    with pytest.raises(ValueError, match="z_dim"):
        buffer.add(action_of(1, 0), 0.0, 1.0, obs_of(1, 1))
    single = make_buffer()
    run_episode(single, 0, 1)
    with pytest.raises(ValueError, match="2-step successor"):
        single.sample(4, need_future=True)


def test_restarting_an_empty_episode_reuses_its_slot():
    buffer = make_buffer(capacity=20, max_episode_length=10)
    for _ in range(10):
        buffer.start_episode(obs_of(0, 0))
    assert buffer.num_episodes == 1
    run_episode(buffer, 0, 2)
    assert buffer.num_episodes == 1 and len(buffer) == 2


def test_documented_memory_figure():
    documented = re.search(r"estimate_nbytes\(2_000_000, 24, 6, 50\)`` .*? = ([\d,]+) bytes",
                           replay_module.__doc__, re.S)
    assert documented, "module docstring must state the 2M-walker memory"
    assert int(documented.group(1).replace(",", "")) == ReplayBuffer.estimate_nbytes(
        2_000_000, 24, 6, 50)
    for capacity, max_len, z_dim in ((5000, 100, 50), (1000, 1000, 0)):
        buffer = ReplayBuffer(capacity, 24, 6, z_dim, max_episode_length=max_len)
        assert buffer.nbytes == ReplayBuffer.estimate_nbytes(capacity, 24, 6, z_dim, max_len)


# ---------------------------------------------------------------------------------------------
# n-step tuples (URLB-style agents, n = 3)


def test_nstep_tuples_by_hand_across_an_episode_boundary():
    """Episodes of 4 and 5 steps: with n = 3 only t <= T - 3 is eligible (2 + 3 transitions), and
    each row is (s_t, a_t, r_t + g r_{t+1} + g^2 r_{t+2}, g^3, s_{t+3}, z_t), never crossing into the
    next episode."""
    gamma = 0.9
    buffer = make_buffer()
    fill(buffer, [4, 5])
    batch = buffer.sample(4000, gamma, nstep=3, generator=torch.Generator().manual_seed(0))
    episode, t = batch.obs[:, 0].long(), batch.obs[:, 1].long()
    pairs = set(zip(episode.tolist(), t.tolist()))
    assert pairs == {(0, 0), (0, 1), (1, 0), (1, 1), (1, 2)}  # every eligible one is drawn, no other
    for e, s in pairs:
        rows = (episode == e) & (t == s)
        expected = sum(gamma ** i * reward_of(e, s + i) for i in range(3))
        assert torch.allclose(batch.reward[rows], torch.full((int(rows.sum()), 1), expected))
        assert torch.equal(batch.next_obs[rows][0], torch.as_tensor(obs_of(e, s + 3)))
        assert torch.equal(batch.action[rows][0], torch.as_tensor(action_of(e, s)))
        assert torch.equal(batch.z[rows][0], torch.as_tensor(z_of(e, s)))
    assert torch.allclose(batch.discount, torch.full_like(batch.discount, gamma ** 3))
    # The draw is uniform over the 5 eligible transitions.
    counts = np.array([int(((episode == e) & (t == s)).sum()) for e, s in sorted(pairs)])
    assert stats.chisquare(counts).pvalue > 1e-3


def test_nstep_reward_stops_at_a_terminal_step():
    """An environment discount of 0 at step t+1 zeroes the rewards after it and the bootstrap."""
    gamma = 0.5
    buffer = make_buffer(z_dim=0)
    buffer.start_episode(obs_of(0, 0))
    for t, discount in enumerate([1.0, 0.0, 1.0, 1.0]):
        buffer.add(action_of(0, t), reward_of(0, t), discount, obs_of(0, t + 1))
    batch = buffer.sample(2000, gamma, nstep=3, generator=torch.Generator().manual_seed(1))
    first = batch.obs[:, 1] == 0
    # r_0 + g * d_0 * r_1 + g^2 * d_0 * d_1 * r_2 with d_1 = 0; bootstrap g^3 * d_0 d_1 d_2 = 0.
    assert torch.allclose(batch.reward[first], torch.tensor(reward_of(0, 0) + gamma * reward_of(0, 1)))
    assert torch.equal(batch.discount[first], torch.zeros_like(batch.discount[first]))
    second = batch.obs[:, 1] == 1
    assert torch.allclose(batch.reward[second], torch.tensor(reward_of(0, 1)))


def test_nstep_needs_n_steps_in_one_episode():
    buffer = make_buffer()
    fill(buffer, [2, 2])
    with pytest.raises(ValueError, match="3-step successor"):
        buffer.sample(8, nstep=3)
    assert len(buffer.sample(8, nstep=2)) == 8


def test_declared_columns_are_stored_sampled_saved_and_counted():
    """A column declared by what needs it (here a 3-wide 'physics' state) rides with every step: in
    1-step and n-step batches (the row of s_t), chunks, the state round trip and the memory estimate."""
    buffer = ReplayBuffer(100, 2, 1, z_dim=2, max_episode_length=10, columns={"physics": 3})
    assert buffer.nbytes == ReplayBuffer.estimate_nbytes(100, 2, 1, 2, 10, columns={"physics": 3})
    assert buffer.nbytes > ReplayBuffer.estimate_nbytes(100, 2, 1, 2, 10)
    buffer.start_episode(np.zeros(2, np.float32))
    for t in range(8):
        buffer.add(np.full(1, t, np.float32), float(t), 1.0, np.full(2, t + 1, np.float32),
                   np.full(2, -t, np.float32), physics=np.full(3, 10 * t, np.float32))
    batch = buffer.sample(64, nstep=3, generator=torch.Generator().manual_seed(0))
    step = batch.action[:, 0]
    assert torch.equal(batch.columns["physics"], (10 * step).unsqueeze(1).expand(-1, 3))
    assert torch.equal(batch.z, (-step).unsqueeze(1).expand(-1, 2))
    assert all(torch.equal(c.columns["physics"], batch.columns["physics"][i * 32:(i + 1) * 32])
               for i, c in enumerate(batch.chunk(2)))
    restored = ReplayBuffer(100, 2, 1, z_dim=2, max_episode_length=10, columns={"physics": 3})
    restored.load_state_dict(buffer.state_dict())
    assert torch.equal(restored.transitions().columns["physics"], buffer.transitions().columns["physics"])
    plain = ReplayBuffer(100, 2, 1, z_dim=2, max_episode_length=10)
    with pytest.raises(CheckpointError, match="columns"):
        plain.load_state_dict(buffer.state_dict())
    buffer.start_episode(np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="physics"):
        buffer.add(np.zeros(1, np.float32), 0.0, 1.0, np.zeros(2, np.float32), np.zeros(2, np.float32))
    with pytest.raises(ConfigError, match="skill"):
        ReplayBuffer(100, 2, 1, max_episode_length=10, columns={"skill": 2})
