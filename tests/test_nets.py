"""Tests for dvfb.nets: shapes, ranges, the z geometry, the policy distribution, initialisation,
EMA targets and running statistics (docs/methods.md §3, §4, §5; §13 invariants 1-9, 18, 26)."""

import math

import numpy as np
import pytest
import torch
from scipy import stats
from torch import nn

from dvfb.agents.fb import BACKWARD_INPUTS, FBAgent
from dvfb.rewards.contrastive import ContrastiveEncoders
from dvfb.rewards.rnd import RNDNetworks
from dvfb.nets import (
    ACTION_EPS,
    Actor,
    BackwardMap,
    ForwardMap,
    HostActor,
    RunningMeanStd,
    TwinCritic,
    TwinHead,
    make_target,
    orthogonal_init_,
    project_to_sphere,
    rollout_action,
    sample_z_prior,
    skill_values,
    soft_update_,
    training_action,
)
from tiny import ACT, D, E, H, OBS, random_batch, tiny_config


# ---------------------------------------------------------------------------------------------
# Shapes and ranges (invariants 1, 2)


@pytest.mark.parametrize("arch", ["two_stream", "mlp"])
def test_actor_mean_shape_and_open_range(arch):
    torch.manual_seed(0)
    actor = Actor(OBS, D, ACT, H, E, arch)
    obs, z = 3 * torch.randn(64, OBS), sample_z_prior(64, D)
    mu = actor(obs, z)
    assert mu.shape == (64, ACT)
    assert torch.all(mu > -1) and torch.all(mu < 1)


def test_network_output_shapes():
    torch.manual_seed(0)
    n = 17
    obs, action, z = torch.randn(n, OBS), torch.rand(n, ACT) * 2 - 1, sample_z_prior(n, D)
    forward = ForwardMap(OBS, ACT, D, H, E)
    out = forward(obs, action, z)
    assert out.shape == (2, n, D)  # two (N, d) heads
    assert skill_values(out, z).shape == (2, n)
    assert torch.allclose(skill_values(out, z), torch.einsum("knd,nd->kn", out, z))
    backward = BackwardMap(OBS, H, D)
    assert backward(obs).shape == (n, D)
    critic = TwinCritic(OBS, ACT, D, H)
    assert critic(obs, z, action).shape == (2, n, 1)
    rnd = RNDNetworks(OBS, H, rep_dim=16)
    normed = rnd.normalise(obs)
    assert normed.shape == (n, OBS) and normed.abs().max() <= 5.0
    err = RNDNetworks.error(rnd.predictor(normed), rnd.target(normed))
    assert err.shape == (n,) and torch.all(err >= 0)
    enc = ContrastiveEncoders(OBS, D, H)
    assert enc.key(obs, obs).shape == (n, D) and enc.query(z).shape == (n, D)


def test_twin_critic_input_order_is_s_z_a():
    """§4.4: the trunk reads [s, z, a] in that order."""
    torch.manual_seed(0)
    critic = TwinCritic(OBS, ACT, D, H)
    obs, z, a = torch.randn(4, OBS), sample_z_prior(4, D), torch.rand(4, ACT)
    lin = critic.trunk[0]
    expected = critic.trunk[2](critic.trunk[1](torch.cat([obs, z, a], -1) @ lin.weight.T + lin.bias))
    assert torch.allclose(critic.heads(expected), critic(obs, z, a))


@pytest.mark.parametrize("mode", BACKWARD_INPUTS)
def test_backward_norm_is_sqrt_d_in_every_input_mode(mode):
    torch.manual_seed(1)
    agent = FBAgent(OBS, ACT, tiny_config(backward_input=mode))
    batch = random_batch(64, step=0.1, future=True)
    # Scale the inputs over several orders of magnitude, and include a constant input.
    batch.obs[:8] *= 1e3
    batch.next_obs[8:16] *= 1e-3
    batch.future_obs[16:24] = 0.0
    online_in, target_in = agent.backward_inputs(batch)
    expected_in = OBS if mode == "state" else 2 * OBS
    assert online_in.shape[-1] == expected_in and target_in.shape[-1] == expected_in
    for values in (agent.backward_map(online_in), agent.backward_target(target_in),
                   agent.model.backward_features(batch.obs, batch.next_obs)):
        assert values.shape == (64, D)
        torch.testing.assert_close(values.norm(dim=-1), torch.full((64,), math.sqrt(D)), atol=1e-5, rtol=0)


def test_project_to_sphere_radius_direction_and_zero_floor():
    v = torch.randn(100, 7, dtype=torch.float64) * torch.logspace(-6, 6, 100, dtype=torch.float64)[:, None]
    p = project_to_sphere(v)
    torch.testing.assert_close(p.norm(dim=-1), torch.full((100,), math.sqrt(7), dtype=torch.float64))
    cos = (p * v).sum(-1) / (p.norm(dim=-1) * v.norm(dim=-1))
    torch.testing.assert_close(cos, torch.ones(100, dtype=torch.float64))
    zero = project_to_sphere(torch.zeros(2, 7))
    assert torch.all(torch.isfinite(zero)) and torch.all(zero == 0)


# ---------------------------------------------------------------------------------------------
# z prior and mixing (invariants 3, 4, 5)


def test_prior_draws_are_on_the_sphere():
    torch.manual_seed(0)
    z = sample_z_prior(1000, 50)
    torch.testing.assert_close(z.norm(dim=-1), torch.full((1000,), math.sqrt(50)), atol=1e-5, rtol=0)


def test_prior_moments_for_1e5_draws():
    """mean(z) ~ 0 and E[z z^T] ~ I_d (since E[zz^T] = ||z||^2/d I = I)."""
    d, n = 50, 100_000
    z = sample_z_prior(n, d, generator=torch.Generator().manual_seed(123)).double()
    mean = z.mean(0)
    second = z.T @ z / n
    # Per-coordinate standard error 1/sqrt(n) = 0.0032; allow ~6 SE for the max over 50 coords.
    assert mean.abs().max() < 0.02
    assert (second - torch.eye(d, dtype=torch.float64)).abs().max() < 0.03
    assert abs(torch.trace(second).item() - d) < 1e-3  # exactly d up to float rounding
    # Isotropy: not concentrated on the axes (a sign-only or one-hot prior would fail this).
    assert abs(z.abs().max(dim=1).values.mean().item() - math.sqrt(d)) > 1.0


def _goal_index(z_row, goals, atol=1e-5):
    dist = (goals - z_row).norm(dim=-1)
    j = int(dist.argmin())
    return j if dist[j] < atol else None


@pytest.mark.parametrize("mode", BACKWARD_INPUTS)
def test_training_z_mixing_rows_are_goals_or_the_original_prior_draws(mode):
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(backward_input=mode))
    batch = random_batch(48, seed=3, step=0.1, future=True)
    n = 48
    with torch.no_grad():
        if mode == "state":
            goal_inputs = batch.obs
        elif mode == "transition":
            goal_inputs = torch.cat([batch.obs, batch.next_obs], -1)
        else:  # code_exact: B(s_i, s_perm(i)); the candidates of row i are B(s_i, s_j) for every j
            goal_inputs = torch.cat([batch.obs[:, None].expand(n, n, OBS),
                                     batch.obs[None, :].expand(n, n, OBS)], -1).reshape(n * n, -1)
        goals = project_to_sphere(agent.backward_map(goal_inputs))
        if mode == "code_exact":
            goals = goals.reshape(n, n, D)
    replaced_total = same_row_total = 0
    for seed in range(30):
        torch.manual_seed(seed)
        prior = sample_z_prior(n, D)  # the first draw training_z makes is the prior batch
        torch.manual_seed(seed)
        z = agent.training_z(batch)
        torch.testing.assert_close(z.norm(dim=-1), torch.full((n,), math.sqrt(D)), atol=1e-5, rtol=0)
        used, replaced_rows = [], []
        for i in range(n):
            j = _goal_index(z[i], goals[i] if mode == "code_exact" else goals)
            if j is None:
                assert torch.equal(z[i], prior[i]), f"row {i} is neither a goal nor the prior draw"
            else:
                used.append(j)
                replaced_rows.append(i)
        # Replaced rows come from a permutation: each replay row is used at most once.
        assert len(used) == len(set(used))
        replaced_total += len(used)
        if mode != "code_exact":
            same_row_total += sum(j == i for i, j in zip(replaced_rows, used))
    # Binomial test on 30 * 48 = 1440 rows with p = 0.5: sd = 19; allow 4 sd.
    total = 30 * n
    assert abs(replaced_total - 0.5 * total) < 4 * math.sqrt(total * 0.25)
    # The goal rows are shuffled: row i gets B of a random replay row, rarely its own (p = 1/n).
    assert same_row_total < 0.1 * replaced_total


@pytest.mark.parametrize("ratio", [0.0, 0.2, 1.0])
def test_training_z_mix_ratio(ratio):
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(mix_ratio=ratio))
    batch = random_batch(64, seed=5, step=0.1, future=True)
    with torch.no_grad():
        goals = project_to_sphere(agent.backward_map(batch.obs))
    replaced = 0
    trials = 20
    for seed in range(trials):
        torch.manual_seed(100 + seed)
        z = agent.training_z(batch)
        replaced += sum(_goal_index(row, goals) is not None for row in z)
    total = trials * 64
    assert abs(replaced - ratio * total) <= 4 * math.sqrt(total * ratio * (1 - ratio)) + 1e-9


# ---------------------------------------------------------------------------------------------
# Policy distribution (invariants 6-9)


def _means_near_the_bounds(n=4000):
    torch.manual_seed(0)
    raw = torch.randn(n, ACT) * 5
    mu = torch.tanh(raw)
    mu[:3] = torch.tensor([1.0, -1.0, 0.0])  # saturated means included
    return mu


def test_rollout_action_range_and_unclipped_noise():
    mu = _means_near_the_bounds()
    torch.manual_seed(1)
    a = rollout_action(mu, 0.2)
    assert torch.all(a >= -1 + ACTION_EPS) and torch.all(a <= 1 - ACTION_EPS)
    # The noise is not clipped at 0.3: among central means, some deviations exceed it.
    central = mu.abs() < 0.2
    assert ((a - mu).abs()[central] > 0.35).any()
    big = rollout_action(mu, 5.0)
    assert torch.all(big >= -1 + ACTION_EPS) and torch.all(big <= 1 - ACTION_EPS)


def test_training_action_clip_range_and_straight_through_gradient():
    mu = _means_near_the_bounds().requires_grad_(True)
    torch.manual_seed(2)
    a = training_action(mu, 0.2, 0.3)
    assert torch.all(a >= -1 + ACTION_EPS) and torch.all(a <= 1 - ACTION_EPS)
    dev = (a - mu).abs()
    assert torch.all(dev <= 0.3 + 1e-6)
    assert (dev > 0.3 - 1e-6).any()  # the clip is active for some samples
    clamped = (a.detach().abs() >= 1 - ACTION_EPS)
    assert clamped.sum() > 10
    weights = torch.randn_like(mu)
    (a * weights).sum().backward()
    torch.testing.assert_close(mu.grad, weights, atol=0, rtol=0)  # d a / d mu = 1, even if clamped
    # Large std: the clip bounds the deviation regardless of sigma.
    a2 = training_action(mu.detach(), 10.0, 0.3)
    assert torch.all((a2 - mu.detach()).abs() <= 0.3 + 1e-6)


def test_training_action_noise_is_reparameterised():
    mu = torch.zeros(1000, ACT)
    torch.manual_seed(3)
    a = training_action(mu, 0.2, 0.3)
    torch.manual_seed(3)
    b = training_action(mu + 0.1, 0.2, 0.3)
    torch.testing.assert_close(b - a, torch.full_like(a, 0.1))  # same noise, shifted mean
    # Noise is N(0, 0.2^2) clipped at +-0.3 = 1.5 sigma: std = 0.2 * sqrt(E[min(X^2, 1.5^2)]).
    c = 1.5
    tail = 2 * stats.norm.sf(c)
    clipped_var = (1 - tail) - 2 * c * stats.norm.pdf(c) + c ** 2 * tail
    assert a.std().item() == pytest.approx(0.2 * math.sqrt(clipped_var), rel=0.03)
    assert (a.abs() == 0.3).float().mean().item() == pytest.approx(tail, abs=0.03)


def test_mean_action_is_deterministic_and_rollout_is_stochastic():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    obs, z = np.random.default_rng(0).standard_normal((1, OBS)).astype(np.float32), agent.sample_skill(1)
    a1, a2 = agent.act(obs, z, explore=False), agent.act(obs, z, explore=False)
    assert np.array_equal(a1, a2) and a1.shape == (1, ACT)
    with torch.no_grad():
        mu = agent.actor(torch.as_tensor(obs), z).numpy()
    np.testing.assert_allclose(a1, mu, rtol=0, atol=1e-6)  # numpy acting path vs the torch module
    e1, e2 = agent.act(obs, z, explore=True), agent.act(obs, z, explore=True)
    assert not np.array_equal(e1, e2)
    assert np.all(np.abs(e1) <= 1 - ACTION_EPS)


# ---------------------------------------------------------------------------------------------
# HostActor: the numpy acting path


def _actor_inputs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((n, OBS)).astype(np.float32) * 3,
            rng.standard_normal((n, D)).astype(np.float32))


@pytest.mark.parametrize("arch", ["two_stream", "mlp"])
def test_host_actor_equals_the_torch_actor(arch):
    torch.manual_seed(0)
    actor = Actor(OBS, D, ACT, H, E, arch)
    obs, z = _actor_inputs(20)
    with torch.no_grad():
        expected = actor(torch.as_tensor(obs), torch.as_tensor(z)).numpy()
    host = HostActor(actor)
    got = np.stack([host(o, zz) for o, zz in zip(obs, z)])
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-6)
    assert np.abs(got).max() > 0.05  # a real function of the input, not a constant


def test_host_actor_follows_optimiser_steps_and_loaded_weights():
    torch.manual_seed(0)
    actor = Actor(OBS, D, ACT, H, E)
    host = HostActor(actor)
    obs, z = _actor_inputs(4)
    before = host(obs[0], z[0]).copy()
    optimizer = torch.optim.Adam(actor.parameters(), lr=1e-2, fused=True)
    for _ in range(3):
        optimizer.zero_grad()
        actor(torch.as_tensor(obs), torch.as_tensor(z)).sum().backward()
        optimizer.step()
    after = host(obs[0], z[0])
    with torch.no_grad():
        expected = actor(torch.as_tensor(obs[:1]), torch.as_tensor(z[:1]))[0].numpy()
    assert not np.allclose(after, before)
    np.testing.assert_allclose(after, expected, rtol=0, atol=2e-6)
    other = Actor(OBS, D, ACT, H, E)
    actor.load_state_dict(other.state_dict())
    with torch.no_grad():
        expected = other(torch.as_tensor(obs[:1]), torch.as_tensor(z[:1]))[0].numpy()
    np.testing.assert_allclose(host(obs[0], z[0]), expected, rtol=0, atol=2e-6)


def test_host_actor_rebinds_when_a_parameter_storage_is_replaced():
    torch.manual_seed(0)
    actor = Actor(OBS, D, ACT, H, E)
    host = HostActor(actor)
    obs, z = _actor_inputs(1)
    host(obs[0], z[0])
    head_out = actor.head[-1]
    head_out.bias.data = head_out.bias.data + 0.5  # a new tensor, not an in-place write
    with torch.no_grad():
        expected = actor(torch.as_tensor(obs), torch.as_tensor(z))[0].numpy()
    np.testing.assert_allclose(host(obs[0], z[0]), expected, rtol=0, atol=2e-6)


def test_act_follows_a_replaced_actor_module():
    model = FBAgent(OBS, ACT, tiny_config()).model
    obs, z = _actor_inputs(1)
    model.act(obs, torch.as_tensor(z), explore=False)
    torch.manual_seed(7)
    model.actor = Actor(OBS, D, ACT, H, E)
    with torch.no_grad():
        expected = model.actor(torch.as_tensor(obs), torch.as_tensor(z)).numpy()
    np.testing.assert_allclose(model.act(obs, torch.as_tensor(z), explore=False), expected, rtol=0, atol=2e-6)
    assert model._hosts[0].actor is model.actor  # the numpy path ran


def test_host_actor_rejects_non_float32_actors():
    with pytest.raises(ValueError, match="float32 actor on the CPU"):
        HostActor(Actor(OBS, D, ACT, H, E).double())


def test_act_noise_comes_from_torch_generator_like_the_torch_path():
    model = FBAgent(OBS, ACT, tiny_config()).model
    obs, z = _actor_inputs(1)
    z_t = torch.as_tensor(z)
    torch.manual_seed(123)
    host_actions = [model.act(obs, z_t, explore=True) for _ in range(3)]
    torch.manual_seed(123)
    torch_actions = [model._act_torch(obs, z_t, explore=True) for _ in range(3)]
    np.testing.assert_allclose(np.stack(host_actions), np.stack(torch_actions), rtol=0, atol=2e-6)


# ---------------------------------------------------------------------------------------------
# TwinHead


def _separate_heads(head: TwinHead):
    """K nn.Sequential(Linear, ReLU, Linear) built from the TwinHead's weights."""
    hd = head.hidden_dim
    members = []
    for k in range(head.num_heads):
        l1, l2 = nn.Linear(head.in_dim, hd), nn.Linear(hd, head.out_dim)
        with torch.no_grad():
            l1.weight.copy_(head.first.weight[k * hd:(k + 1) * hd])
            l1.bias.copy_(head.first.bias[k * hd:(k + 1) * hd])
            l2.weight.copy_(head.second_weight[k].T)
            l2.bias.copy_(head.second_bias[k, 0])
        members.append(nn.Sequential(l1, nn.ReLU(), l2))
    return members


@pytest.mark.parametrize("num_heads,out", [(2, 5), (3, 1)])
def test_twin_head_equals_separate_heads(num_heads, out):
    torch.manual_seed(0)
    head = TwinHead(12, 20, out, num_heads)
    with torch.no_grad():  # non-zero biases so the bias paths are exercised
        head.first.bias.normal_()
        head.second_bias.normal_()
    members = _separate_heads(head)
    x = torch.randn(9, 12)
    y = head(x)
    assert y.shape == (num_heads, 9, out)
    for k, m in enumerate(members):
        torch.testing.assert_close(y[k], m(x), atol=1e-6, rtol=1e-5)
    # Gradients also match those of the separate heads.
    w = torch.randn_like(y)
    (y * w).sum().backward()
    for k, m in enumerate(members):
        (m(x) * w[k]).sum().backward()
        hd = head.hidden_dim
        torch.testing.assert_close(head.first.weight.grad[k * hd:(k + 1) * hd], m[0].weight.grad,
                                   atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(head.second_weight.grad[k], m[2].weight.grad.T, atol=1e-5, rtol=1e-5)


def test_twin_head_members_are_independent():
    torch.manual_seed(0)
    head = TwinHead(6, 10, 3)
    x = torch.randn(5, 6)
    before = head(x).detach()
    with torch.no_grad():
        head.first.weight[10:] += 1.0
        head.second_weight[1] += 1.0
    after = head(x).detach()
    assert torch.equal(after[0], before[0])
    assert not torch.allclose(after[1], before[1])
    # The two heads start different (independent initialisation).
    assert not torch.allclose(head.first.weight[:10], head.first.weight[10:])


# ---------------------------------------------------------------------------------------------
# Initialisation and targets (§3.2, invariant 26)


def _assert_orthogonal(w: torch.Tensor, what: str):
    w = w.detach().double()
    if w.shape[0] <= w.shape[1]:  # square or wide: orthonormal rows
        gram, eye = w @ w.T, torch.eye(w.shape[0], dtype=torch.float64)
    else:  # tall: orthonormal columns
        gram, eye = w.T @ w, torch.eye(w.shape[1], dtype=torch.float64)
    assert (gram - eye).abs().max() < 1e-5, what


def _all_networks():
    torch.manual_seed(0)
    return {
        "actor": Actor(OBS, D, ACT, H, E),
        "actor_mlp": Actor(OBS, D, ACT, H, E, arch="mlp"),
        "forward": ForwardMap(OBS, ACT, D, H, E),  # heads: in 2E = 32 = H (square blocks)
        "backward": BackwardMap(OBS, H, D),
        "critic": TwinCritic(OBS, ACT, D, H),
        "rnd": RNDNetworks(OBS, H, rep_dim=16),
        "contrastive": ContrastiveEncoders(OBS, D, H),
    }


@pytest.mark.parametrize("name", list(_all_networks()))
def test_orthogonal_init_of_every_layer(name):
    net = _all_networks()[name]
    twin_first = set()
    for mod_name, sub in net.named_modules():
        if isinstance(sub, TwinHead):
            twin_first.add(id(sub.first))
            hd = sub.hidden_dim
            for k in range(sub.num_heads):
                # Each member is orthogonal by itself, as K separate Linear layers would be.
                _assert_orthogonal(sub.first.weight[k * hd:(k + 1) * hd], f"{mod_name} head {k} layer 1")
                _assert_orthogonal(sub.second_weight[k].T, f"{mod_name} head {k} layer 2")
            assert torch.all(sub.first.bias == 0) and torch.all(sub.second_bias == 0)
    n_linear = 0
    for mod_name, sub in net.named_modules():
        if isinstance(sub, nn.Linear) and id(sub) not in twin_first:
            _assert_orthogonal(sub.weight, mod_name)
            assert torch.all(sub.bias == 0), mod_name
            n_linear += 1
        elif isinstance(sub, nn.LayerNorm):
            assert torch.all(sub.weight == 1) and torch.all(sub.bias == 0)
    assert n_linear > 0


def test_orthogonal_init_reinitialises_perturbed_module():
    torch.manual_seed(0)
    net = ForwardMap(OBS, ACT, D, H, E)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(1.0)
    orthogonal_init_(net)
    hd = net.heads.hidden_dim
    for k in range(2):
        _assert_orthogonal(net.heads.first.weight[k * hd:(k + 1) * hd], f"head {k}")
    _assert_orthogonal(net.encoder.first[0].weight, "stream 1")
    assert torch.all(net.heads.first.bias == 0)


def test_rnd_target_is_independent_and_frozen():
    torch.manual_seed(0)
    rnd = RNDNetworks(OBS, H, rep_dim=16)
    assert all(not p.requires_grad for p in rnd.target.parameters())
    assert all(p.requires_grad for p in rnd.predictor.parameters())
    for p, q in zip(rnd.predictor.parameters(), rnd.target.parameters()):
        if p.dim() == 2:
            assert not torch.allclose(p, q)


def test_make_target_exact_copy_without_grad():
    torch.manual_seed(0)
    online = ForwardMap(OBS, ACT, D, H, E)
    target = make_target(online)
    for (n1, p), (n2, q) in zip(online.named_parameters(), target.named_parameters()):
        assert n1 == n2 and torch.equal(p, q)
        assert p.requires_grad and not q.requires_grad
        assert p.data_ptr() != q.data_ptr()
    x = (torch.randn(4, OBS), torch.rand(4, ACT), sample_z_prior(4, D))
    assert torch.equal(online(*x), target(*x))


def test_soft_update_one_step_is_exact_ema():
    torch.manual_seed(0)
    online = TwinCritic(OBS, ACT, D, H)
    target = make_target(online)
    with torch.no_grad():
        for p in target.parameters():
            p.add_(torch.randn_like(p))
    old = [q.detach().double().clone() for q in target.parameters()]
    tau = 0.01
    soft_update_(target, online, tau)
    for q_new, q_old, p in zip(target.parameters(), old, online.parameters()):
        expected = tau * p.double() + (1 - tau) * q_old
        torch.testing.assert_close(q_new.double(), expected, atol=1e-6, rtol=1e-6)
        assert not q_new.requires_grad


def test_soft_update_decay_with_frozen_online_net():
    torch.manual_seed(0)
    online = BackwardMap(OBS, H, D)
    target = make_target(online)
    with torch.no_grad():
        for p in online.parameters():
            p.add_(torch.randn_like(p))
    diff0 = [(p - q).double() for p, q in zip(online.parameters(), target.parameters())]
    snapshot = [p.detach().clone() for p in online.parameters()]
    tau = 0.05
    for k in range(1, 41):
        soft_update_(target, online, tau)
        if k in (1, 10, 40):
            for p, q, d0 in zip(online.parameters(), target.parameters(), diff0):
                torch.testing.assert_close((p - q).double(), (1 - tau) ** k * d0, atol=1e-5, rtol=1e-4)
    for p, s in zip(online.parameters(), snapshot):
        assert torch.equal(p, s)  # the online net is untouched by the EMA


# ---------------------------------------------------------------------------------------------
# Running mean / variance (§3.4, invariant 18)


def test_running_mean_std_first_update_follows_the_formula():
    rms = RunningMeanStd()
    x = torch.tensor([1.0, 2.0, 4.0, 7.0])
    mean, var = rms.update(x)
    n, b = 1e-4, 4
    xm, xv = 3.5, np.var([1, 2, 4, 7], ddof=1)
    exp_mean = 0 + xm * b / (n + b)
    exp_var = (1 * n + xv * b + xm ** 2 * n * b / (n + b)) / (n + b)
    assert mean.item() == pytest.approx(exp_mean, rel=1e-12)
    assert var.item() == pytest.approx(exp_var, rel=1e-12)
    assert rms.count.item() == pytest.approx(4.0001, rel=1e-12)
    assert mean is rms.mean and var is rms.var  # returns the updated statistics


def test_running_mean_std_matches_pooled_numpy_statistics():
    rng = np.random.default_rng(0)
    rms = RunningMeanStd()
    batches = [rng.normal(3.0 + i, 0.5 + 0.3 * i, size=size) for i, size in
               enumerate([64, 1, 7, 128, 33, 2, 500])]
    # Replay the §3.4 recurrence in numpy float64 for an exact comparison.
    m, s, c = 0.0, 1.0, 1e-4
    for x in batches:
        mean, var = rms.update(torch.as_tensor(x, dtype=torch.float32))
        x32 = x.astype(np.float32).astype(np.float64)
        b = len(x32)
        vb = x32.var(ddof=1) if b > 1 else 0.0
        delta = x32.mean() - m
        m, s, c = m + delta * b / (c + b), (s * c + vb * b + delta ** 2 * c * b / (c + b)) / (c + b), c + b
        assert mean.item() == pytest.approx(m, rel=1e-12)
        assert var.item() == pytest.approx(s, rel=1e-12)
    # Pooled statistics: overall mean, and the pooled variance where each batch contributes its
    # Bessel-corrected variance plus its between-batch term.
    allx = np.concatenate([x.astype(np.float32).astype(np.float64) for x in batches])
    total = len(allx)
    pooled_mean = allx.mean()
    within = sum(len(x) * (np.var(x.astype(np.float32).astype(np.float64), ddof=1) if len(x) > 1 else 0.0)
                 for x in batches)
    between = sum(len(x) * (x.astype(np.float32).astype(np.float64).mean() - pooled_mean) ** 2 for x in batches)
    pooled_var = (within + between) / total
    assert rms.mean.item() == pytest.approx(pooled_mean, rel=1e-4 / total * 10)
    assert rms.var.item() == pytest.approx(pooled_var, rel=1e-4 * (1 + pooled_mean ** 2) / total * 10)
    assert rms.count.item() == pytest.approx(total + 1e-4, rel=1e-12)
