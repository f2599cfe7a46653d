"""Tests for the intrinsic-reward modules in dvfb.rewards: the kNN particle entropy, Disagreement,
ICM-APT and Proto, each checked against hand computations on small fixed batches
(docs/methods.md, "Rewards")."""

import math

import pytest
import torch
from torch.nn import functional as F_nn

from dvfb.core.errors import ConfigError
from dvfb.nets import RunningMeanStd
from dvfb.data import Batch
from dvfb.rewards.disagreement import DisagreementConfig, DisagreementReward
from dvfb.rewards.icm import ICMAPTConfig, ICMAPTReward
from dvfb.rewards.knn import KNNConfig, ParticleEntropy, nearest_distances, particle_entropy
from dvfb.rewards.proto import ProtoConfig, ProtoReward, sample_one_per_row, sinkhorn_knopp
from tiny import random_batch

OBS, ACT = 4, 3


def loop_knn(rep: torch.Tensor, k: int) -> list[list[float]]:
    """The k smallest distances of every row to all rows (itself included), by plain loops."""
    rows = []
    for i in range(rep.shape[0]):
        d = sorted(math.sqrt(sum((float(rep[i, c]) - float(rep[j, c])) ** 2 for c in range(rep.shape[1])))
                   for j in range(rep.shape[0]))
        rows.append(d[:k])
    return rows


# ---------------------------------------------------------------------------------------------
# Particle entropy

# Four points on a line at 0, 1, 3, 7 (second coordinate 0). Sorted distances per row:
# p0: 0 1 3 7 | p1: 0 1 2 6 | p2: 0 2 3 4 | p3: 0 4 6 7
LINE = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [7.0, 0.0]])


def test_nearest_distances_hand_example():
    expected = torch.tensor([[0.0, 1, 3], [0, 1, 2], [0, 2, 3], [0, 4, 6]])
    torch.testing.assert_close(nearest_distances(LINE, LINE, 3), expected)
    # Against another set: targets at 2 and 5 only.
    target = torch.tensor([[2.0, 0.0], [5.0, 0.0]])
    expected = torch.tensor([[2.0, 5], [1, 4], [1, 2], [2, 5]])
    torch.testing.assert_close(nearest_distances(LINE, target, 2), expected)


def test_particle_entropy_hand_example_no_normaliser():
    # average, k = 2: means 0.5, 0.5, 1, 2
    r = particle_entropy(LINE, 2, average=True, clip=0.0, normaliser="none")
    torch.testing.assert_close(r, torch.log(torch.tensor([[1.5], [1.5], [2.0], [3.0]])))
    # k-th only, k = 3: 3, 2, 3, 6
    r = particle_entropy(LINE, 3, average=False, clip=0.0, normaliser="none")
    torch.testing.assert_close(r, torch.log(torch.tensor([[4.0], [3.0], [4.0], [7.0]])))
    # clip 1.5, average, k = 3: max(d - 1.5, 0) -> p0 (0,0,1.5) p1 (0,0,0.5) p2 (0,0.5,1.5) p3 (0,2.5,4.5)
    r = particle_entropy(LINE, 3, average=True, clip=1.5, normaliser="none")
    torch.testing.assert_close(r, torch.log1p(torch.tensor([[0.5], [0.5 / 3], [2.0 / 3], [7.0 / 3]])))
    # A negative clip disables the clip (URLB): plain mean (0+1+3)/3 etc.
    r = particle_entropy(LINE, 3, average=True, clip=-1.0, normaliser="none")
    torch.testing.assert_close(r, torch.log1p(torch.tensor([[4 / 3], [1.0], [5 / 3], [10 / 3]])))


def test_particle_entropy_k1_is_zero_through_self_inclusion():
    rep = torch.randn(7, 5, generator=torch.Generator().manual_seed(3)) * 10
    for average in (True, False):
        r = particle_entropy(rep, 1, average=average, clip=0.0, normaliser="none")
        assert r.shape == (7, 1)
        assert torch.equal(r, torch.zeros(7, 1))  # log(1 + 0): the row's own distance, exactly 0


def test_particle_entropy_mean_normaliser_hand_example():
    """PBE-URLB with rms: the statistic sees the N*k flattened distances, then divides them by M."""
    stats = RunningMeanStd()
    r = particle_entropy(LINE, 2, average=True, clip=0.0, normaliser="mean", stats=stats)
    # Flattened distances 0,1,0,1,0,2,0,4: batch mean 1, unbiased variance 14/7 = 2, b = 8.
    m = 1.0 * 8 / (1e-4 + 8)
    s = (1.0 * 1e-4 + 2.0 * 8 + 1.0 ** 2 * 1e-4 * 8 / (1e-4 + 8)) / (1e-4 + 8)
    assert stats.count.item() == pytest.approx(8 + 1e-4)
    assert stats.mean.item() == pytest.approx(m, rel=1e-12)
    assert stats.var.item() == pytest.approx(s, rel=1e-12)
    expected = torch.log1p(torch.tensor([[0.5], [0.5], [1.0], [2.0]]) / m)
    torch.testing.assert_close(r, expected)


def test_particle_entropy_var_normaliser_kth_hand_example():
    """APT-style division by the running variance; the k-th variant feeds only the N k-th distances."""
    stats = RunningMeanStd()
    r = particle_entropy(LINE, 3, average=False, clip=0.5, normaliser="var", stats=stats)
    # k-th distances 3, 2, 3, 6: mean 3.5, unbiased variance (0.25+2.25+0.25+6.25)/3 = 3, b = 4.
    n, b = 1e-4, 4
    s = (1.0 * n + 3.0 * b + 3.5 ** 2 * n * b / (n + b)) / (n + b)
    assert stats.count.item() == pytest.approx(b + n)
    assert stats.var.item() == pytest.approx(s, rel=1e-12)
    value = (torch.tensor([[3.0], [2.0], [3.0], [6.0]]) / s - 0.5).clamp_min(0.0)
    torch.testing.assert_close(r, torch.log1p(value))


@pytest.mark.parametrize("normaliser", ["none", "mean", "var"])
@pytest.mark.parametrize("average", [True, False])
def test_particle_entropy_matches_loops_on_random_batch(normaliser, average):
    rep = torch.randn(10, 5, generator=torch.Generator().manual_seed(1))
    k, clip = 4, 0.05
    stats = RunningMeanStd() if normaliser != "none" else None
    # Two calls, so the running statistic has history.
    particle_entropy(rep * 2, k, average, clip, normaliser, stats)
    r = particle_entropy(rep, k, average, clip, normaliser, stats)
    rows = loop_knn(rep, k)
    kept = torch.tensor(rows if average else [[row[-1]] for row in rows], dtype=torch.float64)
    # The same statistics by hand (the first call saw the distances of 2*rep: twice these).
    ref = RunningMeanStd()
    ref.update(2 * kept)
    mean, var = ref.update(kept)
    divisor = {"none": 1.0, "mean": mean.item(), "var": var.item()}[normaliser]
    expected = torch.log1p(((kept / divisor) - clip).clamp_min(0.0).mean(1, keepdim=True))
    torch.testing.assert_close(r, expected.float(), rtol=1e-5, atol=1e-6)
    if stats is not None:
        torch.testing.assert_close(stats.mean, ref.mean)
        torch.testing.assert_close(stats.var, ref.var)


def test_particle_entropy_module_and_config_checks():
    assert KNNConfig.apt_cic() == KNNConfig(k=16, average=True, clip=5e-4, normaliser="var")
    plain = ParticleEntropy(KNNConfig(k=2))
    assert plain.stats is None and not list(plain.buffers())
    torch.testing.assert_close(plain(LINE), particle_entropy(LINE, 2, True, 0.0, "none"))
    cic = ParticleEntropy(KNNConfig.apt_cic())
    assert isinstance(cic.stats, RunningMeanStd) and "stats.var" in cic.state_dict()
    with pytest.raises(ConfigError):
        particle_entropy(LINE, 2, True, 0.0, "mean", None)
    with pytest.raises(ConfigError):
        particle_entropy(LINE, 2, True, 0.0, "std")


# ---------------------------------------------------------------------------------------------
# Disagreement


def member_predictions(module: DisagreementReward, batch: Batch) -> torch.Tensor:
    """Each member as its own Linear -> ReLU -> Linear, evaluated one by one."""
    ens = module.ensemble
    x = torch.cat([batch.obs, batch.action], -1)
    h = ens.hidden_dim
    preds = []
    for k in range(ens.num_heads):
        w1, b1 = ens.first.weight[k * h:(k + 1) * h], ens.first.bias[k * h:(k + 1) * h]
        hidden = torch.relu(x @ w1.T + b1)
        preds.append(hidden @ ens.second_weight[k] + ens.second_bias[k, 0])
    return torch.stack(preds)


def test_disagreement_loss_and_reward_by_hand():
    torch.manual_seed(0)
    config = DisagreementConfig(ensemble_size=3, hidden_dim=16)
    module = DisagreementReward(OBS, ACT, config)
    module.make_optimizer(config.lr, fused=False)
    batch = random_batch(6, obs_dim=OBS, reward="zeros")
    with torch.no_grad():
        preds = member_predictions(module, batch)
        errors = [[(batch.next_obs[i] - preds[k, i]).pow(2).sum().sqrt() for i in range(6)] for k in range(3)]
        expected_loss = sum(sum(row) for row in errors) / (3 * 6)
    before = [p.detach().clone() for p in module.parameters()]
    metrics = {}
    reward = module.update_and_score(batch, metrics)
    torch.testing.assert_close(metrics["disagreement_loss"], expected_loss)
    assert not metrics["disagreement_loss"].requires_grad
    assert all(not torch.equal(b, p) for b, p in zip(before, module.parameters()))
    with torch.no_grad():
        preds = member_predictions(module, batch)  # the updated members
    mean = preds.sum(0) / 3
    unbiased_var = (preds - mean).pow(2).sum(0) / (3 - 1)
    expected = unbiased_var.mean(-1, keepdim=True)
    assert reward.shape == (6, 1) and not reward.requires_grad
    torch.testing.assert_close(reward, expected)
    # score alone gives the same (no further update)
    torch.testing.assert_close(module.score(batch), expected)


def test_disagreement_uses_default_not_orthogonal_init():
    torch.manual_seed(1)
    in_dim, hidden = OBS + ACT, 16
    module = DisagreementReward(OBS, ACT, DisagreementConfig(ensemble_size=2, hidden_dim=hidden))
    ens = module.ensemble
    w1 = ens.first.weight[:hidden].detach()  # (16, 7): orthogonal would give w1^T w1 = I
    assert not torch.allclose(w1.T @ w1, torch.eye(in_dim), atol=0.1)
    # PyTorch's default Linear: weights and biases uniform within 1/sqrt(fan_in), biases non-zero.
    assert w1.abs().max() <= 1 / math.sqrt(in_dim)
    assert ens.first.bias.abs().min() > 0 and ens.second_bias.abs().min() > 0
    assert ens.second_weight.abs().max() <= 1 / math.sqrt(hidden)
    with pytest.raises(ConfigError):
        DisagreementReward(OBS, ACT, DisagreementConfig(ensemble_size=1))


# ---------------------------------------------------------------------------------------------
# ICM-APT


def test_icm_apt_loss_and_reward_by_hand():
    torch.manual_seed(0)
    rep_dim, hidden, n = 5, 16, 8
    config = ICMAPTConfig(rep_dim=rep_dim, hidden_dim=hidden, knn_k=3)
    module = ICMAPTReward(OBS, ACT, config)
    module.make_optimizer(config.lr, fused=False)
    batch = random_batch(n, seed=2, obs_dim=OBS, reward="zeros")
    lin, ln = module.trunk[0], module.trunk[1]
    f1, f2 = module.forward_model[0], module.forward_model[2]
    i1, i2 = module.inverse_model[0], module.inverse_model[2]

    def trunk(x):
        return torch.tanh(F_nn.layer_norm(x @ lin.weight.T + lin.bias, (rep_dim,), ln.weight, ln.bias))

    # Orthogonal init (5 x 4 weight: orthonormal columns) with zero biases
    assert torch.allclose(lin.weight.T @ lin.weight, torch.eye(OBS), atol=1e-5)
    assert torch.equal(f1.bias, torch.zeros(hidden)) and torch.equal(i2.bias, torch.zeros(ACT))
    with torch.no_grad():
        e_s, e_next = trunk(batch.obs), trunk(batch.next_obs)
        hidden = torch.relu(torch.cat([e_s, batch.action], -1) @ f1.weight.T + f1.bias)
        next_hat = hidden @ f2.weight.T + f2.bias
        hidden = torch.relu(torch.cat([e_s, e_next], -1) @ i1.weight.T + i1.bias)
        a_hat = torch.tanh(hidden @ i2.weight.T + i2.bias)
        fwd = sum((e_next[i] - next_hat[i]).pow(2).sum().sqrt() for i in range(n)) / n
        inv = sum((batch.action[i] - a_hat[i]).pow(2).sum().sqrt() for i in range(n)) / n
    metrics = {}
    reward = module.update_and_score(batch, metrics)
    torch.testing.assert_close(metrics["icm_loss"], fwd + inv)
    # Reward: k = 3 average kNN over e(s) of the updated trunk (current state, not s').
    with torch.no_grad():
        rows = loop_knn(trunk(batch.obs), 3)
    expected = torch.log1p(torch.tensor([[sum(r) / 3] for r in rows]))
    assert reward.shape == (n, 1) and not reward.requires_grad
    torch.testing.assert_close(reward, expected, rtol=1e-5, atol=1e-6)
    assert module.entropy.stats is None  # knn_normaliser "none": no running statistics


def test_icm_apt_trunk_gets_gradient_from_both_states():
    """As URLB, e(s') is not detached in the loss: the trunk also learns through the targets."""
    torch.manual_seed(0)
    module = ICMAPTReward(OBS, ACT, ICMAPTConfig(rep_dim=5, hidden_dim=8))
    batch = random_batch(6, obs_dim=OBS, reward="zeros")
    module.loss(batch).backward()
    grad_both = module.trunk[0].weight.grad.clone()
    module.zero_grad()
    rep_obs = module.trunk(batch.obs)
    rep_next = module.trunk(batch.next_obs).detach()
    loss = ((rep_next - module.forward_model(torch.cat([rep_obs, batch.action], -1))).norm(dim=-1).mean()
            + (batch.action - module.inverse_model(torch.cat([rep_obs, rep_next], -1))).norm(dim=-1).mean())
    loss.backward()
    assert not torch.allclose(grad_both, module.trunk[0].weight.grad)


# ---------------------------------------------------------------------------------------------
# Proto


def tiny_proto(seed: int = 0, **overrides) -> ProtoReward:
    torch.manual_seed(seed)
    kw = dict(pred_dim=4, proj_dim=8, num_protos=4, queue_size=8, topk=3)
    kw.update(overrides)
    config = ProtoConfig(**kw)
    module = ProtoReward(OBS, ACT, config)
    module.make_optimizer(config.lr, fused=False)
    return module


def loop_sinkhorn(scores: torch.Tensor, iters: int) -> torch.Tensor:
    """Sinkhorn-Knopp written entry by entry in float64."""
    n, p = scores.shape
    top = max(float(v) for v in scores.flatten())
    q = [[math.exp(float(scores[i, j]) - top) for i in range(n)] for j in range(p)]  # (P, N)
    total = sum(map(sum, q))
    q = [[v / total for v in row] for row in q]
    for _ in range(iters):
        q = [[v / (sum(row) * p) for v in row] for row in q]
        cols = [sum(q[j][i] for j in range(p)) for i in range(n)]
        q = [[q[j][i] / (cols[i] * n) for i in range(n)] for j in range(p)]
    cols = [sum(q[j][i] for j in range(p)) for i in range(n)]
    return torch.tensor([[q[j][i] / cols[i] for j in range(p)] for i in range(n)])


def test_sinkhorn_matches_loops_and_has_the_right_marginals():
    scores = torch.randn(6, 4, generator=torch.Generator().manual_seed(0)) * 3
    q = sinkhorn_knopp(scores, 3)
    assert q.shape == (6, 4)
    torch.testing.assert_close(q, loop_sinkhorn(scores, 3).float())
    torch.testing.assert_close(q.sum(1), torch.ones(6))  # each sample's assignment sums to 1
    # Converged: every prototype receives an equal share N/P of the samples.
    q = sinkhorn_knopp(scores, 200)
    torch.testing.assert_close(q.sum(0), torch.full((4,), 6 / 4), rtol=1e-4, atol=1e-4)
    assert torch.all(q >= 0)


def test_proto_loss_by_hand_and_unit_prototypes_after_update():
    module = tiny_proto()
    batch = random_batch(8, obs_dim=OBS, reward="zeros")
    c = module.config
    with torch.no_grad():
        module.protos.weight.mul_(3.0)  # off the sphere: the update must normalise first
        protos = F_nn.normalize(module.protos.weight, dim=1)
        proj1, proj2 = module.projector[0], module.projector[2]
        pred = batch.obs @ module.predictor.weight.T + module.predictor.bias
        hidden = torch.relu(pred @ proj1.weight.T + proj1.bias)
        online = F_nn.normalize(hidden @ proj2.weight.T + proj2.bias, dim=1)
        log_p = torch.log_softmax(online @ protos.T / c.temperature, dim=1)
        tgt = module.predictor_target
        target = F_nn.normalize(batch.next_obs @ tgt.weight.T + tgt.bias, dim=1)
        q = loop_sinkhorn(target @ protos.T / c.temperature, c.sinkhorn_iters).float()
        expected = -sum((q[i] * log_p[i]).sum() for i in range(8)) / 8
        online_before = module.predictor.weight.clone()
        target_before = tgt.weight.clone()
    metrics = module.update(batch)
    torch.testing.assert_close(metrics["proto_loss"], expected)
    # EMA target: theta' = 0.05 * theta_new + 0.95 * theta'_old
    torch.testing.assert_close(tgt.weight, 0.05 * module.predictor.weight + 0.95 * target_before)
    assert not torch.equal(module.predictor.weight, online_before)
    assert not tgt.weight.requires_grad
    module.score(batch)  # re-normalises the rows moved by the optimiser step
    torch.testing.assert_close(module.protos.weight.norm(dim=1), torch.ones(4))


def test_proto_reward_is_distance_to_third_nearest_queue_entry():
    module = tiny_proto()
    batch = random_batch(10, seed=4, obs_dim=OBS, reward="zeros")
    module.update(batch)
    with torch.no_grad():
        module.normalize_protos()
        z = F_nn.normalize(batch.next_obs @ module.predictor.weight.T + module.predictor.bias, dim=1)
        prob = torch.softmax((z @ module.protos.weight.T).T, dim=1)  # (P, N)
    torch.manual_seed(11)
    expected_idx = torch.multinomial(prob, 1).squeeze(1)
    torch.manual_seed(11)
    reward = module.score(batch)
    assert module.queue_ptr == 4
    torch.testing.assert_close(module.queue[:4], z[expected_idx])
    assert torch.equal(module.queue[4:], torch.zeros(4, 4))  # still the initial zeros
    # Brute force: distances to every queue entry, sorted, 3rd smallest.
    expected = []
    for i in range(10):
        d = sorted(float((z[i] - module.queue[j]).pow(2).sum().sqrt()) for j in range(8))
        expected.append([d[2]])
    assert reward.shape == (10, 1) and not reward.requires_grad
    torch.testing.assert_close(reward, torch.tensor(expected))


def test_candidate_sampling_equals_torch_multinomial():
    prob = torch.softmax(torch.randn(16, 10, generator=torch.Generator().manual_seed(2)) * 2, dim=1)
    torch.manual_seed(3)
    expected = torch.cat([torch.multinomial(prob, 1).squeeze(1) for _ in range(5)])
    torch.manual_seed(3)
    got = torch.cat([sample_one_per_row(prob) for _ in range(5)])
    assert torch.equal(got, expected)
    # A one-hot row always yields its index.
    assert torch.equal(sample_one_per_row(torch.eye(4)), torch.arange(4))


def test_proto_queue_pointer_cycles_and_wraps():
    module = tiny_proto()
    batch = random_batch(6, obs_dim=OBS, reward="zeros")
    ptrs = []
    for _ in range(3):
        module.score(batch)
        ptrs.append(module.queue_ptr)
    assert ptrs == [4, 0, 4]  # 8 / 4: exact cycle
    odd = tiny_proto(queue_size=10)
    cands = [torch.full((4, 4), float(v)) for v in (1, 2, 3)]
    for cand in cands:
        odd.enqueue(cand)
    assert odd.queue_ptr == 2  # 0 -> 4 -> 8 -> (8, 9, 0, 1) -> 2
    torch.testing.assert_close(odd.queue[:, 0], torch.tensor([3.0, 3, 1, 1, 2, 2, 2, 2, 3, 3]))
    with pytest.raises(ConfigError):
        tiny_proto(num_protos=16, queue_size=8)


def test_proto_state_dict_round_trip_resumes_exactly():
    module = tiny_proto(seed=0)
    batch = random_batch(6, seed=5, obs_dim=OBS, reward="zeros")
    for _ in range(3):  # pointer at 4 afterwards: not the initial value
        module.update_and_score(batch, {})
    assert module.queue_ptr == 4
    state = module.state_dict()
    assert "queue" in state and state["_extra_state"] == {"queue_ptr": 4}
    fresh = tiny_proto(seed=123)
    fresh.load_state_dict(state)
    assert fresh.queue_ptr == 4
    torch.testing.assert_close(fresh.queue, module.queue)
    torch.manual_seed(7)
    expected = module.score(batch)
    torch.manual_seed(7)
    got = fresh.score(batch)
    assert torch.equal(got, expected)
    assert torch.equal(fresh.queue, module.queue) and fresh.queue_ptr == module.queue_ptr == 0
