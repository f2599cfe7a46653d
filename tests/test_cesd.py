"""CeSD (docs/methods.md, "CeSD"): the partitioned reward on planted clusters, the cluster draws,
the prototype loss with Sinkhorn, the ensemble critic, its masked critic loss and per-skill actor
loss, the unmasked (fine-tuning) update, the agent's update order and the URLB fine-tuner on it.
Every expectation is computed by hand with plain loops."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torch.nn import functional as F_nn

from dvfb.agents.cesd import CeSDAgent, CeSDConfig, CeSDCore, EnsembleCritic
from dvfb.agents.ddpg import DDPGConfig
from dvfb.agents.registry import get_spec
from dvfb.nets import RunningMeanStd
from dvfb.protocols.urlb import DDPGFinetuneConfig, DDPGFinetuner
from dvfb.rewards.cesd import CeSDReward, partitioned_apt_reward
from tiny import ACT, OBS, skill_batch

K = 4
TINY = dict(hidden_dim=32, critic_trunk_dim=16, critic_hidden_dim=32)


def one_hot_skills(n: int, generator: torch.Generator) -> torch.Tensor:
    """One-hot skills of K, drawn from a batch's generator (tiny.skill_batch)."""
    return F_nn.one_hot(torch.randint(0, K, (n,), generator=generator), K).float()


def tiny_core(skills: int = K) -> CeSDCore:
    torch.manual_seed(0)
    core = CeSDCore(OBS, skills, ACT, DDPGConfig(hidden_dim=32, batch_size=32, fused_adam=False),
                    trunk_dim=16, head_hidden_dim=32)
    core.make_optimizers()
    return core


def tiny_agent(**overrides) -> CeSDAgent:
    torch.manual_seed(0)
    config = CeSDConfig(**{**TINY, "skill_dim": K, "knn_k": 3, **overrides})
    return CeSDAgent(OBS, ACT, DDPGConfig(hidden_dim=32, batch_size=32, fused_adam=False), config)


# ---------------------------------------------------------------------------------------------
# The partitioned reward, given the cluster assignment


class HandRMS:
    """§0.3's tracker in Python floats."""

    def __init__(self, mean=0.0, var=1.0, count=1e-4):
        self.mean, self.var, self.count = mean, var, count

    def update(self, values: list[float]) -> float:
        b = len(values)
        mu = sum(values) / b
        v = sum((x - mu) ** 2 for x in values) / (b - 1)
        delta = mu - self.mean
        total = self.count + b
        self.mean = self.mean + delta * b / total
        self.var = (self.var * self.count + v * b + delta ** 2 * self.count * b / total) / total
        self.count = total
        return self.var


def hand_partitioned_reward(rep, cluster, skill, num_clusters, k, clip, factor, rms: HandRMS | None):
    n = rep.shape[0]
    reward = [0.0] * n
    for i in range(num_clusters):  # the official loop, in index order
        members = [j for j in range(n) if int(cluster[j]) == i]
        if len(members) <= k:
            continue
        nearest = {}
        for a in members:
            d = sorted(math.sqrt(sum((float(rep[a, c]) - float(rep[b, c])) ** 2 for c in range(rep.shape[1])))
                       for b in members)
            nearest[a] = d[:k]
        scale = rms.update([x for a in members for x in nearest[a]]) if rms is not None else 1.0
        off = sum(1 for a in members if int(skill[a]) != i)
        for a in members:
            entropy = math.log(1.0 + sum(max(x / scale - clip, 0.0) for x in nearest[a]) / k)
            reward[a] = entropy + factor / (1.0 + off)
    return torch.tensor(reward, dtype=torch.float32).unsqueeze(1)


def planted_clusters(sizes: list[int], seed: int = 0) -> torch.Tensor:
    cluster = torch.cat([torch.full((s,), i) for i, s in enumerate(sizes)])
    return cluster[torch.randperm(len(cluster), generator=torch.Generator().manual_seed(seed))]


@pytest.mark.parametrize("k", [16, 3])
def test_partitioned_reward_by_hand(k):
    # Cluster sizes straddle the threshold: > k is rewarded, exactly k (and fewer) is not; one is empty.
    sizes = [20, 17, 16, 7, 0] if k == 16 else [5, 3, 4, 1, 0]
    cluster = planted_clusters(sizes)
    n, num = len(cluster), len(sizes)
    g = torch.Generator().manual_seed(1)
    rep = torch.randn(n, 3, generator=g) * 2.0 + 1.0
    skill = torch.where(torch.rand(n, generator=g) < 0.6, cluster, torch.randint(0, num, (n,), generator=g))
    stats = RunningMeanStd()
    stats.update(torch.rand(50, generator=g) * 3)  # a non-trivial prior state
    rms = HandRMS(float(stats.mean), float(stats.var), float(stats.count))
    for call in range(2):  # the tracker carries over between calls
        reward, metrics = partitioned_apt_reward(rep, cluster, skill, num, k, 5e-4, 0.7, stats)
        expected = hand_partitioned_reward(rep, cluster, skill, num, k, 5e-4, 0.7, rms)
        torch.testing.assert_close(reward, expected, rtol=1e-5, atol=1e-6)
        assert float(stats.mean) == pytest.approx(rms.mean, rel=1e-6)
        assert float(stats.var) == pytest.approx(rms.var, rel=1e-6)
        assert float(stats.count) == pytest.approx(rms.count, rel=1e-12)
        assert float(metrics["scored_clusters"]) == sum(s > k for s in sizes)
        assert float(metrics["off_cluster_fraction"]) == pytest.approx(float((skill != cluster).float().mean()))
        rep = rep + 0.3 * call


def test_partitioned_reward_small_clusters_and_no_normalisation():
    cluster = planted_clusters([6, 2, 2])
    g = torch.Generator().manual_seed(2)
    rep = torch.randn(10, 4, generator=g)
    skill = torch.randint(0, 3, (10,), generator=g)
    reward, _ = partitioned_apt_reward(rep, cluster, skill, 3, 4, 0.0, 1.0, None)
    expected = hand_partitioned_reward(rep, cluster, skill, 3, 4, 0.0, 1.0, None)
    torch.testing.assert_close(reward, expected, rtol=1e-5, atol=1e-6)
    assert (reward[cluster != 0] == 0).all() and (reward[cluster == 0] > 0).all()
    # No cluster is large enough: all zeros and the tracker does not move.
    stats = RunningMeanStd()
    reward, metrics = partitioned_apt_reward(rep, cluster, skill, 3, 6, 5e-4, 1.0, stats)
    assert (reward == 0).all() and float(metrics["scored_clusters"]) == 0
    assert float(stats.var) == pytest.approx(1.0) and float(stats.mean) == pytest.approx(0.0)
    assert float(stats.count) == pytest.approx(1e-4)


def test_reward_clusters_and_losses_never_read_values_back_to_the_host():
    """Dynamo traces them as single graphs: an .item(), a bool(tensor) or a Python branch on a
    tensor value would be a graph break, an error with fullgraph (a sync on a GPU)."""
    module = tiny_reward()
    batch = skill_batch(32, one_hot_skills, step=None)
    reward, cluster, _, _ = torch.compile(module.score_and_assign, fullgraph=True, backend="eager")(batch)
    assert reward.shape == (32, 1) and cluster.shape == (32,)
    core = tiny_core()
    mask = torch.arange(K).unsqueeze(1) == cluster.unsqueeze(0)
    loss = torch.compile(core.critic_loss, fullgraph=True, backend="eager")(batch, batch.z, reward, mask=mask)
    assert torch.isfinite(loss)
    assert torch.isfinite(torch.compile(core.actor_loss, fullgraph=True, backend="eager")(batch.obs, batch.z))
    assert torch.isfinite(torch.compile(module.prototype_loss, fullgraph=True, backend="eager")(batch))


# ---------------------------------------------------------------------------------------------
# Clusters, prototypes and Sinkhorn


def tiny_reward(**kw) -> CeSDReward:
    torch.manual_seed(0)
    config = CeSDConfig(**{**TINY, "skill_dim": K, "knn_k": 3})
    module = CeSDReward(OBS, K, config, **kw)
    module.make_optimizer(1e-3, fused=False)
    return module


def test_cluster_probabilities_and_draws():
    module = tiny_reward()
    with torch.no_grad():
        module.protos.weight.mul_(torch.tensor([[2.0], [0.5], [3.0], [1.5]]))  # rows off the unit sphere
    rep = torch.tensor([[1.0, 0.0, 2.0, -1.0], [0.0, 3.0, -1.0, 0.5]])
    c = module.protos.weight / module.protos.weight.norm(dim=1, keepdim=True)
    expected = []
    for r in rep:
        u = r / r.norm()
        expected.append(torch.softmax(torch.stack([c[j] @ u for j in range(K)]) / 0.1, dim=0))
    expected = torch.stack(expected)
    draws = module.assign(rep.repeat_interleave(20000, dim=0))
    torch.testing.assert_close(module.protos.weight.norm(dim=1), torch.ones(K))  # re-normalised in place
    with torch.no_grad():
        torch.testing.assert_close(torch.softmax(module.cluster_scores(rep), dim=1), expected)
    for row in range(2):
        freq = torch.bincount(draws[row * 20000:(row + 1) * 20000], minlength=K).float() / 20000
        torch.testing.assert_close(freq, expected[row], atol=0.015, rtol=0)


def hand_sinkhorn(scores: torch.Tensor, iters: int) -> torch.Tensor:
    """§11's Sinkhorn on an (N, P) score matrix (already divided by T), in float64 with loops."""
    n, p = scores.shape
    top = max(float(x) for x in scores.flatten())
    q = [[math.exp(float(scores[i, j]) - top) for i in range(n)] for j in range(p)]  # (P, N)
    finite = max(x for row in q for x in row if math.isfinite(x))
    q = [[x if math.isfinite(x) else finite for x in row] for row in q]
    total = sum(map(sum, q))
    q = [[x / total for x in row] for row in q]
    for _ in range(iters):
        for j in range(p):
            s = sum(q[j])
            q[j] = [x * (1.0 / p) / s for x in q[j]]
        for i in range(n):
            s = sum(q[j][i] for j in range(p))
            for j in range(p):
                q[j][i] *= (1.0 / n) / s
    for i in range(n):
        s = sum(q[j][i] for j in range(p))
        for j in range(p):
            q[j][i] /= s
    return torch.tensor(q, dtype=torch.float64).T


def test_prototype_loss_by_hand_and_only_the_prototypes_learn():
    module = tiny_reward(proto_temperature=0.1, sinkhorn_iters=6)
    batch = skill_batch(12, one_hot_skills, step=None)
    with torch.no_grad():
        module.protos.weight.mul_(1.7)
    loss = module.prototype_loss(batch)
    c = module.protos.weight.detach()
    assert torch.allclose(c.norm(dim=1), torch.ones(K))
    with torch.no_grad():
        g_s = module.encoders.state_net(batch.obs)
        g_t = module.encoders.state_net(batch.next_obs)
    scores_t = torch.stack([torch.stack([c[j] @ (g_t[i] / g_t[i].norm()) for j in range(K)])
                            for i in range(12)]) / 0.1
    q = hand_sinkhorn(scores_t, 6)
    expected = 0.0
    for i in range(12):
        logits = [float(c[j] @ (g_s[i] / g_s[i].norm())) / 0.1 for j in range(K)]
        log_z = math.log(sum(math.exp(x) for x in logits))
        expected -= sum(float(q[i, j]) * (logits[j] - log_z) for j in range(K))
    expected /= 12
    assert float(loss.detach()) == pytest.approx(expected, rel=1e-5)
    # The repository's Sinkhorn is §11's (the inf replacement never fires on unit-norm scores).
    from dvfb.rewards.proto import sinkhorn_knopp

    torch.testing.assert_close(sinkhorn_knopp(scores_t, 6).double(), q, rtol=1e-5, atol=1e-7)
    # Only C is trained by this loss; g stays as it is.
    encoders = {n: p.detach().clone() for n, p in module.encoders.named_parameters()}
    protos = module.protos.weight.detach().clone()
    module.update_prototypes(batch)
    assert all(torch.equal(p, encoders[n]) for n, p in module.encoders.named_parameters())
    assert not torch.equal(module.protos.weight, protos)


# ---------------------------------------------------------------------------------------------
# The ensemble critic and the core's losses


def test_ensemble_critic_is_32_small_mlps_with_the_right_init():
    torch.manual_seed(0)
    critic = EnsembleCritic(OBS, ACT, 16, 32, 16)
    obs, action = torch.randn(7, OBS), torch.rand(7, ACT)
    q = critic(obs, None, action)
    assert q.shape == (2, 16, 7, 1)
    lin, ln = critic.trunk[0], critic.trunk[1]
    h = torch.tanh(F_nn.layer_norm(torch.cat([obs, action], 1) @ lin.weight.T + lin.bias, (16,), ln.weight, ln.bias))
    heads = critic.heads
    for t in range(2):
        for k in range(16):
            m = t * 16 + k
            w1 = heads.first.weight[m * 32:(m + 1) * 32]
            b1 = heads.first.bias[m * 32:(m + 1) * 32]
            for i in range(7):
                hidden = torch.relu(w1 @ h[i] + b1)
                value = hidden @ heads.second_weight[m, :, 0] + heads.second_bias[m, 0, 0]
                torch.testing.assert_close(q[t, k, i, 0], value, rtol=1e-5, atol=1e-6)
    # Trunk: orthogonal columns (16 x 8 weight), zero bias. Members: PyTorch's default Linear init.
    torch.testing.assert_close(lin.weight.T @ lin.weight, torch.eye(OBS + ACT), rtol=0, atol=1e-5)
    assert (lin.bias == 0).all()
    assert heads.first.weight.abs().max() <= 1 / math.sqrt(16) and heads.first.bias.abs().max() <= 1 / math.sqrt(16)
    assert heads.second_weight.abs().max() <= 1 / math.sqrt(32) and heads.second_bias.abs().max() <= 1 / math.sqrt(32)
    assert heads.first.bias.abs().min() > 0 and heads.second_bias.abs().min() > 0


def replayed_next_values(core, batch, seed):
    """The target members min(Q1'_k, Q2'_k)(s', a') with a' replayed from ``seed``, (K, N)."""
    torch.manual_seed(seed)
    with torch.no_grad():
        mean = core.actor(batch.next_obs, batch.z)
        noise = (torch.randn_like(mean) * 0.2).clamp(-0.3, 0.3)
        next_action = (mean + noise).clamp(-1 + 1e-6, 1 - 1e-6)
        target = core.critic_target(batch.next_obs, batch.z, next_action)
    return torch.minimum(target[0], target[1])[..., 0]


def hand_critic_loss(core, batch, mask, seed):
    n = batch.obs.shape[0]
    next_v = replayed_next_values(core, batch, seed)
    with torch.no_grad():
        q = core.critic(batch.obs, batch.z, batch.action)
    total = 0.0
    for t in range(2):
        acc = 0.0
        for k in range(K):
            for i in range(n):
                m = 1.0 if mask is None else float(mask[k, i])
                y = float(batch.reward[i, 0]) + float(batch.discount[i, 0]) * float(next_v[k, i])
                acc += (m * float(q[t, k, i, 0]) - m * y) ** 2
        total += acc / (K * n)
    return total


def test_masked_and_unmasked_critic_loss_by_hand():
    core = tiny_core()
    batch = skill_batch(12, one_hot_skills, step=None)
    cluster = planted_clusters([5, 0, 4, 3])
    mask = torch.arange(K).unsqueeze(1) == cluster.unsqueeze(0)
    for m in (mask, None):
        torch.manual_seed(3)
        loss = core.critic_loss(batch, batch.z, batch.reward, mask=m)
        assert float(loss.detach()) == pytest.approx(hand_critic_loss(core, batch, m, 3), rel=1e-5)


def test_actor_loss_uses_the_head_of_each_skill():
    core = tiny_core()
    batch = skill_batch(12, one_hot_skills, step=None)
    torch.manual_seed(4)
    loss = core.actor_loss(batch.obs, batch.z)
    torch.manual_seed(4)
    with torch.no_grad():
        mean = core.actor(batch.obs, batch.z)
        action = (mean + (torch.randn_like(mean) * 0.2).clamp(-0.3, 0.3)).clamp(-1 + 1e-6, 1 - 1e-6)
        q = core.critic(batch.obs, batch.z, action)
    expected = 0.0
    for i in range(12):
        k = int(batch.z[i].argmax())
        expected -= min(float(q[0, k, i, 0]), float(q[1, k, i, 0]))
    assert float(loss.detach()) == pytest.approx(expected / (K * 12), rel=1e-5)


def head_slices(critic):
    heads = critic.heads
    h = heads.hidden_dim
    return [(heads.first.weight[m * h:(m + 1) * h].detach().clone(), heads.second_weight[m].detach().clone(),
             heads.second_bias[m].detach().clone()) for m in range(heads.num_heads)]


def changed_heads(before, after):
    return {m for m, (b, a) in enumerate(zip(before, after)) if any(not torch.equal(x, y) for x, y in zip(b, a))}


def test_update_without_mask_regresses_every_head_and_a_mask_only_its_clusters():
    core = tiny_core()
    batch = skill_batch(12, one_hot_skills, step=None)
    expected = hand_critic_loss(core, batch, None, 7)
    before = head_slices(core.critic)
    metrics = {}
    torch.manual_seed(7)
    core.update(batch, batch.reward, metrics)  # the fine-tuner's call
    assert float(metrics["critic_loss"]) == pytest.approx(expected, rel=1e-5)
    assert changed_heads(before, head_slices(core.critic)) == set(range(2 * K))
    # With a mask, only the members of occupied clusters (here cluster 2: member 2 of Q1 and of Q2) learn.
    core = tiny_core()
    before = head_slices(core.critic)
    mask = torch.zeros(K, 12, dtype=torch.bool)
    mask[2, :5] = True
    core.update(batch, batch.reward, {}, mask=mask)
    assert changed_heads(before, head_slices(core.critic)) == {2, K + 2}


# ---------------------------------------------------------------------------------------------
# The agent


def test_skill_prior_and_registration():
    agent = tiny_agent(skill_dim=16)
    z = agent.sample_skill(2000)
    assert z.shape == (2000, 16) and ((z == 0) | (z == 1)).all() and (z.sum(1) == 1).all()
    assert (z.sum(0) > 0).all()
    assert agent.skill.kind == "one_hot" and agent.skill.every == 50 and agent.skill.at_episode_start
    assert isinstance(agent.core, CeSDCore) and agent.core.critic.ensemble_size == 16
    spec = get_spec("cesd")
    assert spec.agent_cls is CeSDAgent and spec.sections["cesd"] is CeSDConfig
    assert spec.zero_shot == "skill_selection" and spec.finetuner == "urlb"
    default = CeSDConfig()
    assert (default.skill_dim, default.skill_every, default.temperature, default.proto_temperature,
            default.sinkhorn_iters, default.constraint_factor, default.knn_k, default.knn_clip, default.lr,
            default.critic_trunk_dim, default.critic_hidden_dim, default.hidden_dim) == \
        (16, 50, 0.5, 0.1, 6, 1.0, 16, 5e-4, 1e-4, 512, 1024, 1024)


def test_agent_update_changes_every_optimised_parameter():
    agent = tiny_agent()
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    optimised = {id(p) for opt in agent.optimizers().values() for group in opt.param_groups for p in group["params"]}
    for seed in range(3):
        metrics = agent.update(skill_batch(32, one_hot_skills, seed=seed, step=None))
    assert {"nce_loss", "proto_loss", "critic_loss", "actor_loss", "reward", "scored_clusters"} <= set(metrics)
    assert all(isinstance(v, torch.Tensor) and v.dim() == 0 and torch.isfinite(v) for v in metrics.values())
    for name, p in agent.named_parameters():
        if id(p) in optimised:
            assert not torch.equal(before[name], p), name
        else:
            assert not p.requires_grad, name


def test_agent_update_follows_cesds_order():
    """CIC step -> clusters and reward (with the updated g) -> critic -> actor -> prototypes -> EMA."""
    agent = tiny_agent()
    batch = skill_batch(32, one_hot_skills, step=None)
    manual = copy.deepcopy(agent)
    torch.manual_seed(11)
    metrics = agent.update(batch)
    torch.manual_seed(11)
    module, core = manual.intrinsic, manual.core
    module.update(batch)
    with torch.no_grad():
        rep = module.encoders.state_net(batch.next_obs)
    cluster = module.assign(rep)
    reward, _ = partitioned_apt_reward(rep, cluster, batch.z.argmax(1), K, 3, 5e-4, 1.0, module.entropy.stats)
    mask = torch.stack([cluster == k for k in range(K)])
    core.train_step(batch, reward, {}, mask=mask)
    proto_loss = module.prototype_loss(batch)
    module.step(proto_loss)
    core.update_target()
    assert float(metrics["proto_loss"]) == pytest.approx(float(proto_loss.detach()), rel=1e-6)
    assert float(metrics["reward"]) == pytest.approx(float(reward.mean()), rel=1e-6)
    for (n, p), (_, q) in zip(agent.state_dict().items(), manual.state_dict().items()):
        torch.testing.assert_close(p, q, rtol=1e-6, atol=1e-7, msg=n)


def test_urlb_finetuner_rebuilds_the_ensemble_and_trains_every_head():
    agent = tiny_agent()
    for seed in range(2):
        agent.update(skill_batch(32, one_hot_skills, seed=seed, step=None))
    pretrained = {k: v.clone() for k, v in agent.core.critic.state_dict().items()}
    skill = agent.sample_skill(1)[0]
    finetuner = DDPGFinetuner(agent.model, skill, DDPGFinetuneConfig())
    critic = agent.core.critic
    assert isinstance(critic, EnsembleCritic)
    for key, value in critic.state_dict().items():
        assert torch.equal(value, pretrained[key]) == key.startswith("trunk."), key
    before = head_slices(critic)
    metrics = finetuner.update(skill_batch(32, one_hot_skills, seed=5, step=None))
    assert torch.isfinite(metrics["critic_loss"]) and torch.isfinite(metrics["actor_loss"])
    assert changed_heads(before, head_slices(agent.core.critic)) == set(range(2 * K))
