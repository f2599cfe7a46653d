"""Tests for DVFB's exploration part and the pre-training update (docs/methods.md §4.5-§4.6,
§7.2-§7.7; §13 invariants 23-26 and 31): the NCE loss, the contrastive-entropy reward, RND, the
exploration critic, gradient isolation of every step and the EMA of the targets."""

import math

import numpy as np
import pytest
import torch
from torch.nn import functional as F_nn

from dvfb.agents.dvfb import DVFBAgent
from dvfb.agents.fb import BACKWARD_INPUTS, FBAgent, FBConfig
from dvfb.rewards.contrastive import contrastive_entropy_reward, nce_loss
from dvfb.rewards.rnd import RNDReward
from dvfb.nets import sample_z_prior, training_action
from tiny import ACT, D, H, OBS, random_batch, tiny_exploration
from tiny import tiny_config as shared_tiny_config


TAU = 0.01


def tiny_config(**overrides) -> FBConfig:
    return shared_tiny_config(**{"tau": TAU, **overrides})


# ---------------------------------------------------------------------------------------------
# NCE (invariant 23)


def test_nce_hand_built_value():
    expected = -math.log(math.e / (1 + 1e-6))  # about -1
    for dim in (2, 5):
        basis = torch.eye(dim)[:2]  # q_i = k_i = e_i, N = 2
        assert nce_loss(basis, basis).item() == pytest.approx(expected, abs=1e-6)
        assert nce_loss(basis, basis, exact_positive=True).item() == pytest.approx(expected, abs=1e-6)
    # Inputs are L2-normalised first: scaling q or k changes nothing.
    basis = torch.eye(2)
    assert nce_loss(3 * basis, 0.5 * basis).item() == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("temperature,exact", [(1.0, False), (0.5, False), (0.5, True)])
def test_nce_matches_reference_formula(temperature, exact):
    g = torch.Generator().manual_seed(0)
    q, k = torch.randn(16, 6, generator=g, dtype=torch.float64), torch.randn(16, 6, generator=g, dtype=torch.float64)
    qn, kn = q / q.norm(dim=-1, keepdim=True), k / k.norm(dim=-1, keepdim=True)
    s = qn @ kn.T / temperature
    pos = s.diagonal().exp()
    sub = pos if exact else math.exp(1 / temperature)
    neg = (s.exp().sum(-1) - sub).clamp_min(1e-6)
    ref = -torch.log(pos / (neg + 1e-6)).mean()
    torch.testing.assert_close(nce_loss(q, k, temperature, exact), ref)


def _keys(n, a, b):
    """k_i = a e_i + b * (sum_{j != i} e_j) / sqrt(n-1) + c e_extra with |k_i| = 1; q_i = e_i.

    Then S_ii = a (positive alignment) and S_ij = b / sqrt(n-1) for i != j (negatives)."""
    eye = torch.eye(n + 1, dtype=torch.float64)[:n]
    others = (eye[:, :n].sum(0, keepdim=True) - eye[:, :n]) / math.sqrt(n - 1)
    c = math.sqrt(1 - a * a - b * b)
    keys = a * eye + b * torch.cat([others, torch.zeros(n, 1, dtype=torch.float64)], -1)
    keys[:, n] = c
    return eye, keys


@pytest.mark.parametrize("exact", [False, True])
def test_nce_decreases_as_negatives_separate(exact):
    n, a = 4, 0.6
    values = []
    for b in np.linspace(0.7, -0.7, 15):
        q, k = _keys(n, a, b)
        values.append(nce_loss(q, k, exact_positive=exact).item())
    assert np.all(np.diff(values) < 0), values


def test_nce_decreases_as_positives_align():
    for exact, n in ((True, 2), (True, 8), (False, 8)):
        values = []
        for a in np.linspace(0.1, 1.0, 10):
            q, k = _keys(n, a, 0.0)
            values.append(nce_loss(q, k, exact_positive=exact).item())
        assert np.all(np.diff(values) < 0), (exact, n, values)


def test_nce_cic_form_with_small_negative_mass_rewards_misalignment():
    """The [C] form subtracts e^{1/T}, not exp(S_ii): d L_i / d S_ii = (e - sum_{j!=i} e^{S_ij}) /
    (e^{S_ii} + sum_{j!=i} e^{S_ij} - e), which is positive when the negatives' mass is below e
    (e.g. N = 2). Documented here because §13 item 23 states monotonicity without this condition;
    at N = 1024 the negatives' mass is far above e."""
    values = []
    for a in np.linspace(0.6, 1.0, 5):
        q, k = _keys(2, a, 0.0)
        values.append(nce_loss(q, k).item())
    assert np.all(np.diff(values) > 0), values


# ---------------------------------------------------------------------------------------------
# Contrastive-entropy reward (invariant 24)


def _angles_to_vectors(angles_deg):
    a = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    return torch.tensor(np.stack([np.cos(a), np.sin(a)], -1))


def test_ce_reward_hand_computed_3x3():
    keys = _angles_to_vectors([0, 90, 180])
    queries = _angles_to_vectors([0, 45, 120])
    # c_ij = cos(angle(key_i) - angle(query_j)):
    s2, s3 = math.sqrt(0.5), math.sqrt(3) / 2
    c = np.array([[1.0, s2, -0.5],
                  [0.0, s2, s3],
                  [-1.0, -s2, 0.5]])
    least = [[-0.5, s2], [0.0, s2], [-1.0, -s2]]  # 2 smallest per row
    most = [[1.0, s2], [s2, s3], [-s2, 0.5]]  # 2 largest per row
    expected = {
        ("least_similar", "log_of_mean"): [math.log(1 + np.mean([1 - x for x in row])) for row in least],
        ("least_similar", "mean_of_log"): [np.mean([math.log(2 - x) for x in row]) for row in least],
        ("most_similar", "log_of_mean"): [math.log(1 + np.mean([1 - x for x in row])) for row in most],
        ("most_similar", "mean_of_log"): [np.mean([math.log(2 - x) for x in row]) for row in most],
    }
    assert expected[("least_similar", "log_of_mean")][0] == pytest.approx(math.log(1 + (1.5 + 1 - s2) / 2))
    cos = F_nn.normalize(keys, dim=-1) @ F_nn.normalize(queries, dim=-1).T
    np.testing.assert_allclose(cos.numpy(), c, atol=1e-12)
    for (neighbours, aggregate), values in expected.items():
        r = contrastive_entropy_reward(keys, queries, k=2, neighbours=neighbours, aggregate=aggregate)
        assert r.shape == (3, 1)
        np.testing.assert_allclose(r[:, 0].numpy(), values, rtol=1e-12, atol=1e-12)
    # k >= N uses every row j, including j = i.
    r_all = contrastive_entropy_reward(keys, queries, k=12)
    np.testing.assert_allclose(r_all[:, 0].numpy(), np.log(1 + (1 - c).mean(1)), rtol=1e-12)


@pytest.mark.parametrize("neighbours", ["least_similar", "most_similar"])
@pytest.mark.parametrize("aggregate", ["log_of_mean", "mean_of_log"])
def test_ce_reward_range(neighbours, aggregate):
    g = torch.Generator().manual_seed(0)
    keys, queries = torch.randn(64, D, generator=g), torch.randn(64, D, generator=g)
    r = contrastive_entropy_reward(keys, queries, 12, neighbours, aggregate)
    assert r.shape == (64, 1)
    assert torch.all(r >= 0) and torch.all(r <= math.log(3) + 1e-6)
    # Extremes: anti-aligned everywhere gives log 3, aligned everywhere gives exactly 0.
    v = torch.randn(1, D, generator=g)
    anti = contrastive_entropy_reward(v.expand(10, D), -v.expand(10, D), 4, neighbours, aggregate)
    torch.testing.assert_close(anti, torch.full((10, 1), math.log(3)), atol=1e-6, rtol=0)
    axis = torch.zeros(10, D)
    axis[:, 2] = torch.arange(1.0, 11.0)  # same direction, different lengths
    aligned = contrastive_entropy_reward(axis, axis.flip(0) * 0.5, 4, neighbours, aggregate)
    assert torch.all(aligned == 0)


def test_ce_reward_non_decreasing_when_one_similarity_is_lowered():
    """Queries e_1..e_N and unit keys with a spare coordinate make c_ij directly settable."""
    n, k = 6, 3
    rng = np.random.default_rng(0)
    queries = torch.eye(n + 1, dtype=torch.float64)[:n]

    def keys_from(c):
        spare = np.sqrt(1 - (c ** 2).sum(1, keepdims=True))
        return torch.tensor(np.concatenate([c, spare], 1))

    for _ in range(100):
        c = rng.uniform(-0.4, 0.4, size=(n, n))
        r0 = contrastive_entropy_reward(keys_from(c), queries, k)[:, 0]
        i, j = rng.integers(n), rng.integers(n)
        c2 = c.copy()
        c2[i, j] -= rng.uniform(0.0, c[i, j] + 0.4)
        r1 = contrastive_entropy_reward(keys_from(c2), queries, k)[:, 0]
        assert r1[i] >= r0[i] - 1e-12
        others = torch.arange(n) != i
        torch.testing.assert_close(r1[others], r0[others], atol=1e-12, rtol=0)
    # A lowered similarity that enters the neighbour set strictly increases the reward.
    c = np.full((n, n), 0.3)
    c2 = c.copy()
    c2[0, 4] = -0.4
    r0 = contrastive_entropy_reward(keys_from(c), queries, k)[0, 0]
    r1 = contrastive_entropy_reward(keys_from(c2), queries, k)[0, 0]
    assert r1 > r0 + 0.1


def test_ce_reward_rejects_unknown_options():
    x = torch.randn(4, 3)
    with pytest.raises(ValueError):
        contrastive_entropy_reward(x, x, neighbours="nearest")
    with pytest.raises(ValueError):
        contrastive_entropy_reward(x, x, aggregate="sum")


# ---------------------------------------------------------------------------------------------
# RND (invariant 25)


def test_rnd_error_and_first_reward_follow_the_formulas():
    torch.manual_seed(0)
    rnd = RNDReward(OBS, H, rep_dim=16)
    obs = 4 * torch.randn(64, OBS) + 10
    normed, target = rnd.prepare(obs)
    # Batch norm without affine parameters (biased variance, eps 1e-5), then clamp to [-5, 5].
    ref = ((obs - obs.mean(0)) / torch.sqrt(obs.var(0, unbiased=False) + 1e-5)).clamp(-5, 5)
    torch.testing.assert_close(normed, ref, atol=1e-5, rtol=1e-5)
    obs[0, 0] = 1e4  # an outlier is clipped
    assert rnd.prepare(obs)[0].abs().max() == 5.0
    error = (rnd.networks.target(normed) - rnd.networks.predictor(normed)).pow(2).mean(-1).detach()
    assert torch.all(error >= 0)
    assert rnd.loss(normed, target).item() == pytest.approx(error.mean().item(), rel=1e-6)
    reward = rnd.reward(normed, target)
    e64 = error.double()
    n0, b = 1e-4, 64
    delta = e64.mean()
    var = (1 * n0 + e64.var() * b + delta ** 2 * n0 * b / (n0 + b)) / (n0 + b)
    torch.testing.assert_close(reward[:, 0].double(), e64 / (var.sqrt() + 1e-8), atol=1e-6, rtol=1e-5)
    assert reward.shape == (64, 1)


def test_rnd_reward_has_unit_running_std_on_stationary_data():
    torch.manual_seed(0)
    rnd = RNDReward(OBS, H, rep_dim=16)
    g = torch.Generator().manual_seed(1)
    late = []
    for step in range(300):
        obs = torch.randn(64, OBS, generator=g) * torch.tensor([1.0, 2.0, 0.5, 3.0, 1.0]) + 1.0
        normed, target = rnd.prepare(obs)
        error = (rnd.networks.target(normed) - rnd.networks.predictor(normed)).pow(2).mean(-1).detach()
        reward = rnd.reward(normed, target)[:, 0]
        # The reward is the error divided by the updated running std; the mean is not subtracted.
        torch.testing.assert_close(reward.double() * (rnd.error_stats.var.sqrt() + 1e-8), error.double(),
                                   atol=1e-6, rtol=1e-5)
        if step >= 200:
            late.append(reward)
    late = torch.cat(late)
    assert late.std().item() == pytest.approx(1.0, abs=0.1)
    assert late.mean().item() > 1.0  # not centred
    assert rnd.error_stats.count.item() == pytest.approx(300 * 64, abs=1e-3)


# ---------------------------------------------------------------------------------------------
# Exploration critic and intrinsic reward (§7.5-§7.7)


def test_exploration_critic_loss_matches_td_reference():
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(), tiny_exploration())
    with torch.no_grad():
        for p in agent.exploration_critic_target.parameters():
            p.add_(0.1 * torch.randn_like(p))
    batch = random_batch(32, future=True)
    z = sample_z_prior(32, D)
    next_action = training_action(agent.actor(batch.next_obs, z), 0.2, 0.3).detach()
    reward = torch.rand(32, 1)
    loss = agent.explorer.critic_loss(agent, batch, z, next_action, reward)
    with torch.no_grad():
        tq = agent.exploration_critic_target(batch.next_obs, z, next_action)
        y = reward + batch.discount * torch.minimum(tq[0], tq[1])
        q = agent.exploration_critic(batch.obs, z, batch.action)
        ref = F_nn.mse_loss(q[0], y) + F_nn.mse_loss(q[1], y)
    torch.testing.assert_close(loss.detach(), ref)
    loss.backward()
    assert all(p.grad is not None for p in agent.exploration_critic.parameters())
    assert all(p.grad is None for p in agent.actor.parameters())


@pytest.mark.parametrize("rnd_input", ["next_obs", "obs"])
def test_intrinsic_reward_uses_the_just_updated_modules(rnd_input):
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(), tiny_exploration(rnd_input=rnd_input, beta=0.7))
    batch = random_batch(32, future=True)
    with torch.no_grad():
        labels = agent.backward_map(batch.next_obs)
    metrics = {}
    reward = agent.explorer.intrinsic_reward(agent, batch, labels, metrics)
    with torch.no_grad():  # recompute from the state after the call
        x = batch.next_obs if rnd_input == "next_obs" else batch.obs
        normed = agent.rnd.networks.normalise(x)
        err = (agent.rnd.networks.target(normed) - agent.rnd.networks.predictor(normed)).pow(2).mean(-1)
        r_rnd = err / (agent.rnd.error_stats.var.sqrt().float() + 1e-8)
        key = agent.contrastive.encoders.key(batch.obs, batch.next_obs)
        query = agent.contrastive.encoders.query(labels)
        r_ce = contrastive_entropy_reward(key, query, k=4)
    torch.testing.assert_close(reward, (r_rnd + 0.7 * r_ce[:, 0]).unsqueeze(-1), atol=1e-5, rtol=1e-5)
    assert {"rnd_loss", "nce_loss", "rnd_reward", "ce_reward", "intrinsic_reward"} <= set(metrics)


def test_dvfb_without_ce_has_no_contrastive_module():
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(), tiny_exploration(use_ce=False))
    assert agent.contrastive is None
    assert "contrastive_optimizer" not in agent.optimizers()
    assert not any(name.startswith("contrastive") for name, _ in agent.named_parameters())
    metrics = agent.update(random_batch(32, future=True))
    assert "nce_loss" not in metrics and "ce_reward" not in metrics
    torch.testing.assert_close(metrics["intrinsic_reward"], metrics["rnd_reward"])
    # beta = 0 keeps the module (trained) but adds no CE term.
    agent0 = DVFBAgent(OBS, ACT, tiny_config(), tiny_exploration(beta=0.0))
    metrics0 = agent0.update(random_batch(32, future=True))
    assert "nce_loss" in metrics0 and "ce_reward" not in metrics0
    torch.testing.assert_close(metrics0["intrinsic_reward"], metrics0["rnd_reward"])


# ---------------------------------------------------------------------------------------------
# Every B input mode runs (invariant 2 for the update path)


@pytest.mark.parametrize("mode", BACKWARD_INPUTS)
@pytest.mark.parametrize("agent_cls", ["fb", "dvfb"])
def test_update_runs_with_finite_losses_in_every_backward_mode(mode, agent_cls):
    torch.manual_seed(0)
    cfg = tiny_config(backward_input=mode)
    agent = FBAgent(OBS, ACT, cfg) if agent_cls == "fb" else DVFBAgent(OBS, ACT, cfg, tiny_exploration())
    for step in range(2):
        metrics = agent.update(random_batch(32, seed=step, future=True))
        assert {"fb_loss", "fb_total", "ortho_loss", "fb_q_loss", "actor_loss"} <= set(metrics)
        if agent_cls == "dvfb":
            assert {"exploration_critic_loss", "rnd_loss", "nce_loss", "intrinsic_reward"} <= set(metrics)
        for name, value in metrics.items():
            assert torch.isfinite(value).all(), (name, value)
            assert not value.requires_grad
    if mode == "code_exact":
        with pytest.raises(ValueError, match="code_exact"):
            agent.update(random_batch(32))
    else:
        agent.update(random_batch(32))  # s'' is not needed


# ---------------------------------------------------------------------------------------------
# Gradient isolation and EMA on a full update (invariants 26, 31)

OWNERS = {
    "rnd_optimizer": ("rnd.networks.predictor.",),
    "contrastive_optimizer": ("contrastive.",),
    "critic_optimizer": ("exploration_critic.",),
    "fb_optimizer": ("forward_map.", "backward_map."),
    "actor_optimizer": ("actor.",),
}
TARGETS = {"forward_target.": "forward_map.", "backward_target.": "backward_map.",
           "exploration_critic_target.": "exploration_critic."}


def _snapshot(agent):
    return {name: p.detach().clone() for name, p in agent.named_parameters()}


def _grads(agent):
    return {name: None if p.grad is None else p.grad.detach().clone() for name, p in agent.named_parameters()}


def _instrument(agent):
    """Record parameters and gradients around every optimiser step (the steps themselves run)."""
    log = []
    for opt_name, opt in agent.optimizers().items():
        original = opt.step

        def step(*args, _name=opt_name, _orig=original, **kwargs):
            before, grads = _snapshot(agent), _grads(agent)
            out = _orig(*args, **kwargs)
            log.append((_name, before, _snapshot(agent), grads))
            return out

        opt.step = step
    return log


def _changed(a, b):
    return {name for name in a if not torch.equal(a[name], b[name])}


@pytest.mark.parametrize("mode", ["state", "code_exact"])
def test_dvfb_update_gradient_isolation_and_ema(mode):
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(backward_input=mode), tiny_exploration(alpha=5.0))
    log = _instrument(agent)
    for update in range(2):
        log.clear()
        start = _snapshot(agent)
        agent.update(random_batch(32, seed=update, future=True))
        end = _snapshot(agent)
        names = [entry[0] for entry in log]
        # §7.2 order: RND, contrastive, Q_P, FB, actor.
        assert names == ["rnd_optimizer", "contrastive_optimizer", "critic_optimizer", "fb_optimizer",
                         "actor_optimizer"]
        previous = start
        for opt_name, before, after, grads in log:
            assert not _changed(previous, before), f"parameters changed outside an optimiser step before {opt_name}"
            changed = _changed(before, after)
            assert changed, opt_name
            assert all(n.startswith(OWNERS[opt_name]) for n in changed), (opt_name, sorted(changed))
            previous = after
            if update == 0:  # fresh agent: no gradients are left over from an earlier update
                if opt_name == "contrastive_optimizer":  # NCE backward does not reach B
                    assert all(grads[n] is None for n in grads if n.startswith("backward_map."))
                if opt_name == "fb_optimizer":  # FB backward does not reach the actor
                    assert all(grads[n] is None for n in grads if n.startswith("actor."))
        grads_at = {entry[0]: entry[3] for entry in log}
        # Q_P's gradients are those of its own TD step: neither the FB nor the actor backward adds to them.
        for n, g in grads_at["critic_optimizer"].items():
            if n.startswith("exploration_critic."):
                assert torch.equal(grads_at["fb_optimizer"][n], g), n
        # The actor's backward adds nothing to the gradients of F and Q_P.
        for n, g in grads_at["actor_optimizer"].items():
            if n.startswith(("forward_map.", "backward_map.")):
                assert torch.equal(g, grads_at["fb_optimizer"][n]), n
            if n.startswith("exploration_critic."):
                assert torch.equal(g, grads_at["critic_optimizer"][n]), n
        # After the last step only the targets move, and exactly by the EMA.
        last = log[-1][2]
        changed = _changed(last, end)
        assert changed and all(n.startswith(tuple(TARGETS)) for n in changed), sorted(changed)
        for n in end:
            for tprefix, oprefix in TARGETS.items():
                if n.startswith(tprefix):
                    online = end[oprefix + n[len(tprefix):]]
                    expected = TAU * online.double() + (1 - TAU) * last[n].double()
                    torch.testing.assert_close(end[n].double(), expected, atol=1e-7, rtol=1e-6)
        # The RND target never changes.
        for n in start:
            if n.startswith("rnd.networks.target."):
                assert torch.equal(start[n], end[n])


def test_targets_equal_online_nets_after_construction():
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(), tiny_exploration())
    params = _snapshot(agent)
    for n in params:
        for tprefix, oprefix in TARGETS.items():
            if n.startswith(tprefix):
                assert torch.equal(params[n], params[oprefix + n[len(tprefix):]])


def test_fb_agent_update_steps_only_fb_then_actor():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    log = _instrument(agent)
    agent.update(random_batch(32, future=True))
    assert [entry[0] for entry in log] == ["fb_optimizer", "actor_optimizer"]
    for opt_name, before, after, _ in log:
        changed = _changed(before, after)
        assert changed and all(n.startswith(OWNERS[opt_name]) for n in changed)


def test_rnd_target_unchanged_over_many_updates_and_predictor_learns():
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(lr=1e-3), tiny_exploration())
    target = {n: p.clone() for n, p in agent.rnd.networks.target.named_parameters()}
    batch = random_batch(64, seed=3, future=True)
    losses = [agent.update(batch)["rnd_loss"].item() for _ in range(30)]
    for n, p in agent.rnd.networks.target.named_parameters():
        assert torch.equal(p, target[n])
    assert losses[-1] < 0.7 * losses[0]
