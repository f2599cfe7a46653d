"""Tests for dvfb.agents.fb: implicit reward, z inference, the FB / auxiliary-Q / orthonormality
losses and the actor objectives (docs/methods.md §7.8-§7.11, §8.2; §13 invariants 10-14, 19-22).

The population-level checks (invariants 19, 20 and the "FB training recovers the successor measure"
test) run on a tabular MDP in float64. They cannot drive :meth:`FBAgent.fb_losses` itself, whose F
and B are MLPs of observations and z with a learned actor, so they re-state the loss formula of
§7.8 (the same ``0.5 * offdiag - diag`` expression, with exact expectations in place of batch means)
and use the library's :func:`offdiag_mean` for the batch estimator. ``fb_losses`` itself is checked
against an explicit reference computation on real networks.
"""

import math

import pytest
import torch

from dvfb.agents.dvfb import DVFBAgent
from dvfb.protocols.zeroshot import InferenceConfig
from dvfb.agents.fb import (
    BACKWARD_INPUTS,
    FBAgent,
    implicit_reward,
    infer_z_from_rewards,
    offdiag_mean,
)
from dvfb.nets import project_to_sphere, sample_z_prior, skill_values, training_action
from dvfb.data import Batch
from tiny import ACT, D, OBS, random_batch, tiny_config, tiny_exploration


F64 = torch.float64


def perturb_(module, scale=0.05, seed=0):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g))


def offdiag_mask(n):
    return ~torch.eye(n, dtype=torch.bool)


# ---------------------------------------------------------------------------------------------
# Implicit reward (invariants 10, 11)


def test_offdiag_mean_matches_masked_mean():
    x = torch.randn(3, 7, 7, dtype=F64)
    ref = torch.stack([x[k][offdiag_mask(7)].mean() for k in range(3)])
    torch.testing.assert_close(offdiag_mean(x), ref)


def test_implicit_reward_hat_matrix_on_span():
    g = torch.Generator().manual_seed(0)
    n, d = 64, 8
    b = torch.randn(n, d, generator=g, dtype=F64)
    w = torch.randn(d, generator=g, dtype=F64)
    r = b @ w
    z = b.T @ r / n  # not projected
    torch.testing.assert_close(implicit_reward(b, z), r, atol=1e-12, rtol=1e-12)
    # One z per row (the pre-training form) gives the same result when all rows share z.
    torch.testing.assert_close(implicit_reward(b, z.expand(n, d)), r, atol=1e-12, rtol=1e-12)


def test_implicit_reward_is_least_squares_projection_for_general_r():
    g = torch.Generator().manual_seed(1)
    n, d = 50, 6
    b = torch.randn(n, d, generator=g, dtype=F64)
    r = torch.randn(n, generator=g, dtype=F64)  # not in span(B)
    r_imp = implicit_reward(b, b.T @ r / n)
    lstsq = b @ torch.linalg.lstsq(b, r.unsqueeze(-1)).solution.squeeze(-1)
    torch.testing.assert_close(r_imp, lstsq, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(b.T @ (r - r_imp), torch.zeros(d, dtype=F64), atol=1e-10, rtol=0)
    assert (r - r_imp).norm() > 0.1  # r really was outside the span


def test_implicit_reward_per_row_z_and_ridge():
    g = torch.Generator().manual_seed(2)
    n, d = 40, 5
    b = torch.randn(n, d, generator=g, dtype=F64)
    z = torch.randn(n, d, generator=g, dtype=F64)
    cov = b.T @ b / n
    ref = torch.einsum("nd,de,ne->n", b, torch.linalg.inv(cov), z)
    torch.testing.assert_close(implicit_reward(b, z), ref, atol=1e-10, rtol=1e-10)
    ridge = 0.3
    ref_ridge = torch.einsum("nd,de,ne->n", b, torch.linalg.inv(cov + ridge * torch.eye(d, dtype=F64)), z)
    torch.testing.assert_close(implicit_reward(b, z, ridge), ref_ridge, atol=1e-10, rtol=1e-10)
    assert not torch.allclose(ref, ref_ridge)


def test_implicit_reward_linear_invariance():
    g = torch.Generator().manual_seed(3)
    n, d = 64, 8
    b = torch.randn(n, d, generator=g, dtype=F64)
    z = torch.randn(d, generator=g, dtype=F64)
    a = torch.randn(d, d, generator=g, dtype=F64) + 3 * torch.eye(d, dtype=F64)  # invertible
    torch.testing.assert_close(implicit_reward(b @ a, a.T @ z), implicit_reward(b, z), atol=1e-9, rtol=1e-9)
    zs = torch.randn(n, d, generator=g, dtype=F64)
    torch.testing.assert_close(implicit_reward(b @ a, zs @ a), implicit_reward(b, zs), atol=1e-9, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# z inference (invariants 3, 12, 13, 14). Tested on infer_z_from_rewards, because the identity
# covariance of invariant 12 cannot be imposed on a network B.


def orthonormal_features(n, d, seed):
    """Rows B with Cov = B^T B / n = I exactly."""
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, d, generator=g, dtype=F64))
    return math.sqrt(n) * q


def test_inference_direction_with_identity_covariance():
    n, d = 200, 6
    b = orthonormal_features(n, d, seed=0)
    torch.testing.assert_close(b.T @ b / n, torch.eye(d, dtype=F64))
    w = torch.randn(d, generator=torch.Generator().manual_seed(1), dtype=F64)
    z, info = infer_z_from_rewards(b, b @ w, quantile=None)
    torch.testing.assert_close(z, project_to_sphere(w), atol=1e-10, rtol=1e-10)
    assert info["num_kept"] == n and info["fallback"] is None


@pytest.mark.parametrize("quantile", [None, 0.99, 0.9])
def test_inferred_z_positive_rescaling_invariance(quantile):
    g = torch.Generator().manual_seed(4)
    feats = project_to_sphere(torch.randn(1000, D, generator=g, dtype=F64))
    r = torch.randn(1000, generator=g, dtype=F64)
    z, _ = infer_z_from_rewards(feats, r, quantile)
    for k in (1e-3, 3.7, 250.0):
        zk, _ = infer_z_from_rewards(feats, k * r, quantile)
        torch.testing.assert_close(zk, z, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(z.norm(), torch.tensor(math.sqrt(D), dtype=F64))


def test_inferred_z_flips_sign_without_filter():
    g = torch.Generator().manual_seed(5)
    feats = project_to_sphere(torch.randn(500, D, generator=g, dtype=F64))
    r = torch.rand(500, generator=g, dtype=F64) + torch.linspace(0, 1, 500, dtype=F64)
    z, _ = infer_z_from_rewards(feats, r, None)
    z_neg, _ = infer_z_from_rewards(feats, -r, None)
    torch.testing.assert_close(z_neg, -z, atol=1e-12, rtol=0)


@pytest.mark.parametrize("n", [7, 100, 101, 150, 199, 1000, 1001, 10_000])
def test_quantile_filter_keeps_the_top_one_percent(n):
    g = torch.Generator().manual_seed(n)
    feats = torch.randn(n, D, generator=g)
    r = torch.randn(n, generator=g)  # distinct values
    z, info = infer_z_from_rewards(feats, r, 0.99)
    k = info["num_kept"]
    assert k >= math.ceil(0.01 * n)
    assert k <= math.ceil(0.01 * n) + 1
    top = r.argsort(descending=True)[:k]
    expected = project_to_sphere((r[top, None] * feats[top]).mean(0))
    torch.testing.assert_close(z, expected, atol=1e-5, rtol=1e-5)
    assert r.argmax() in top


def test_quantile_filter_keeps_every_maximal_reward():
    g = torch.Generator().manual_seed(6)
    n = 1000
    feats = torch.randn(n, D, generator=g)
    r = torch.rand(n, generator=g)
    ties = torch.randperm(n, generator=g)[:57]
    r[ties] = 2.0  # 5.7 % of the samples share the maximum
    z, info = infer_z_from_rewards(feats, r, 0.99)
    assert info["num_kept"] == 57
    torch.testing.assert_close(z, project_to_sphere(feats[ties].mean(0)), atol=1e-5, rtol=1e-5)


def test_zero_rewards_fall_back():
    g = torch.Generator().manual_seed(7)
    feats = torch.randn(300, D, generator=g)
    z, info = infer_z_from_rewards(feats, torch.zeros(300), 0.99)
    assert info["fallback"] == "zero" and torch.all(z == 0)
    # Kept rewards all zero, others negative: retry without the filter.
    r = -torch.rand(300, generator=g)
    r[:30] = 0.0
    z, info = infer_z_from_rewards(feats, r, 0.99)
    assert info["fallback"] == "no_filter" and info["num_kept"] == 300
    torch.testing.assert_close(z, project_to_sphere((r[:, None] * feats).mean(0)))
    # The agent replaces a zero z by a prior draw on the sphere.
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    batch = random_batch(64, future=True)
    z, info = agent.model.infer_skill(batch.obs, batch.next_obs, torch.zeros(64), InferenceConfig(reward_quantile=0.99))
    assert info["fallback"] == "prior"
    torch.testing.assert_close(z.norm(), torch.tensor(math.sqrt(D)), atol=1e-5, rtol=0)


@pytest.mark.parametrize("mode", BACKWARD_INPUTS)
def test_agent_infer_z_uses_label_features_and_is_on_the_sphere(mode):
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(backward_input=mode))
    batch = random_batch(500, seed=1, future=True)
    reward = batch.next_obs[:, 0]
    z, info = agent.model.infer_skill(batch.obs, batch.next_obs, reward, InferenceConfig(reward_quantile=0.9))
    torch.testing.assert_close(z.norm(), torch.tensor(math.sqrt(D)), atol=1e-5, rtol=0)
    inputs = batch.next_obs if mode == "state" else torch.cat([batch.obs, batch.next_obs], -1)
    with torch.no_grad():
        feats = agent.backward_map(inputs)
    keep = reward >= torch.quantile(reward.double(), 0.9).float()
    torch.testing.assert_close(z, project_to_sphere((reward[keep, None] * feats[keep]).mean(0)))
    assert info["num_kept"] == int(keep.sum()) == 50


def test_infer_z_from_goal_is_projected_b():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    goal = torch.randn(OBS)
    z = agent.model.skill_from_goal(goal)
    with torch.no_grad():
        torch.testing.assert_close(z, agent.backward_map(goal[None])[0])
    torch.testing.assert_close(z.norm(), torch.tensor(math.sqrt(D)), atol=1e-5, rtol=0)


# ---------------------------------------------------------------------------------------------
# Tabular MDP: population FB loss (invariants 19, 20) and recovery of the successor measure


class TabularMDP:
    """|S| states, |A| actions, random P, pi and data distribution rho_sa (float64)."""

    def __init__(self, n_states=5, n_actions=3, gamma=0.9, seed=0):
        g = torch.Generator().manual_seed(seed)

        def dirichlet(*shape):
            x = -torch.log(torch.rand(*shape, generator=g, dtype=F64))  # Exp(1) -> Dirichlet(1)
            return x / x.sum(-1, keepdim=True)

        self.S, self.A, self.gamma = n_states, n_actions, gamma
        self.P = dirichlet(n_states * n_actions, n_states)  # P(x | sa), (SA, S)
        self.pi = dirichlet(n_states, n_actions)  # pi(a | s)
        self.rho_sa = dirichlet(n_states * n_actions)
        self.rho = self.rho_sa @ self.P  # next-state marginal
        # P_pi[(s,a), (s',a')] = P(s'|s,a) pi(a'|s')
        self.P_pi = (self.P[:, :, None] * self.pi[None]).reshape(n_states * n_actions, -1)
        eye = torch.eye(n_states * n_actions, dtype=F64)
        self.M = torch.linalg.solve(eye - gamma * self.P_pi, self.P)  # counts s_{t+1} from t = 0
        self.m_star = self.M / self.rho  # density w.r.t. rho

    def backup(self, m_bar):
        """Tm = gamma * P_pi m_bar."""
        return self.gamma * self.P_pi @ m_bar

    def population_loss(self, m, m_bar):
        """L(m, m_bar) = sum_sa rho_sa [sum_x rho(x) (m - Tm)^2 - 2 sum_x P(x|sa) m(sa, x)]."""
        tm = self.backup(m_bar)
        sq = (self.rho[None] * (m - tm) ** 2).sum(-1)
        lin = (self.P * m).sum(-1)
        return (self.rho_sa * (sq - 2 * lin)).sum()

    def constant(self, m_bar):
        tm = self.backup(m_bar)
        return (self.rho_sa * (self.P ** 2 / self.rho + 2 * self.P * tm).sum(-1)).sum()


def test_population_fb_loss_is_stationary_at_the_successor_measure():
    mdp = TabularMDP()
    # Sanity: M^pi rows sum to 1 / (1 - gamma) and M^pi = P + gamma P_pi M^pi.
    torch.testing.assert_close(mdp.M.sum(-1), torch.full((15,), 10.0, dtype=F64))
    m = mdp.m_star.clone().requires_grad_(True)
    loss = mdp.population_loss(m, mdp.m_star)
    (grad,) = torch.autograd.grad(loss, m)
    assert grad.abs().max() < 1e-13  # (a)
    assert abs(loss.item() + mdp.constant(mdp.m_star).item()) < 1e-12  # (b)
    assert loss.item() < -1.0  # the raw loss is not zero at the optimum
    # Bellman-residual form: L + C = sum rho_sa rho (m - Tm - P/rho)^2 for any m.
    g = torch.Generator().manual_seed(1)
    m_pert = mdp.m_star + 0.1 * torch.randn(mdp.m_star.shape, generator=g, dtype=F64)
    m_bar = mdp.m_star + 0.1 * torch.randn(mdp.m_star.shape, generator=g, dtype=F64)
    residual = m_pert - mdp.backup(m_bar) - mdp.P / mdp.rho
    torch.testing.assert_close(mdp.population_loss(m_pert, m_bar) + mdp.constant(m_bar),
                               (mdp.rho_sa[:, None] * mdp.rho[None] * residual ** 2).sum())
    # (c) non-zero gradient away from the fixed point.
    m_pert.requires_grad_(True)
    (grad,) = torch.autograd.grad(mdp.population_loss(m_pert, mdp.m_star), m_pert)
    assert grad.abs().max() > 1e-3


def test_batch_fb_estimator_matches_population_loss():
    """Invariant 20: E[offdiag_mean((M - D*TM)^2) - 2 diag_mean(M)] = L(m, m_bar).

    TM[i, j] is the expected backup Tm(sa_i, s'_j)/gamma evaluated at the sampled pair, so that the
    estimator's expectation is exactly the population loss (a sampled next action would add its
    variance to the squared term).
    """
    mdp = TabularMDP(seed=3)
    g = torch.Generator().manual_seed(4)
    m = mdp.m_star + 0.5 * torch.randn(mdp.m_star.shape, generator=g, dtype=F64)
    m_bar = mdp.m_star + 0.5 * torch.randn(mdp.m_star.shape, generator=g, dtype=F64)
    tm_over_gamma = mdp.P_pi @ m_bar
    reps, n = 500, 64
    sa = torch.multinomial(mdp.rho_sa, reps * n, replacement=True, generator=g).reshape(reps, n)
    nxt = torch.multinomial(mdp.P[sa.reshape(-1)], 1, generator=g).reshape(reps, n)
    big_m = m[sa[:, :, None], nxt[:, None, :]]  # (reps, N, N): m(sa_i, s'_j)
    big_tm = tm_over_gamma[sa[:, :, None], nxt[:, None, :]]
    discount = torch.full((reps, n, 1), mdp.gamma, dtype=F64)  # D scales row i
    values = offdiag_mean((big_m - discount * big_tm) ** 2) - 2 * big_m.diagonal(dim1=-2, dim2=-1).mean(-1)
    estimate, se = values.mean().item(), values.std().item() / math.sqrt(reps)
    exact = mdp.population_loss(m, m_bar).item()
    assert abs(estimate - exact) < 4 * se, (estimate, exact, se)
    assert se < 0.05 * abs(exact)  # the check has power


def test_fb_training_recovers_the_successor_measure():
    """Tabular F (SA x d) and B (S x d), d = |S|, trained on the §7.8 loss with exact expectations
    and an EMA target (tau as in [C]'s schedule, larger for speed): F B^T rho -> M^pi."""
    mdp = TabularMDP(seed=0)
    d = mdp.S
    g = torch.Generator().manual_seed(0)
    f = torch.nn.Parameter(0.1 * torch.randn(mdp.S * mdp.A, d, generator=g, dtype=F64))
    b = torch.nn.Parameter(0.1 * torch.randn(mdp.S, d, generator=g, dtype=F64))
    f_bar, b_bar = f.detach().clone(), b.detach().clone()
    initial_err = ((f @ b.T).detach() * mdp.rho[None] - mdp.M).abs().max() / mdp.M.abs().max()
    opt = torch.optim.Adam([f, b], lr=0.01)
    weights_off = mdp.rho_sa[:, None] * mdp.rho[None]  # independent (sa_i, x_j), i != j
    weights_diag = mdp.rho_sa[:, None] * mdp.P  # (sa_i, s'_i) pairs
    for _ in range(2500):
        m = f @ b.T
        with torch.no_grad():
            target = mdp.P_pi @ (f_bar @ b_bar.T)  # E over (s', a' ~ pi) of F_bar(s', a') . B_bar(x)
        offdiag = (weights_off * (m - mdp.gamma * target) ** 2).sum()
        diag = (weights_diag * m).sum()
        loss = 0.5 * offdiag - diag
        opt.zero_grad()
        loss.backward()
        opt.step()
        with torch.no_grad():
            f_bar.lerp_(f, 0.05)
            b_bar.lerp_(b, 0.05)
    recovered = (f @ b.T).detach() * mdp.rho[None]
    rel_err = (recovered - mdp.M).abs().max() / mdp.M.abs().max()
    assert rel_err < 1e-3, rel_err
    # The initial guess was far from M^pi, so the training did the work.
    assert initial_err > 0.5, initial_err


# ---------------------------------------------------------------------------------------------
# FB losses on real networks (invariants 1, 21, 22)


def fb_inputs(agent: FBAgent, batch: Batch, seed=0):
    torch.manual_seed(seed)
    z = agent.training_z(batch)
    with torch.no_grad():
        next_action = training_action(agent.actor(batch.next_obs, z), agent.config.stddev,
                                      agent.config.stddev_clip)
    online_input, target_input = agent.backward_inputs(batch)
    backward = agent.backward_map(online_input)
    return z, next_action, backward, target_input


@pytest.mark.parametrize("mode", BACKWARD_INPUTS)
def test_fb_losses_match_reference_computation(mode):
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(backward_input=mode, ortho_coef=0.7, q_loss_coef=0.3))
    perturb_(agent.forward_target, seed=1)  # targets differ from the online nets
    perturb_(agent.backward_target, seed=2)
    n = 48
    discount = torch.linspace(0.5, 1.0, n).unsqueeze(-1)  # per-row D: must scale row i of TM
    batch = random_batch(n, seed=1, future=True, discount=discount)
    z, next_action, backward, target_input = fb_inputs(agent, batch)
    losses = agent.fb_losses(batch, z, next_action, backward, target_input)

    with torch.no_grad():
        fwd = agent.forward_map(batch.obs, batch.action, z)
        fwd_t = agent.forward_target(batch.next_obs, next_action, z)
        b_t = agent.backward_target(target_input)
        bb = backward.detach()
        tm = torch.minimum(fwd_t[0] @ b_t.T, fwd_t[1] @ b_t.T)
        assert tm.shape == (n, n)
        mask = offdiag_mask(n)
        fb = 0.0
        for k in range(2):
            mk = fwd[k] @ bb.T
            assert mk.shape == (n, n)
            off = ((mk - discount * tm) ** 2)[mask].mean()
            fb = fb + 0.5 * off - mk.diagonal().mean()
        gram = bb @ bb.T
        ortho = (gram ** 2)[mask].mean() - 2 * gram.diagonal().mean()
        cov = (bb.T @ bb / n).double()
        r_imp = torch.einsum("nd,de,ne->n", bb.double(), torch.linalg.inv(cov), z.double()).float()
        next_q = torch.minimum((fwd_t[0] * z).sum(-1), (fwd_t[1] * z).sum(-1))
        y = r_imp + discount.squeeze(-1) * next_q
        q_loss = sum(((fwd[k] * z).sum(-1) - y).pow(2).mean() for k in range(2))
    torch.testing.assert_close(losses["fb_loss"], fb, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(losses["ortho_loss"], ortho, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(losses["fb_q_loss"], q_loss, rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(losses["fb_total"], fb + 0.7 * ortho + 0.3 * q_loss, rtol=1e-3, atol=1e-3)

    # Gradients reach F and B only; the targets, the actor and z get none.
    losses["fb_total"].backward()
    assert all(p.grad is not None for p in agent.forward_map.parameters())
    assert all(p.grad is not None for p in agent.backward_map.parameters())
    assert all(p.grad is None for p in agent.actor.parameters())
    for net in (agent.forward_target, agent.backward_target):
        assert all(p.grad is None and not p.requires_grad for p in net.parameters())


def test_q_loss_flag_removes_the_auxiliary_loss():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(q_loss=False))
    batch = random_batch(32, future=True)
    losses = agent.fb_losses(batch, *fb_inputs(agent, batch))
    assert "fb_q_loss" not in losses
    torch.testing.assert_close(losses["fb_total"], losses["fb_loss"] + losses["ortho_loss"])


def _copy_head(twin, src=0, dst=1):
    hd = twin.hidden_dim
    with torch.no_grad():
        twin.first.weight[dst * hd:(dst + 1) * hd] = twin.first.weight[src * hd:(src + 1) * hd]
        twin.first.bias[dst * hd:(dst + 1) * hd] = twin.first.bias[src * hd:(src + 1) * hd]
        twin.second_weight[dst] = twin.second_weight[src]
        twin.second_bias[dst] = twin.second_bias[src]


def test_twin_head_reduction_to_single_head_loss():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    perturb_(agent.forward_target, seed=3)
    _copy_head(agent.forward_map.heads)
    _copy_head(agent.forward_target.heads)
    n = 40
    batch = random_batch(n, seed=2, future=True)
    z, next_action, backward, target_input = fb_inputs(agent, batch)
    with torch.no_grad():
        fwd = agent.forward_map(batch.obs, batch.action, z)
        fwd_t = agent.forward_target(batch.next_obs, next_action, z)
    assert torch.equal(fwd[0], fwd[1]) and torch.equal(fwd_t[0], fwd_t[1])
    losses = agent.fb_losses(batch, z, next_action, backward, target_input)
    with torch.no_grad():
        m = fwd[0] @ backward.T
        tm = fwd_t[0] @ agent.backward_target(target_input).T
        single = ((m - 0.99 * tm) ** 2)[offdiag_mask(n)].mean() - 2 * m.diagonal().mean()
    torch.testing.assert_close(losses["fb_loss"], single, rtol=1e-5, atol=1e-5)
    # Before the copy (distinct heads) the reduction does not hold in general.
    torch.manual_seed(0)
    other = FBAgent(OBS, ACT, tiny_config())
    perturb_(other.forward_target, seed=3)
    z, next_action, backward, target_input = fb_inputs(other, batch)
    lo = other.fb_losses(batch, z, next_action, backward, target_input)
    with torch.no_grad():
        m = other.forward_map(batch.obs, batch.action, z)[0] @ backward.T
        tm = other.forward_target(batch.next_obs, next_action, z)[0] @ other.backward_target(target_input).T
        single = ((m - 0.99 * tm) ** 2)[offdiag_mask(n)].mean() - 2 * m.diagonal().mean()
    assert lo["fb_loss"].item() != pytest.approx(single.item(), rel=1e-3)


def test_orthonormality_loss_of_orthogonal_rows_is_minus_2d():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(q_loss=False))
    for n in (2, 5, D):
        batch = random_batch(n, seed=n, future=True)
        z, next_action, _, target_input = fb_inputs(agent, batch)
        q, _ = torch.linalg.qr(torch.randn(D, n))
        rows = math.sqrt(D) * q.T  # n <= d mutually orthogonal rows of norm sqrt(d)
        losses = agent.fb_losses(batch, z, next_action, rows, target_input)
        torch.testing.assert_close(losses["ortho_loss"], torch.tensor(-2.0 * D), atol=1e-4, rtol=0)


def test_orthonormality_loss_is_unbiased_for_frobenius_distance():
    """E[L_ortho] + d = ||C - I||_F^2 for i.i.d. zero-mean rows with covariance C."""
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config(q_loss=False))
    n, reps = 128, 100
    batch = random_batch(n, seed=9, future=True)
    z, next_action, _, target_input = fb_inputs(agent, batch)
    g = torch.Generator().manual_seed(10)
    a = torch.randn(D, D, generator=g) / math.sqrt(D)
    cov = a @ a.T + 0.5 * torch.eye(D)
    chol = torch.linalg.cholesky(cov)
    values = []
    with torch.no_grad():
        for _ in range(reps):
            rows = torch.randn(n, D, generator=g) @ chol.T
            values.append(agent.fb_losses(batch, z, next_action, rows, target_input)["ortho_loss"])
    values = torch.stack(values).double()
    estimate, se = values.mean().item() + D, values.std().item() / math.sqrt(reps)
    exact = ((cov - torch.eye(D)) ** 2).sum().item()
    assert abs(estimate - exact) < 4 * se, (estimate, exact, se)
    assert se < 0.1 * exact


# ---------------------------------------------------------------------------------------------
# Actor objectives (§7.11)


def _reference_action(agent, obs, z, seed):
    torch.manual_seed(seed)
    mu = agent.actor(obs, z)
    noise = (torch.randn_like(mu) * agent.config.stddev).clamp(-agent.config.stddev_clip,
                                                               agent.config.stddev_clip)
    raw = mu + noise
    return raw + (raw.clamp(-1 + 1e-6, 1 - 1e-6) - raw).detach()  # straight-through clamp (§3.3)


def test_fb_actor_loss_is_minus_mean_min_skill_value():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, tiny_config())
    perturb_(agent.forward_map, scale=0.2, seed=4)  # make the two heads differ more
    obs, z = torch.randn(32, OBS), sample_z_prior(32, D)
    torch.manual_seed(11)
    metrics = {}
    loss = agent.actor_loss(obs, z, metrics)
    with torch.no_grad():
        a = _reference_action(agent, obs, z, 11)
        qm = skill_values(agent.forward_map(obs, a, z), z)
        ref = -torch.minimum(qm[0], qm[1]).mean()
    torch.testing.assert_close(loss.detach(), ref, atol=1e-5, rtol=1e-5)
    assert (qm[0] != qm[1]).any()
    assert metrics["skill_value"].item() == pytest.approx(-ref.item(), rel=1e-5, abs=1e-6)


@pytest.mark.parametrize("alpha_mode,alpha", [("constant", 5.0), ("constant", 50.0), ("adaptive", 5.0)])
def test_dvfb_actor_loss_combines_skill_and_exploration_values(alpha_mode, alpha):
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(), tiny_exploration(alpha=alpha, alpha_mode=alpha_mode))
    perturb_(agent.exploration_critic, scale=0.3, seed=5)
    obs, z = torch.randn(32, OBS), sample_z_prior(32, D)
    torch.manual_seed(12)
    loss = agent.actor_loss(obs, z, {})
    a = _reference_action(agent, obs, z, 12)
    qm = skill_values(agent.forward_map(obs, a, z), z).amin(0)
    qp = agent.exploration_critic(obs, z, a).amin(0).squeeze(-1)
    if alpha_mode == "adaptive":
        weight = (2 * qm.mean() / qp.mean()).detach()
        assert weight.item() != pytest.approx(alpha)
    else:
        weight = alpha
    ref = -(qm + weight * qp).mean()
    torch.testing.assert_close(loss, ref, atol=1e-5, rtol=1e-5)
    # Gradients w.r.t. the actor agree too: in adaptive mode alpha is detached.
    params = list(agent.actor.parameters())
    g_loss = torch.autograd.grad(loss, params)
    g_ref = torch.autograd.grad(ref, params)
    for gl, gr in zip(g_loss, g_ref):
        torch.testing.assert_close(gl, gr, atol=1e-5, rtol=1e-4)


def test_noise_free_actor_loss_uses_the_mean_action():
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, tiny_config(stddev=0.0), tiny_exploration(alpha=2.0))
    obs, z = torch.randn(16, OBS), sample_z_prior(16, D)
    with torch.no_grad():
        loss = agent.actor_loss(obs, z, {})
        a = agent.actor(obs, z)
        ref = -(skill_values(agent.forward_map(obs, a, z), z).amin(0)
                + 2.0 * agent.exploration_critic(obs, z, a).amin(0).squeeze(-1)).mean()
    torch.testing.assert_close(loss, ref, atol=1e-6, rtol=1e-6)
