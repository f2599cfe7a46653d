"""BeCL and ComSD: losses and rewards against hand computations, their skill priors, and
agent-level updates (tiny widths, one CPU thread)."""

from __future__ import annotations

import math

import pytest
import torch
from torch.testing import assert_close

from dvfb.agents.becl import BeCLAgent, BeCLConfig
from dvfb.agents.comsd import ComSDAgent, ComSDConfig
from dvfb.agents.ddpg import DDPGConfig
from dvfb.data import Batch
from dvfb.rewards.becl import BeCLReward, becl_contrastive_loss
from dvfb.rewards.comsd import ComSDReward, diversity_reward, skill_weight
from tiny import ACT, OBS, skill_batch

H, B = 32, 32


def one_hot_skills(n: int, dim: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.one_hot(torch.randint(0, dim, (n,), generator=g), dim).float()


def box_skills(n: int, dim: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, dim, generator=torch.Generator().manual_seed(seed))


# BeCL ------------------------------------------------------------------------------------------

def becl_loss_by_hand(features: torch.Tensor, labels: list[int], temperature: float):
    """Row by row, literally as the recipe reads: drop the anchor from its row, divide by T,
    subtract the row max, exponentiate, pick the first same-label entry of the reduced row (else
    its entry 0). Returns the losses and the chosen positives as indices of the full batch."""
    n = features.shape[0]
    u = [f / f.norm() for f in features]
    losses, chosen = [], []
    for i in range(n):
        others = [j for j in range(n) if j != i]
        s = torch.stack([torch.dot(u[i], u[j]) / temperature for j in others])
        e = torch.exp(s - s.max())
        pick = 0
        for position, j in enumerate(others):
            if labels[j] == labels[i]:
                pick = position
                break
        chosen.append(others[pick])
        losses.append(-torch.log(e[pick] / (e.sum() + 1e-6) + 1e-6))
    return torch.stack(losses).unsqueeze(1), chosen


def test_becl_positive_selection_on_a_planted_batch():
    # Skills 5, 2 and 4 have a single member: anchor 0 (a singleton) falls back to row 1 (entry 0 of
    # its reduced row), anchors 3 and 7 to row 0. Skill 0 has members 2, 5, 6: each picks the first
    # other member, so 5 and 6 both pick 2 and 2 picks 5.
    labels = [5, 1, 0, 2, 1, 0, 0, 4]
    features = torch.randn(8, 16, generator=torch.Generator().manual_seed(1))
    expected, chosen = becl_loss_by_hand(features, labels, 0.5)
    assert chosen == [1, 4, 5, 0, 1, 2, 2, 0]
    got = becl_contrastive_loss(features, torch.tensor(labels), 0.5)
    assert got.shape == (8, 1)
    assert_close(got, expected)
    # The positive is not the best same-skill match but the first one: moving a duplicate of
    # anchor 6's feature onto row 5 (a later member than 2) must not change anchor 6's positive.
    planted = features.clone()
    planted[5] = planted[6]
    expected, chosen = becl_loss_by_hand(planted, labels, 0.5)
    assert chosen[6] == 2
    assert_close(becl_contrastive_loss(planted, torch.tensor(labels), 0.5), expected)


def test_becl_loss_on_a_random_batch_and_other_temperature():
    z = one_hot_skills(B, 16, seed=2)
    features = torch.randn(B, 16, generator=torch.Generator().manual_seed(3))
    labels = z.argmax(-1)
    for t in (0.5, 2.0):
        expected, _ = becl_loss_by_hand(features, labels.tolist(), t)
        assert_close(becl_contrastive_loss(features, labels, t), expected)


def test_becl_loss_gradient_is_finite():
    # The diagonal is masked with -inf: it must not leak NaN into the gradient.
    features = torch.randn(B, 16, generator=torch.Generator().manual_seed(4), requires_grad=True)
    becl_contrastive_loss(features, one_hot_skills(B, 16).argmax(-1), 0.5).mean().backward()
    assert torch.isfinite(features.grad).all() and features.grad.abs().sum() > 0


def test_becl_reward_module_update_and_score_by_hand():
    torch.manual_seed(0)
    config = BeCLConfig(hidden_dim=H)
    module = BeCLReward(OBS, 16, config)
    module.make_optimizer(config.lr, fused=False)
    assert [m.out_features for m in module.net.embed if isinstance(m, torch.nn.Linear)] == [H, H, 16]
    assert [m.out_features for m in module.net.project_head if isinstance(m, torch.nn.Linear)] == [H, 16]
    batch = skill_batch(B, one_hot_skills(B, 16), seed=5, step=None, reward="zeros")
    labels = batch.z.argmax(-1).tolist()
    with torch.no_grad():
        # f is applied to s_{t+n} (batch.next_obs), never to s_t.
        before, _ = becl_loss_by_hand(module.net.project_head(module.net.embed(batch.next_obs)), labels, 0.5)
    weights = [p.detach().clone() for p in module.parameters()]
    metrics = module.update(batch)
    assert_close(metrics["contrastive_loss"], before.mean())
    assert all(not torch.equal(w, p) for w, p in zip(weights, module.parameters()))
    reward = module.score(batch)
    with torch.no_grad():
        after, _ = becl_loss_by_hand(module.net(batch.next_obs), labels, 0.5)
    assert reward.shape == (B, 1) and not reward.requires_grad
    assert_close(reward, torch.exp(-after))
    assert ((reward > 0) & (reward <= 1)).all()


def tiny_becl(seed: int = 0) -> BeCLAgent:
    torch.manual_seed(seed)
    return BeCLAgent(OBS, ACT, DDPGConfig(hidden_dim=H, batch_size=B), BeCLConfig(hidden_dim=H))


def test_becl_skill_prior():
    agent = tiny_becl()
    assert (agent.skill.kind, agent.skill.dim, agent.skill.every, agent.skill.at_episode_start) == \
        ("one_hot", 16, 50, True)
    z = agent.sample_skill(500, generator=torch.Generator().manual_seed(0))
    assert z.shape == (500, 16) and z.dtype == torch.float32
    assert torch.equal(z.sum(-1), torch.ones(500)) and set(z.unique().tolist()) == {0.0, 1.0}
    assert (z.sum(0) > 0).all()  # every skill is drawn


def test_becl_agent_update_runs_three_contrastive_steps_on_fresh_batches():
    agent = tiny_becl()
    needs = agent.replay_needs()
    assert needs.batch_size == 3 * B and needs.nstep == 3
    twin = tiny_becl()  # the same initial weights, updated by hand below
    assert all(torch.equal(p, q) for p, q in zip(agent.intrinsic.parameters(), twin.intrinsic.parameters()))
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    for i in range(3):
        batch = skill_batch(3 * B, one_hot_skills(3 * B, 16, seed=10 + i), seed=20 + i, step=None, reward="zeros")
        metrics = agent.update(batch)
        parts = batch.chunk(3)
        for part in parts:
            twin.intrinsic.update(part)
        # Each chunk got its contrastive step, in order ...
        assert all(torch.equal(p, q) for p, q in zip(agent.intrinsic.parameters(), twin.intrinsic.parameters()))
        # ... and the last chunk, scored after the three steps, fed the DDPG step.
        assert_close(metrics["reward"], agent.intrinsic.score(parts[-1]).mean())
    steps = {int(s["step"]) for s in agent.intrinsic.optimizer.state.values()}
    assert steps == {9}  # 3 agent updates x 3 contrastive steps
    assert {int(s["step"]) for s in agent.core.critic_optimizer.state.values()} == {3}
    assert {"contrastive_loss", "critic_loss", "actor_loss", "reward"} <= set(metrics)
    assert all(isinstance(v, torch.Tensor) and v.dim() == 0 and torch.isfinite(v) for v in metrics.values())
    optimised = {id(p) for opt in agent.optimizers().values() for g in opt.param_groups for p in g["params"]}
    for name, p in agent.named_parameters():
        if id(p) in optimised:
            assert not torch.equal(before[name], p), name


# ComSD -----------------------------------------------------------------------------------------

def encodings(module: ComSDReward, batch: Batch):
    """g(s'), the transition keys and the skill queries, called layer by layer."""
    enc = module.encoders
    g_obs, g_next = enc.state_net(batch.obs), enc.state_net(batch.next_obs)
    key = enc.transition_net(torch.cat([g_obs, g_next], dim=-1))
    return g_next, key, enc.skill_net(batch.z)


def nce_by_hand(query: torch.Tensor, key: torch.Tensor, t: float) -> torch.Tensor:
    n = query.shape[0]
    q = [v / v.norm() for v in query]
    k = [v / v.norm() for v in key]
    losses = []
    for i in range(n):
        pos = torch.exp(torch.dot(q[i], k[i]) / t)
        total = sum(torch.exp(torch.dot(q[i], k[j]) / t) for j in range(n))
        neg = torch.clamp(total - math.exp(1 / t), min=1e-6)
        losses.append(-torch.log(pos / (neg + 1e-6)))
    return torch.stack(losses).mean()


def apt_cic_first_call_by_hand(rep: torch.Tensor, k: int, clip: float) -> torch.Tensor:
    """k nearest distances (self included) of every row, divided by the running variance after
    its first update from the (M, S, n) = (0, 1, 1e-4) prior, clipped, averaged, log(1 + .)."""
    n = rep.shape[0]
    rows = []
    for i in range(n):
        d = sorted(float((rep[i] - rep[j]).norm()) for j in range(n))
        rows.append(d[:k])
    x = torch.tensor(rows, dtype=torch.float64)
    b, count = x.numel(), 1e-4
    mu, var = x.mean(), x.var(unbiased=True)
    s = (1.0 * count + var * b + mu ** 2 * count * b / (count + b)) / (count + b)
    value = (x / s - clip).clamp_min(0.0).mean(dim=1, keepdim=True)
    return torch.log1p(value).float()


def test_comsd_config_extends_cic():
    c = ComSDConfig()
    assert (c.skill_dim, c.skill_every, c.temperature, c.knn_k, c.knn_clip, c.knn_rms) == (64, 50, 0.5, 16, 5e-4, True)
    assert (c.weight_low, c.weight_high, c.weight_mapping, c.hidden_dim, c.lr) == (0.5, 1.0, "first", 1024, 1e-4)


def test_comsd_skill_weight_and_diversity_reward_by_hand():
    z = box_skills(B, 64, seed=6)
    assert_close(skill_weight(z, 0.5, 1.0), torch.stack([0.5 + 0.5 * row[0] for row in z]).unsqueeze(1))
    assert_close(skill_weight(z, 0.5, 1.0, "mean"), torch.stack([0.5 + 0.5 * row.mean() for row in z]).unsqueeze(1))
    corners = torch.stack([torch.zeros(64), torch.ones(64)])
    assert_close(skill_weight(corners, 0.5, 1.0), torch.tensor([[0.5], [1.0]]))
    with pytest.raises(ValueError):
        skill_weight(z, 0.5, 1.0, "norm")
    g = torch.Generator().manual_seed(7)
    query, key = torch.randn(B, 64, generator=g), torch.randn(B, 64, generator=g)
    expected = torch.stack([torch.exp(torch.dot(q / q.norm(), k / k.norm()) / 0.5) for q, k in zip(query, key)])
    got = diversity_reward(query, key, 0.5)
    assert got.shape == (B, 1)
    assert_close(got, expected.unsqueeze(1))
    assert ((got >= math.exp(-2) - 1e-5) & (got <= math.exp(2) + 1e-5)).all()


@pytest.mark.parametrize("mapping", ["first", "mean"])
def test_comsd_reward_module_update_and_score_by_hand(mapping):
    torch.manual_seed(0)
    config = ComSDConfig(hidden_dim=H, knn_k=4, weight_mapping=mapping)
    module = ComSDReward(OBS, 64, config)
    module.make_optimizer(config.lr, fused=False)
    batch = skill_batch(B, box_skills(B, 64, seed=8), seed=9, step=None, reward="zeros")
    with torch.no_grad():
        _, key, query = encodings(module, batch)
        nce_before = nce_by_hand(query, key, 0.5)
    metrics: dict = {}
    reward = module.update_and_score(batch, metrics)
    # The update is CIC's NCE step ...
    assert_close(metrics["nce_loss"], nce_before)
    # ... and the reward uses the updated encoders: APT on g(s') plus beta(z) times exp(q.kappa/T).
    with torch.no_grad():
        g_next, key, query = encodings(module, batch)
    r_exp = apt_cic_first_call_by_hand(g_next, 4, 5e-4)
    r_div = torch.stack([torch.exp(torch.dot(q / q.norm(), k / k.norm()) / 0.5) for q, k in zip(query, key)])
    m = batch.z[:, 0] if mapping == "first" else batch.z.mean(-1)
    beta = 0.5 + 0.5 * m
    assert reward.shape == (B, 1) and not reward.requires_grad
    assert_close(reward, r_exp + (beta * r_div).unsqueeze(1))
    assert_close(metrics["exploration_reward"], r_exp.mean())
    assert_close(metrics["diversity_reward"], r_div.mean())
    # The running variance was advanced once, with the B * k kept distances.
    assert module.entropy.stats.count.item() == pytest.approx(1e-4 + B * 4)


def test_comsd_rejects_an_unknown_weight_mapping():
    with pytest.raises(ValueError):
        ComSDReward(OBS, 64, ComSDConfig(hidden_dim=H, weight_mapping="norm"))


def tiny_comsd(seed: int = 0) -> ComSDAgent:
    torch.manual_seed(seed)
    return ComSDAgent(OBS, ACT, DDPGConfig(hidden_dim=H, batch_size=B), ComSDConfig(hidden_dim=H, knn_k=4))


def test_comsd_skill_prior():
    agent = tiny_comsd()
    s = agent.skill
    assert (s.kind, s.dim, s.every, s.at_episode_start, s.low, s.high) == ("box", 64, 50, True, 0.0, 1.0)
    z = agent.sample_skill(500, generator=torch.Generator().manual_seed(0))
    assert z.shape == (500, 64) and z.dtype == torch.float32
    assert (z >= 0).all() and (z <= 1).all()
    assert abs(z.mean().item() - 0.5) < 0.02 and z.min() < 0.01 and z.max() > 0.99


def test_comsd_agent_update():
    agent = tiny_comsd()
    assert agent.replay_needs().batch_size == B and agent.replay_needs().nstep == 3
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    for i in range(3):
        metrics = agent.update(skill_batch(B, box_skills(B, 64, seed=30 + i), seed=40 + i, step=None, reward="zeros"))
    assert {"nce_loss", "exploration_reward", "diversity_reward", "critic_loss", "actor_loss", "reward"} <= set(metrics)
    assert all(isinstance(v, torch.Tensor) and v.dim() == 0 and torch.isfinite(v) for v in metrics.values())
    assert {int(s["step"]) for s in agent.intrinsic.optimizer.state.values()} == {3}
    optimised = {id(p) for opt in agent.optimizers().values() for g in opt.param_groups for p in g["params"]}
    assert len(optimised) > 0
    for name, p in agent.named_parameters():
        if id(p) in optimised:
            assert not torch.equal(before[name], p), name
