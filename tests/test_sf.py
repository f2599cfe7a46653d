"""Successor features (docs/methods.md, "Successor features"): every feature loss, the TD loss and
the training skills against hand computations written with explicit loops, the reward regression
on a planted linear reward, the separation of the two objectives, and the registered protocol."""

import math

import pytest
import torch

from dvfb.agents import get_spec, make_agent
from dvfb.agents.sf import PAPER_NAMES, SFAgent, SFConfig, regress_task_vector
from dvfb.core.config import merge
from dvfb.nets.features import FEATURE_LEARNERS
from dvfb.protocols import protocols_of
from dvfb.data import Batch
from tiny import ACT, D, E as E_, H, OBS, filled_replay, tiny_run_config

N = 6


def tiny_agent(features="lap", **overrides):
    config = SFConfig(features=features, z_dim=D, hidden_dim=H, feature_dim=E_, backward_hidden_dim=H,
                      batch_size=N, **overrides)
    return SFAgent(OBS, ACT, config).double()


def random_batch(seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randn(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    return Batch(obs=r(N, OBS), action=torch.rand(N, ACT, generator=g, dtype=torch.float64) * 2 - 1,
                 reward=r(N, 1), discount=torch.full((N, 1), 0.99, dtype=torch.float64), next_obs=r(N, OBS),
                 future_obs=None, z=None)


def ortho_by_hand(phi):
    total_off, total_diag = 0.0, 0.0
    for i in range(N):
        for j in range(N):
            g = float(phi[i] @ phi[j])
            if i == j:
                total_diag += g
            else:
                total_off += g * g
    return total_off / (N * (N - 1)) - 2 * total_diag / N


def test_laplacian_loss_by_hand():
    agent, b = tiny_agent("lap"), random_batch()
    learner = agent.feature_learner
    next_phi = learner.phi(b.next_obs)
    loss, _ = learner.loss(b.obs, b.action, b.next_obs, next_phi)
    phi = learner.phi(b.obs).detach()
    next_phi = next_phi.detach()
    smooth = sum(float((phi[i, k] - next_phi[i, k]) ** 2) for i in range(N) for k in range(D)) / (N * D)
    assert float(loss.detach()) == pytest.approx(smooth + ortho_by_hand(phi), rel=1e-10)


def test_lra_p_loss_by_hand():
    agent, b = tiny_agent("lra_p"), random_batch(1)
    learner = agent.feature_learner
    next_phi = learner.phi(b.next_obs)
    loss, _ = learner.loss(b.obs, b.action, b.next_obs, next_phi)
    mu = learner.mu(torch.cat([b.obs, b.action], -1)).detach()
    phi = next_phi.detach()
    diag = sum(float(mu[i] @ phi[i]) for i in range(N)) / N
    off = sum(float(mu[i] @ phi[j]) ** 2 for i in range(N) for j in range(N) if i != j) / (N * (N - 1))
    assert float(loss.detach()) == pytest.approx(-2 * diag + off + ortho_by_hand(phi), rel=1e-10)


def test_lra_sr_loss_by_hand_and_its_targets_move_inside_the_loss():
    agent, b = tiny_agent("lra_sr"), random_batch(2)
    learner = agent.feature_learner
    with torch.no_grad():  # make the targets differ from their networks
        for p in learner.phi_target.parameters():
            p.add_(0.05)
        for p in learner.mu_target.parameters():
            p.sub_(0.05)
    # What the targets must be after the loss's EMA (tau = 0.01), computed before the call.
    expected_phi_t = [t + 0.01 * (o - t) for t, o in zip(learner.phi_target.parameters(), learner.phi.parameters())]
    expected_mu_t = [t + 0.01 * (o - t) for t, o in zip(learner.mu_target.parameters(), learner.mu.parameters())]
    loss, _ = learner.loss(b.obs, b.action, b.next_obs, learner.phi(b.next_obs))
    for got, want in zip([*learner.phi_target.parameters(), *learner.mu_target.parameters()],
                         expected_phi_t + expected_mu_t):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-15)
    phi = learner.phi(b.obs).detach()
    mu_next = learner.mu(b.next_obs).detach()
    phi_bar = learner.phi_target(b.next_obs)
    mu_bar = learner.mu_target(b.next_obs)
    diag = sum(float(phi[i] @ mu_next[i]) for i in range(N)) / N
    td = sum((float(phi[i] @ mu_next[j]) - 0.99 * float(phi_bar[i] @ mu_bar[j])) ** 2
             for i in range(N) for j in range(N) if i != j) / (N * (N - 1))
    assert float(loss.detach()) == pytest.approx(-2 * diag + td + ortho_by_hand(phi), rel=1e-10)


def test_contrastive_loss_by_hand():
    agent, b = tiny_agent("cl"), random_batch(3)
    learner = agent.feature_learner
    loss, _ = learner.loss(b.obs, b.action, b.next_obs, learner.phi(b.next_obs))
    q = learner.phi(b.obs).detach()
    k = learner.mu(b.next_obs).detach()
    total = 0.0
    for i in range(N):
        sims = [float(q[i] @ k[j]) / (float(q[i].norm()) * float(k[j].norm())) for j in range(N)]
        total += -sims[i] + math.log(sum(math.exp(s) for j, s in enumerate(sims) if j != i))
    assert float(loss.detach()) == pytest.approx(total / N, rel=1e-10)


def test_every_feature_learner_is_registered_with_its_paper_name():
    assert set(FEATURE_LEARNERS) == set(PAPER_NAMES) == {"lap", "lra_p", "lra_sr", "cl"}
    spec = get_spec("sf")
    for features, label in PAPER_NAMES.items():
        assert spec.method_label({"sf": {"features": features}}) == label


def test_td_loss_by_hand_uses_the_smaller_target_head_and_the_projections():
    agent, b = tiny_agent("lap"), random_batch(4)
    z = agent.sample_skill(N).double()
    next_phi = agent.features(b.next_obs)
    gen_state = torch.random.get_rng_state()
    losses = agent.sf_losses(b, z, next_phi)
    torch.random.set_rng_state(gen_state)  # the same noise for the hand computation's next action
    from dvfb.nets import training_action

    with torch.no_grad():
        a_next = training_action(agent.actor(b.next_obs, z), 0.2, 0.3)
        t = agent.successor_target(b.next_obs, a_next, z)  # (2, N, d)
        psi = agent.successor_map(b.obs, b.action, z)
    total = 0.0
    for k in range(2):
        for i in range(N):
            v = [float(t[h, i] @ z[i]) for h in range(2)]
            picked = t[0 if v[0] <= v[1] else 1, i]
            y = next_phi[i].detach() + 0.99 * picked
            total += (float(psi[k, i] @ z[i]) - float(y @ z[i])) ** 2 / N
    assert float(losses["sf_loss"].detach()) == pytest.approx(total, rel=1e-10)


def test_the_td_loss_does_not_train_the_features_and_the_feature_loss_not_psi():
    agent, b = tiny_agent("lra_p"), random_batch(5)
    z = agent.sample_skill(N).double()
    losses = agent.sf_losses(b, z, agent.features(b.next_obs))
    grads = torch.autograd.grad(losses["sf_loss"], list(agent.feature_learner.parameters()), allow_unused=True)
    assert all(g is None for g in grads)
    grads = torch.autograd.grad(losses["feature_loss"], list(agent.successor_map.parameters()), allow_unused=True)
    assert all(g is None for g in grads)


def test_training_skills_replace_a_share_by_the_pseudo_inverse_of_the_feature_covariance():
    agent = tiny_agent("lap", mix_ratio=1.0)
    phi = agent.features(random_batch(6).next_obs).detach()
    agent.use_generator(torch.Generator().manual_seed(3))
    z = agent.feature_skills(phi)
    g = torch.Generator().manual_seed(3)
    torch.randn(N, D, generator=g)  # the prior draw comes first
    perm = torch.randperm(N, generator=g)
    cov = phi[perm].T @ phi[perm] / N
    want = phi[perm] @ torch.linalg.pinv(cov)
    want = math.sqrt(D) * want / want.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(z, want, rtol=1e-8, atol=1e-8)
    agent.config.mix_ratio = 0.0
    assert torch.allclose(agent.feature_skills(phi).norm(dim=-1), torch.full((N,), math.sqrt(D), dtype=phi.dtype))


def test_the_regression_recovers_a_planted_linear_reward():
    g = torch.Generator().manual_seed(0)
    features = torch.randn(500, D, generator=g)
    w = torch.randn(D, generator=g)
    z = regress_task_vector(features, features @ w)
    torch.testing.assert_close(z, math.sqrt(D) * w / w.norm(), rtol=1e-5, atol=1e-5)
    # Through the agent: a reward linear in phi(s') gives back its direction.
    agent = SFAgent(OBS, ACT, SFConfig(z_dim=D, hidden_dim=H, feature_dim=E_, backward_hidden_dim=H, batch_size=N))
    obs, next_obs = torch.randn(400, OBS, generator=g), torch.randn(400, OBS, generator=g)
    reward = agent.features(next_obs).detach() @ w
    z, info = agent.model.infer_skill(obs, next_obs, reward.unsqueeze(-1), None)
    assert info["fallback"] is None
    torch.testing.assert_close(z, math.sqrt(D) * w / w.norm(), rtol=1e-4, atol=1e-4)


def test_the_family_uses_the_regression_protocol_and_a_fresh_task_critic():
    zero_shot, finetuner = protocols_of("sf")
    assert zero_shot.name == "feature_regression" and finetuner.name == "dual_value"
    config = tiny_run_config("sf")
    assert config.finetune.eta == 0.0 and config.finetune.reward_mapping is False


@pytest.mark.parametrize("features", sorted(FEATURE_LEARNERS))
def test_every_variant_updates_and_resumes_its_state(features):
    config = merge(tiny_run_config("sf"), {"sf": {"features": features}})
    agent = make_agent("sf", 4, 2, config)
    replay = filled_replay(agent)
    before = {k: v.clone() for k, v in agent.state_dict().items()}
    metrics = agent.update(agent.replay_needs().sample(replay))
    assert all(torch.isfinite(v) for v in metrics.values())
    changed = {k.split(".")[0] for k, v in agent.state_dict().items() if not torch.equal(before[k], v)}
    assert {"actor", "successor_map", "successor_target", "feature_learner"} <= changed
    clone = make_agent("sf", 4, 2, config)
    clone.load_training_state(agent.training_state())
    for k, v in agent.state_dict().items():
        assert torch.equal(v, clone.state_dict()[k])
