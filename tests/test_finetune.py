"""Tests for dvfb.protocols.dual_value: reward mapping, the task critic Q_F, the dual-value actor and the
freezing of F, B and z_r (docs/methods.md §9; §13 invariants 15-17 and 27).

To feed the mapping a constant implicit reward (invariant 15) the tests use a batch whose rows are
all the same transition: then every B_i is the same b, Cov = b b^T is singular, and with
``cov_ridge = lambda`` the implicit reward of ``z = kappa * b`` is ``kappa * d / (d + lambda)`` for
every row, exactly. That drives the real ``mapped_reward`` path without patching anything.
"""

import copy
import math

import pytest
import torch

from dvfb.agents.dvfb import DVFBAgent, ExplorationConfig
from dvfb.agents.fb import FBAgent, FBConfig
from dvfb.protocols.zeroshot import InferenceConfig
from dvfb.protocols.dual_value import DualValueFinetuner, FinetuneConfig
from dvfb.nets import RunningMeanStd, project_to_sphere
from dvfb.data import Batch
from tiny import random_batch


OBS, ACT, D, H, E = 5, 3, 8, 32, 16
RIDGE = 1.0


def tiny_config(**overrides) -> FBConfig:
    kw = dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32)
    kw.update(overrides)
    return FBConfig(**kw)


def make_agent(kind="dvfb", **overrides):
    torch.manual_seed(0)
    if kind == "fb":
        return FBAgent(OBS, ACT, tiny_config(**overrides))
    return DVFBAgent(OBS, ACT, tiny_config(**overrides),
                     ExplorationConfig(rnd_rep_dim=16, contrastive_hidden_dim=32, ce_k=4))


def constant_batch(n: int, reward: float, dtype=torch.float32) -> Batch:
    """n copies of one transition: B_i = b for every row."""
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(1, OBS, generator=g, dtype=dtype).expand(n, -1).clone()
    next_obs = torch.randn(1, OBS, generator=g, dtype=dtype).expand(n, -1).clone()
    action = torch.zeros(n, ACT, dtype=dtype)
    return Batch(obs, action, torch.full((n, 1), reward, dtype=dtype), torch.full((n, 1), 0.99, dtype=dtype),
                 next_obs, None, None)


def z_for_constant_implicit(agent, batch, c_fb):
    """z = kappa * b with b = B(s'), so that B_i (Cov + lambda I)^-1 z = c_fb for every row."""
    with torch.no_grad():
        b = agent.model.backward_features(batch.obs[:1], batch.next_obs[:1])[0]
    kappa = c_fb * (D + RIDGE) / D  # |b|^2 = d
    return kappa * b


# ---------------------------------------------------------------------------------------------
# Reward mapping (invariants 15-17)


def test_constant_inputs_map_to_the_implicit_reward():
    agent = make_agent()
    batch = constant_batch(64, 0.25)
    finetuner = DualValueFinetuner(agent.model, z_for_constant_implicit(agent, batch, 3.7),
                                   FinetuneConfig(cov_ridge=RIDGE))
    for _ in range(3):  # from the first update on
        metrics = {}
        mapped = finetuner.mapped_reward(batch, metrics)
        assert mapped.shape == (64, 1)
        torch.testing.assert_close(mapped, torch.full((64, 1), 3.7), rtol=2e-6, atol=0)
    # Both running means carry the same (1 - 1e-4/N) prior bias.
    n_total = 3 * 64
    assert finetuner.task_reward_stats.mean.item() == pytest.approx(0.25 * n_total / (n_total + 1e-4), rel=1e-12)
    assert finetuner.implicit_reward_stats.mean.item() == pytest.approx(3.7 * n_total / (n_total + 1e-4), rel=1e-6)
    assert {"implicit_reward_mean", "task_reward_mean", "mapped_reward"} <= set(metrics)


def test_constant_inputs_example_in_float64():
    """c_fb = 3.7, c_t = 0.25 gives 3.69999985: only the +1e-8 remains (float64 to resolve it)."""
    agent = make_agent()
    agent.backward_map.double()
    batch = constant_batch(1024, 0.25, dtype=torch.float64)
    z = z_for_constant_implicit(agent, batch, 3.7)
    assert z.dtype == torch.float64
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig(cov_ridge=RIDGE))
    mapped = finetuner.mapped_reward(batch, {})
    assert mapped.dtype == torch.float64
    assert torch.all((mapped - 3.69999985).abs() < 5e-9)
    assert torch.all((mapped - 3.7).abs() > 1e-7)


def test_mapping_epsilon_is_visible_for_tiny_task_rewards():
    """r_f = c_fb * c_t / (c_t + 1e-8) (the prior-count factors cancel): a 1 % shortfall at c_t = 1e-6."""
    agent = make_agent()
    batch = constant_batch(64, 1e-6)
    z = z_for_constant_implicit(agent, batch, 2.0)
    k = 64 / (64 + 1e-4)
    expected = 2.0 * 1e-6 * k / (1e-6 * k + 1e-8)
    mapped = DualValueFinetuner(agent.model, z, FinetuneConfig(cov_ridge=RIDGE)).mapped_reward(batch, {})
    torch.testing.assert_close(mapped, torch.full((64, 1), expected), rtol=1e-5, atol=0)
    no_eps = DualValueFinetuner(agent.model, z, FinetuneConfig(cov_ridge=RIDGE, reward_map_eps=0.0))
    torch.testing.assert_close(no_eps.mapped_reward(batch, {}), torch.full((64, 1), 2.0), rtol=1e-5, atol=0)


def test_mapping_matches_reference_on_a_random_batch():
    agent = make_agent()
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(2)))
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig())
    rms_fb, rms_t = RunningMeanStd(), RunningMeanStd()
    for seed in range(3):
        batch = random_batch(64, seed=seed, reward="positive")
        mapped = finetuner.mapped_reward(batch, {})
        with torch.no_grad():
            b = agent.backward_map(batch.next_obs).double()  # state mode: B(s')
            r_imp = b @ torch.linalg.solve(b.T @ b / 64, z.double())
        mu_fb, _ = rms_fb.update(r_imp)
        mu_t, _ = rms_t.update(batch.reward)
        expected = batch.reward.double() * mu_fb / (mu_t + 1e-8)
        torch.testing.assert_close(mapped.double(), expected, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("k", [10.0, 0.01])
def test_mapping_is_invariant_to_task_reward_scale(k):
    agent = make_agent()
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(3)))
    base = DualValueFinetuner(agent.model, z, FinetuneConfig())
    scaled = DualValueFinetuner(agent.model, z, FinetuneConfig())
    for seed in range(4):
        batch = random_batch(64, seed=seed, reward="positive")
        batch_k = random_batch(64, seed=seed, reward=k * batch.reward)
        torch.testing.assert_close(scaled.mapped_reward(batch_k, {}), base.mapped_reward(batch, {}),
                                   rtol=1e-5, atol=1e-7)


def test_all_zero_task_rewards_map_to_zero():
    agent = make_agent()
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(4)))
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig())
    for seed in range(3):
        batch = random_batch(32, seed=seed, reward=torch.zeros(32, 1))
        mapped = finetuner.mapped_reward(batch, {})
        assert torch.all(mapped == 0) and torch.all(torch.isfinite(mapped))
        metrics = finetuner.update(batch)
        assert all(torch.isfinite(v).all() for v in metrics.values())


def test_mapping_options_abs_and_clip():
    agent = make_agent()
    batch = constant_batch(64, 0.5)
    z = z_for_constant_implicit(agent, batch, -3.0)  # negative implicit mean flips the sign
    plain = DualValueFinetuner(agent.model, z, FinetuneConfig(cov_ridge=RIDGE)).mapped_reward(batch, {})
    torch.testing.assert_close(plain, torch.full((64, 1), -3.0), rtol=1e-5, atol=0)
    absolute = DualValueFinetuner(agent.model, z, FinetuneConfig(cov_ridge=RIDGE, reward_map_abs=True))
    torch.testing.assert_close(absolute.mapped_reward(batch, {}), torch.full((64, 1), 3.0), rtol=1e-5, atol=0)
    clipped = DualValueFinetuner(agent.model, z, FinetuneConfig(cov_ridge=RIDGE, reward_map_clip=1.5))
    torch.testing.assert_close(clipped.mapped_reward(batch, {}), torch.full((64, 1), -1.5))


def test_without_mapping_the_task_reward_is_used_unchanged():
    agent = make_agent()
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(5)))
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig(reward_mapping=False))
    batch = random_batch(32, reward="positive")
    metrics = {}
    assert finetuner.mapped_reward(batch, metrics) is batch.reward
    assert finetuner.task_reward_stats.count.item() == pytest.approx(1e-4)
    assert finetuner.implicit_reward_stats.count.item() == pytest.approx(1e-4)
    assert "mapped_reward" not in metrics


# ---------------------------------------------------------------------------------------------
# Freezing and the fresh task critic (invariant 27)


def _params(module):
    return {n: p.detach().clone() for n, p in module.named_parameters()}


@pytest.mark.parametrize("kind", ["dvfb", "fb"])
def test_finetuning_freezes_f_b_and_z(kind):
    agent = make_agent(kind)
    for seed in range(2):  # a little pre-training first, so nothing is at its initial value
        agent.update(random_batch(32, seed=10 + seed, reward="positive"))
    batch = random_batch(64, seed=0, reward="positive")
    z, _ = agent.model.infer_skill(batch.obs, batch.next_obs, batch.reward[:, 0], InferenceConfig(reward_quantile=None))
    f0, b0, actor0 = _params(agent.forward_map), _params(agent.backward_map), _params(agent.actor)
    explore0 = _params(agent.exploration_critic) if kind == "dvfb" else None
    f_grads0 = [None if p.grad is None else p.grad.clone() for p in agent.forward_map.parameters()]
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig())
    qf0 = _params(finetuner.task_critic)
    assert all(not p.requires_grad for p in agent.forward_map.parameters())
    assert all(not p.requires_grad for p in agent.backward_map.parameters())
    # Q_F is freshly initialised, not a copy of Q_P, and its target starts equal to it.
    if kind == "dvfb":
        for n, p in finetuner.task_critic.named_parameters():
            q = dict(agent.exploration_critic.named_parameters())[n]
            assert p.data_ptr() != q.data_ptr()
            if p.dim() == 2:
                assert not torch.equal(p, q), n
    for n, p in finetuner.task_critic_target.named_parameters():
        assert torch.equal(p, qf0[n]) and not p.requires_grad
    z_before = finetuner.z.clone()
    for seed in range(4):
        metrics = finetuner.update(random_batch(64, seed=seed, reward="positive"))
        assert all(torch.isfinite(v).all() for v in metrics.values())
    for n, p in agent.forward_map.named_parameters():
        assert torch.equal(p, f0[n]), n
    for n, p in agent.backward_map.named_parameters():
        assert torch.equal(p, b0[n]), n
    assert torch.equal(finetuner.z, z_before) and torch.equal(finetuner.z, z)
    assert any(not torch.equal(p, actor0[n]) for n, p in agent.actor.named_parameters())
    assert all(not torch.equal(p, qf0[n]) for n, p in finetuner.task_critic.named_parameters() if p.dim() == 2)
    if kind == "dvfb":  # Q_P is not used in fine-tuning
        for n, p in agent.exploration_critic.named_parameters():
            assert torch.equal(p, explore0[n])
    # F's gradients are not even accumulated (requires_grad is off): the pre-training ones remain.
    for p, g0 in zip(agent.forward_map.parameters(), f_grads0):
        assert (p.grad is None and g0 is None) or torch.equal(p.grad, g0)


def test_finetuner_optimizers_cover_only_actor_and_task_critic():
    agent = make_agent()
    finetuner = DualValueFinetuner(agent.model, agent.sample_skill(1)[0], FinetuneConfig())
    critic_ids = {id(p) for g in finetuner.critic_optimizer.param_groups for p in g["params"]}
    actor_ids = {id(p) for g in finetuner.actor_optimizer.param_groups for p in g["params"]}
    assert critic_ids == {id(p) for p in finetuner.task_critic.parameters()}
    assert actor_ids == {id(p) for p in agent.actor.parameters()}
    assert finetuner.actor_optimizer is not agent.actor_optimizer
    assert len(finetuner.actor_optimizer.state) == 0  # fresh Adam state


# ---------------------------------------------------------------------------------------------
# Q_F target and the dual-value actor objective (§9.4, §9.5, §9.6)


VARIANTS = {
    "default": dict(),  # eta = 0.5
    "code_preset": dict(qf_coef=50.0, eta=1.0),
    "wo_svf": dict(eta=0.0),
    "wo_map": dict(reward_mapping=False),
    "adaptive": dict(eta_mode="adaptive", reward_mapping=False),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_update_matches_reference_td_target_and_actor_objective(variant):
    """With sigma = 0 the training actions are the clamped means, so the reference is exact."""
    agent = make_agent(stddev=0.0)
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(6)))
    config = FinetuneConfig(**VARIANTS[variant])
    finetuner = DualValueFinetuner(agent.model, z, config)
    with torch.no_grad():  # a target different from the online critic
        for p in finetuner.task_critic_target.parameters():
            p.add_(0.05 * torch.randn_like(p))
    batch = random_batch(48, seed=7, reward="positive")
    actor0 = copy.deepcopy(agent.actor)
    critic0, target0 = copy.deepcopy(finetuner.task_critic), copy.deepcopy(finetuner.task_critic_target)
    captured = {}
    original_step = finetuner.actor_optimizer.step

    def capture(*args, **kwargs):
        captured["critic"] = copy.deepcopy(finetuner.task_critic)  # after the critic step
        captured["grads"] = [p.grad.clone() for p in agent.actor.parameters()]
        return original_step(*args, **kwargs)

    finetuner.actor_optimizer.step = capture
    metrics = finetuner.update(batch)

    n = batch.obs.shape[0]
    zz = z.expand(n, -1)
    with torch.no_grad():
        if config.reward_mapping:
            b = agent.backward_map(batch.next_obs).double()
            r_imp = b @ torch.linalg.solve(b.T @ b / n, z.double())
            k = n / (n + 1e-4)
            reward = (batch.reward.double() * (r_imp.mean() * k) / (batch.reward.double().mean() * k + 1e-8)).float()
        else:
            reward = batch.reward
        next_action = actor0(batch.next_obs, zz).clamp(-1 + 1e-6, 1 - 1e-6)
        y = reward + 0.99 * target0(batch.next_obs, zz, next_action).amin(0)
        q = critic0(batch.obs, zz, batch.action)
        critic_loss = ((q[0] - y) ** 2).mean() + ((q[1] - y) ** 2).mean()
    torch.testing.assert_close(metrics["task_critic_loss"], critic_loss, rtol=1e-4, atol=1e-5)

    action = actor0(batch.obs, zz)
    q_f = captured["critic"](batch.obs, zz, action).amin(0).squeeze(-1)
    q_m = (agent.forward_map(batch.obs, action, zz) * zz).sum(-1).amin(0)
    if config.eta_mode == "adaptive":
        eta = (q_f / q_m).detach()
    else:
        eta = config.eta
    objective = config.qf_coef * q_f + eta * q_m
    ref_loss = -objective.mean()
    torch.testing.assert_close(metrics["actor_loss"], ref_loss.detach(), rtol=1e-4, atol=1e-5)
    if config.eta_mode == "adaptive":  # eta_i Q_M,i = Q_F,i in value
        torch.testing.assert_close(metrics["actor_loss"], -(config.qf_coef + 1) * q_f.detach().mean(),
                                   rtol=1e-4, atol=1e-5)
    if config.eta == 0 and config.eta_mode == "constant":
        assert "skill_value" not in metrics  # w/o SVF: Q_M is not evaluated at all
    else:
        assert metrics["skill_value"].item() == pytest.approx(q_m.mean().item(), rel=1e-4, abs=1e-6)
    ref_grads = torch.autograd.grad(ref_loss, list(actor0.parameters()))
    for g, rg in zip(captured["grads"], ref_grads):
        torch.testing.assert_close(g, rg, rtol=1e-3, atol=1e-6)
    # The Q_F target moved by the EMA after the critic step.
    for p_t, p_t0, p in zip(finetuner.task_critic_target.parameters(), target0.parameters(),
                            finetuner.task_critic.parameters()):
        torch.testing.assert_close(p_t, 0.01 * p + 0.99 * p_t0, rtol=1e-5, atol=1e-7)


def test_adaptive_eta_runs():
    agent = make_agent()
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(8)))
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig(eta_mode="adaptive", reward_mapping=False))
    actor0 = _params(agent.actor)
    for seed in range(5):
        metrics = finetuner.update(random_batch(32, seed=seed, reward="positive"))
        assert all(torch.isfinite(v).all() for v in metrics.values())
        assert "skill_value" in metrics
    assert any(not torch.equal(p, actor0[n]) for n, p in agent.actor.named_parameters())


def test_training_state_round_trip():
    agent = make_agent()
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(9)))
    finetuner = DualValueFinetuner(agent.model, z, FinetuneConfig())
    for seed in range(2):
        finetuner.update(random_batch(32, seed=seed, reward="positive"))
    state = copy.deepcopy(finetuner.training_state())
    assert not any(k.startswith("agent.") for k in state["finetuner"])
    other_agent = make_agent()
    other = DualValueFinetuner(other_agent.model, torch.zeros(D), FinetuneConfig())
    other.load_training_state(state)
    assert torch.equal(other.z, finetuner.z)
    assert other.task_reward_stats.count.item() == finetuner.task_reward_stats.count.item()
    for (n, p), q in zip(other.task_critic.named_parameters(), finetuner.task_critic.parameters()):
        assert torch.equal(p, q), n
    for p, q in zip(other_agent.actor.parameters(), agent.actor.parameters()):
        assert torch.equal(p, q)
    assert math.isfinite(finetuner.update(random_batch(32, seed=5, reward="positive"))["actor_loss"].item())
