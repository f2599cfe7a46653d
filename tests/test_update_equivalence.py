"""The optimised update computes exactly the method: every loss, gradient and parameter of full
pre-training updates equals a plain reference implementation (issue "Performance").

The reference below is written for obviously-correct reading, not speed: every network is evaluated
layer by layer from its weights (LayerNorm and batch norm from their formulas), the twin heads are
separate matrix products, the CE reward builds the N x N x d cosine tensor and sorts it, the
implicit reward uses an explicit matrix inverse, off-diagonal means use boolean masks, and the
optimisers are single-tensor Adam. It draws its random numbers in the order the spec's update
(docs/methods.md §7.2, §5.3, §3.3) consumes them, from the same seed, so both sides use the same z's,
permutation, mixing mask and policy noise.

Also here: the no-host-sync check of the update path, "each forward pass once per update" (a
forward-call count per network), vectorised replay sampling, and the precision / compile / CUDA
graph options of :mod:`dvfb.nets.execution`.
"""

from __future__ import annotations

import copy
import logging
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

import dvfb
from dvfb.agents.dvfb import DVFBAgent, ExplorationConfig
from dvfb.agents.fb import FBAgent, FBConfig
from dvfb.rewards.contrastive import contrastive_entropy_reward
from dvfb.nets.execution import NetRunner, PerfConfig
from dvfb.core.errors import ConfigError
from dvfb.nets import TwinHead
from dvfb.data import Batch, ReplayBuffer
from tiny import per_row_discount_batch

OBS, ACT, D, H, E, HB = 7, 3, 8, 24, 12, 20


def small_config(**overrides) -> FBConfig:
    kw = dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=HB, batch_size=40, lr=1e-3,
              tau=0.05, ortho_coef=0.7, q_loss_coef=0.3)
    kw.update(overrides)
    return FBConfig(**kw)


def small_exploration(**overrides) -> ExplorationConfig:
    kw = dict(rnd_rep_dim=10, contrastive_hidden_dim=16, ce_k=5, alpha=3.0, beta=0.7)
    kw.update(overrides)
    return ExplorationConfig(**kw)


@pytest.fixture
def float64():
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


# ---------------------------------------------------------------------------------------------
# The reference: networks from their weights


def ref_layer_norm(x, ln: nn.LayerNorm):
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + ln.eps) * ln.weight + ln.bias


def ref_seq(x, seq: nn.Sequential):
    for layer in seq:
        if isinstance(layer, nn.Linear):
            x = x @ layer.weight.T + layer.bias
        elif isinstance(layer, nn.LayerNorm):
            x = ref_layer_norm(x, layer)
        elif isinstance(layer, nn.Tanh):
            x = torch.tanh(x)
        elif isinstance(layer, nn.ReLU):
            x = torch.relu(x)
        else:  # pragma: no cover
            raise TypeError(layer)
    return x


def ref_twin(x, head: TwinHead):
    """The K heads as K separate two-layer MLPs: a list of (N, out)."""
    outs = []
    for k in range(head.num_heads):
        rows = slice(k * head.hidden_dim, (k + 1) * head.hidden_dim)
        hidden = torch.relu(x @ head.first.weight[rows].T + head.first.bias[rows])
        outs.append(hidden @ head.second_weight[k] + head.second_bias[k, 0])
    return outs


def ref_proj(v):
    return math.sqrt(v.shape[-1]) * v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def ref_actor(actor, obs, z):
    h_s = ref_seq(obs, actor.encoder.first)
    h_sz = ref_seq(torch.cat([obs, z], -1), actor.encoder.second)
    return torch.tanh(ref_seq(torch.cat([h_s, h_sz], -1), actor.head))


def ref_forward(fmap, obs, action, z):
    h = torch.cat([ref_seq(torch.cat([obs, action], -1), fmap.encoder.first),
                   ref_seq(torch.cat([obs, z], -1), fmap.encoder.second)], -1)
    return ref_twin(h, fmap.heads)  # [F_1, F_2], each (N, d)


def ref_backward(bmap, x):
    return ref_proj(ref_seq(x, bmap.net))


def ref_critic(critic, obs, z, action):
    return ref_twin(ref_seq(torch.cat([obs, z, action], -1), critic.trunk), critic.heads)  # [(N,1)] * 2


def ref_training_action(mu, std, clip):
    noise = (torch.randn_like(mu) * std).clamp(-clip, clip)
    raw = mu + noise
    return raw + (raw.clamp(-1 + 1e-6, 1 - 1e-6) - raw).detach()


def offdiag(x):
    n = x.shape[-1]
    return x[~torch.eye(n, dtype=torch.bool)].mean()


def ref_cos(a, b):
    """c_ij = cos(a_i, b_j) through the N x N x d tensor of elementwise products."""
    an = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    bn = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return (an[:, None, :] * bn[None, :, :]).sum(-1)


def ref_ce_reward(key, query, k, neighbours, aggregate, temperature):
    cos = ref_cos(key, query)
    ordered = cos.sort(dim=-1, descending=(neighbours == "most_similar")).values[:, :k]
    distance = torch.clamp(1 - ordered / temperature, min=0.0)
    if aggregate == "log_of_mean":
        return torch.log(1 + distance.mean(-1, keepdim=True))
    return torch.log(1 + distance).mean(-1, keepdim=True)


def ref_nce(query, key, temperature, exact_positive):
    sim = ref_cos(query, key) / temperature
    pos = torch.exp(sim.diagonal())
    subtract = pos if exact_positive else math.exp(1 / temperature)
    neg = torch.clamp(torch.exp(sim).sum(-1) - subtract, min=1e-6)
    return (-torch.log(pos / (neg + 1e-6))).mean()


class RefRMS:
    """§3.4 running mean/variance, written out."""

    def __init__(self, mean, var, count):
        self.mean, self.var, self.count = float(mean), float(var), float(count)

    def update(self, x):
        x = x.detach().double().reshape(-1)
        b = x.numel()
        delta = x.mean().item() - self.mean
        total = self.count + b
        new_mean = self.mean + delta * b / total
        new_var = (self.var * self.count + x.var(unbiased=True).item() * b
                   + delta ** 2 * self.count * b / total) / total
        self.mean, self.var, self.count = new_mean, new_var, total
        return new_mean, new_var


# ---------------------------------------------------------------------------------------------
# The reference: one update (§7.2)


class Reference:
    """A plain re-statement of the pre-training update on a private copy of the agent's networks."""

    def __init__(self, agent: FBAgent):
        self.net = copy.deepcopy(agent)
        self.c, self.dvfb = agent.config, isinstance(agent, DVFBAgent)
        self.e = agent.exploration if self.dvfb else None
        n = self.net
        c = self.c

        def plain_adam(params):
            return torch.optim.Adam(params, lr=c.lr, foreach=False, fused=False)

        self.opt = {
            "fb_optimizer": torch.optim.Adam(
                [{"params": list(n.forward_map.parameters())},
                 {"params": list(n.backward_map.parameters()), "lr": c.lr * c.backward_lr_coef}],
                lr=c.lr, foreach=False, fused=False),
            "actor_optimizer": plain_adam(n.actor.parameters()),
        }
        if self.dvfb:
            self.opt["critic_optimizer"] = plain_adam(n.exploration_critic.parameters())
            self.opt["rnd_optimizer"] = plain_adam(n.rnd.networks.predictor.parameters())
            if n.contrastive is not None:
                self.opt["contrastive_optimizer"] = plain_adam(n.contrastive.encoders.parameters())
            s = n.rnd.error_stats
            self.rms = RefRMS(s.mean, s.var, s.count)
        self.names = {id(p): name for name, p in n.named_parameters()}

    def _step(self, name, loss, log):
        opt = self.opt[name]
        params = [p for g in opt.param_groups for p in g["params"]]
        grads = torch.autograd.grad(loss, params)
        for p, g in zip(params, grads):
            p.grad = g
        log[name] = {self.names[id(p)]: g.detach().clone() for p, g in zip(params, grads)}
        opt.step()
        opt.zero_grad(set_to_none=True)

    def update(self, batch: Batch, seed: int):
        torch.manual_seed(seed)
        n, c, e = self.net, self.c, self.e
        s, a, s1, s2, disc = batch.obs, batch.action, batch.next_obs, batch.future_obs, batch.discount
        N = s.shape[0]
        mode = c.backward_input
        losses, grads = {}, {}

        def b_in(x, y):
            return torch.cat([x, y], -1)

        # z's (§5.3): prior draws, a permutation, a Bernoulli mask; goals from the online B.
        z = ref_proj(torch.randn(N, c.z_dim))
        perm = torch.randperm(N)
        goal_input = {"state": s[perm], "transition": b_in(s[perm], s1[perm]), "code_exact": b_in(s, s[perm])}[mode]
        with torch.no_grad():
            goals = ref_proj(ref_backward(n.backward_map, goal_input))
        replace = torch.rand(N, 1) < c.mix_ratio
        z = torch.where(replace, goals, z)
        with torch.no_grad():
            next_action = ref_training_action(ref_actor(n.actor, s1, z), c.stddev, c.stddev_clip)
        online_in = {"state": s1, "transition": b_in(s, s1), "code_exact": b_in(s, s2)}[mode]
        target_in = {"state": s1, "transition": b_in(s, s1), "code_exact": b_in(s1, s2)}[mode]
        label_in = s1 if mode == "state" else b_in(s, s1)

        if self.dvfb:
            # RND step (§7.3), on s' or s.
            x = s1 if e.rnd_input == "next_obs" else s
            mean = x.mean(0)
            var = ((x - mean) ** 2).mean(0)
            normed = ((x - mean) / torch.sqrt(var + 1e-5)).clamp(-e.rnd_obs_clip, e.rnd_obs_clip)
            with torch.no_grad():
                rnd_target = ref_seq(normed, n.rnd.networks.target)
            rnd_loss = ((rnd_target - ref_seq(normed, n.rnd.networks.predictor)) ** 2).mean(-1).mean()
            losses["rnd_loss"] = rnd_loss
            self._step("rnd_optimizer", rnd_loss, grads)
            with torch.no_grad():
                labels = ref_backward(n.backward_map, label_in)

            def key_query():
                enc = n.contrastive.encoders
                key = ref_seq(torch.cat([ref_seq(s, enc.state_net), ref_seq(s1, enc.state_net)], -1),
                              enc.transition_net)
                return key, ref_seq(labels, enc.skill_net)

            if n.contrastive is not None:  # NCE step (§7.4)
                key, query = key_query()
                nce = ref_nce(query, key, e.nce_temperature, e.nce_exact_positive)
                losses["nce_loss"] = nce
                self._step("contrastive_optimizer", nce, grads)
            with torch.no_grad():  # intrinsic reward with the updated modules (§7.5, §7.6)
                error = ((rnd_target - ref_seq(normed, n.rnd.networks.predictor)) ** 2).mean(-1)
                _, var_rnd = self.rms.update(error)
                reward = (error / (math.sqrt(var_rnd) + 1e-8)).unsqueeze(-1)
                losses["rnd_reward"] = reward.mean()
                if n.contrastive is not None and e.beta != 0:
                    key, query = key_query()
                    ce = ref_ce_reward(key, query, e.ce_k, e.ce_neighbours, e.ce_aggregate, e.ce_temperature)
                    losses["ce_reward"] = ce.mean()
                    reward = reward + e.beta * ce
                losses["intrinsic_reward"] = reward.mean()
                tq1, tq2 = ref_critic(n.exploration_critic_target, s1, z, next_action)
                y = reward + disc * torch.minimum(tq1, tq2)
            q1, q2 = ref_critic(n.exploration_critic, s, z, a)  # Q_P step (§7.7)
            critic_loss = ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean()
            losses["exploration_critic_loss"] = critic_loss
            self._step("critic_optimizer", critic_loss, grads)

        # FB step (§7.8-§7.10)
        with torch.no_grad():
            ft = ref_forward(n.forward_target, s1, next_action, z)
            bt = ref_backward(n.backward_target, target_in)
            tm = torch.minimum(ft[0] @ bt.T, ft[1] @ bt.T)
        f = ref_forward(n.forward_map, s, a, z)
        bb = ref_backward(n.backward_map, online_in)
        fb_loss = 0
        for fk in f:
            mk = fk @ bb.T
            fb_loss = fb_loss + 0.5 * offdiag((mk - disc * tm) ** 2) - mk.diagonal().mean()
        gram = bb @ bb.T
        ortho = offdiag(gram ** 2) - 2 * gram.diagonal().mean()
        total = fb_loss + c.ortho_coef * ortho
        losses.update(fb_loss=fb_loss, ortho_loss=ortho)
        if c.q_loss:
            with torch.no_grad():
                bd = bb.detach()
                cov = bd.T @ bd / N + c.cov_ridge * torch.eye(c.z_dim)
                r_imp = ((bd @ torch.linalg.inv(cov)) * z).sum(-1)
                y_q = r_imp + disc[:, 0] * torch.minimum((ft[0] * z).sum(-1), (ft[1] * z).sum(-1))
            q_loss = sum((((fk * z).sum(-1) - y_q) ** 2).mean() for fk in f)
            losses["fb_q_loss"] = q_loss
            total = total + c.q_loss_coef * q_loss
        losses["fb_total"] = total
        self._step("fb_optimizer", total, grads)

        # Actor step (§7.11), with the updated F and Q_P.
        action = ref_training_action(ref_actor(n.actor, s, z), c.stddev, c.stddev_clip)
        fa = ref_forward(n.forward_map, s, action, z)
        qm = torch.minimum((fa[0] * z).sum(-1), (fa[1] * z).sum(-1))
        objective = qm
        losses["skill_value"] = qm.mean()
        if self.dvfb:
            p1, p2 = ref_critic(n.exploration_critic, s, z, action)
            qp = torch.minimum(p1, p2)[:, 0]
            alpha = (2 * qm.mean() / qp.mean()).detach() if e.alpha_mode == "adaptive" else e.alpha
            objective = objective + alpha * qp
            losses["exploration_value"] = qp.mean()
        actor_loss = -objective.mean()
        losses["actor_loss"] = actor_loss
        self._step("actor_optimizer", actor_loss, grads)

        # EMA (§3.5)
        with torch.no_grad():
            pairs = [(n.forward_target, n.forward_map), (n.backward_target, n.backward_map)]
            if self.dvfb:
                pairs.append((n.exploration_critic_target, n.exploration_critic))
            for target, online in pairs:
                for pt, po in zip(target.parameters(), online.parameters()):
                    pt.copy_(c.tau * po + (1 - c.tau) * pt)
        return {k: v.detach() for k, v in losses.items()}, grads


def record_grads(agent: FBAgent) -> dict:
    """Patch the agent's optimisers to record each step's gradients, by parameter name."""
    names = {id(p): name for name, p in agent.named_parameters()}
    log: dict = {}
    for opt_name, opt in agent.optimizers().items():
        original = opt.step

        def step(*args, _name=opt_name, _opt=opt, _orig=original, **kwargs):
            log[_name] = {names[id(p)]: p.grad.detach().clone()
                          for g in _opt.param_groups for p in g["params"] if p.grad is not None}
            return _orig(*args, **kwargs)

        opt.step = step
    return log


def assert_update_matches_reference(agent: FBAgent, updates: int = 3, rtol=1e-9, atol=1e-11):
    reference = Reference(agent)
    log = record_grads(agent)
    for u in range(updates):
        batch = per_row_discount_batch(agent.config.batch_size, seed=100 + u, dtype=next(agent.parameters()).dtype,
                                       obs_dim=OBS)
        torch.manual_seed(1000 + u)
        metrics = agent.update(batch)
        ref_losses, ref_grads = reference.update(batch, seed=1000 + u)
        assert set(ref_losses) <= set(metrics), sorted(set(ref_losses) - set(metrics))
        for name, value in ref_losses.items():
            torch.testing.assert_close(metrics[name], value.to(metrics[name].dtype), rtol=rtol, atol=atol,
                                       msg=lambda m, n=name, k=u: f"update {k}, {n}: {m}")
        assert set(log) == set(ref_grads)
        for opt_name, grads in ref_grads.items():
            assert set(log[opt_name]) == set(grads), opt_name  # every parameter got a gradient
            for pname, g in grads.items():
                torch.testing.assert_close(log[opt_name][pname], g, rtol=rtol, atol=atol,
                                           msg=lambda m, n=pname, k=u: f"update {k}, grad of {n}: {m}")
        mine = dict(agent.named_parameters())
        for pname, p in reference.net.named_parameters():
            torch.testing.assert_close(mine[pname], p, rtol=rtol, atol=atol,
                                       msg=lambda m, n=pname, k=u: f"update {k}, parameter {n}: {m}")
        if isinstance(agent, DVFBAgent):
            stats = agent.rnd.error_stats
            assert stats.mean.item() == pytest.approx(reference.rms.mean, rel=max(rtol, 1e-12))
            assert stats.var.item() == pytest.approx(reference.rms.var, rel=max(rtol, 1e-12))


# ---------------------------------------------------------------------------------------------
# Full updates against the reference


@pytest.mark.parametrize("fused_adam", [False, True])
@pytest.mark.parametrize("mode", ["state", "transition", "code_exact"])
def test_dvfb_update_matches_reference(float64, mode, fused_adam):
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, small_config(backward_input=mode, fused_adam=fused_adam), small_exploration())
    assert_update_matches_reference(agent)


@pytest.mark.parametrize("options", [
    dict(exploration=dict(alpha_mode="adaptive", rnd_input="obs", ce_neighbours="most_similar",
                          ce_aggregate="mean_of_log", ce_temperature=0.5, nce_temperature=0.5,
                          nce_exact_positive=True)),
    dict(exploration=dict(use_ce=False)),
    dict(exploration=dict(beta=0.0)),
    dict(fb=dict(q_loss=False, backward_lr_coef=0.5, cov_ridge=0.1)),
])
def test_dvfb_update_options_match_reference(float64, options):
    torch.manual_seed(1)
    agent = DVFBAgent(OBS, ACT, small_config(**options.get("fb", {})),
                      small_exploration(**options.get("exploration", {})))
    assert_update_matches_reference(agent, updates=2)


@pytest.mark.parametrize("mode", ["state", "code_exact"])
def test_fb_update_matches_reference(float64, mode):
    torch.manual_seed(2)
    agent = FBAgent(OBS, ACT, small_config(backward_input=mode))
    assert_update_matches_reference(agent)


def test_dvfb_update_matches_reference_in_float32():
    """The production dtype: same comparison with float32 round-off tolerances."""
    torch.manual_seed(3)
    agent = DVFBAgent(OBS, ACT, small_config(), small_exploration())
    assert_update_matches_reference(agent, updates=2, rtol=2e-4, atol=2e-5)


# ---------------------------------------------------------------------------------------------
# The kNN CE reward: one matrix product + top-k equals the N x N x d reference


@pytest.mark.parametrize("neighbours", ["least_similar", "most_similar"])
@pytest.mark.parametrize("aggregate", ["log_of_mean", "mean_of_log"])
@pytest.mark.parametrize("k,temperature", [(1, 1.0), (12, 1.0), (12, 0.7), (200, 1.0)])
def test_ce_reward_matches_nxnxd_reference(neighbours, aggregate, k, temperature):
    g = torch.Generator().manual_seed(k)
    key = torch.randn(96, 16, generator=g, dtype=torch.float64)
    query = torch.randn(96, 16, generator=g, dtype=torch.float64) * 3
    got = contrastive_entropy_reward(key, query, k, neighbours, aggregate, temperature)
    ref = ref_ce_reward(key, query, min(k, 96), neighbours, aggregate, temperature)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-13)


def test_ce_reward_never_builds_an_nxnxd_tensor():
    """No intermediate of the CE reward has more than N*N elements."""
    from torch.utils._python_dispatch import TorchDispatchMode

    n, d = 64, 32
    largest = []

    class Watch(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            for t in (out if isinstance(out, (tuple, list)) else (out,)):
                if isinstance(t, torch.Tensor):
                    largest.append(t.numel())
            return out

    key, query = torch.randn(n, d), torch.randn(n, d)
    with Watch():
        contrastive_entropy_reward(key, query, 12)
    assert max(largest) <= n * n


# ---------------------------------------------------------------------------------------------
# No host synchronisation in the update path

SRC = str(Path(dvfb.__file__).resolve().parent)
SYNCING = ("item", "tolist", "cpu", "numpy", "__bool__", "__float__", "__int__", "__index__")


@pytest.fixture
def no_host_sync(monkeypatch):
    """Make every host-syncing Tensor method raise when called from dvfb's own source.

    (On CPU nothing actually syncs, so the calls themselves are what is detected. torch's own
    internals -- e.g. Adam reading its CPU step counters -- are not dvfb's code and are allowed.)
    """
    calls = []
    for name in SYNCING:
        original = getattr(torch.Tensor, name)

        def guarded(self, *args, _name=name, _orig=original, **kwargs):
            caller = sys._getframe(1).f_code.co_filename
            if caller.startswith(SRC):
                calls.append((_name, caller, sys._getframe(1).f_lineno))
                raise AssertionError(f"host sync Tensor.{_name} in the update path at "
                                     f"{caller}:{sys._getframe(1).f_lineno}")
            return _orig(self, *args, **kwargs)

        monkeypatch.setattr(torch.Tensor, name, guarded)
    return calls


@pytest.mark.parametrize("agent_name", ["dvfb", "fb"])
@pytest.mark.parametrize("mode", ["state", "code_exact"])
def test_update_path_has_no_host_sync(no_host_sync, agent_name, mode):
    torch.manual_seed(0)
    fb = small_config(backward_input=mode)
    agent = (DVFBAgent(OBS, ACT, fb, small_exploration(alpha_mode="adaptive")) if agent_name == "dvfb"
             else FBAgent(OBS, ACT, fb))
    for seed in range(2):
        metrics = agent.update(per_row_discount_batch(40, seed, torch.float32, obs_dim=OBS))
    assert no_host_sync == []
    assert all(isinstance(v, torch.Tensor) and v.dim() == 0 for v in metrics.values())


def test_sync_detector_detects_a_sync(no_host_sync):
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, small_config())
    original = agent.fb_losses

    def syncing_fb_losses(*args):
        losses = original(*args)
        losses["fb_loss"].item()  # called from this test file: allowed
        from dvfb.training.metric_windows import MetricWindow
        window = MetricWindow()
        window.add(0, {"x": losses["fb_loss"]})
        window.flush()  # .cpu() from dvfb code: caught
        return losses

    agent.fb_losses = syncing_fb_losses
    with pytest.raises(AssertionError, match="host sync"):
        agent.update(per_row_discount_batch(40, 0, torch.float32, obs_dim=OBS))


# ---------------------------------------------------------------------------------------------
# Each network runs the forward passes the method needs, and no more


def count_forwards(agent: FBAgent, names) -> dict:
    counts = dict.fromkeys(names, 0)
    modules = dict(agent.named_modules())
    for name in names:
        modules[name].register_forward_hook(lambda m, i, o, _n=name: counts.__setitem__(_n, counts[_n] + 1))
    return counts


@pytest.mark.parametrize("mode,b_calls", [("state", 2), ("code_exact", 3)])
def test_each_network_forward_runs_once_per_use(mode, b_calls):
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, small_config(backward_input=mode), small_exploration())
    expected = {
        "actor": 2,                 # next actions (all TD targets), actor loss
        "backward_map": b_calls,    # mixed z's, online B (FB, Q and ortho losses, labels) [+ labels]
        "forward_map": 2,           # FB loss, actor loss
        "forward_target": 1,        # TM and the auxiliary Q target
        "backward_target": 1,
        "exploration_critic": 2,    # TD loss, actor loss
        "exploration_critic_target": 1,
        "rnd.networks.target": 1,   # shared by the RND loss and reward
        "rnd.networks.predictor": 2,  # loss, then reward with the updated predictor
        "contrastive.encoders.state_net": 2,   # NCE loss, then CE reward with the updated encoders; s and s' in one pass
        "contrastive.encoders.transition_net": 2,
        "contrastive.encoders.skill_net": 2,
    }
    counts = count_forwards(agent, expected)
    agent.update(per_row_discount_batch(40, 0, torch.float32, obs_dim=OBS))
    assert counts == expected


def test_fb_networks_forward_counts():
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, small_config())
    expected = {"actor": 2, "backward_map": 2, "forward_map": 2, "forward_target": 1, "backward_target": 1}
    counts = count_forwards(agent, expected)
    agent.update(per_row_discount_batch(40, 0, torch.float32, obs_dim=OBS))
    assert counts == expected


def test_no_unused_parameters():
    """Every trained parameter gets a gradient (nothing like [C]'s unused skill-forward head is
    computed), and the only parameters without an optimiser are targets."""
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, small_config(), small_exploration())
    log = record_grads(agent)
    agent.update(per_row_discount_batch(40, 0, torch.float32, obs_dim=OBS))
    stepped = {name for grads in log.values() for name in grads}
    trainable = {name for name, p in agent.named_parameters() if p.requires_grad}
    assert stepped == trainable
    frozen = {name.split(".")[0] if not name.startswith("rnd.") else "rnd.networks.target"
              for name, p in agent.named_parameters() if not p.requires_grad}
    assert frozen == {"forward_target", "backward_target", "exploration_critic_target", "rnd.networks.target"}


# ---------------------------------------------------------------------------------------------
# Replay sampling is vectorised


def _lines_executed(fn, *args, **kwargs) -> int:
    count = 0

    def tracer(frame, event, arg):
        nonlocal count
        if event == "line" and frame.f_code.co_filename.startswith(SRC):
            count += 1
        return tracer

    sys.settrace(tracer)
    try:
        fn(*args, **kwargs)
    finally:
        sys.settrace(None)
    return count


def test_replay_sample_has_no_python_loop_over_the_batch():
    buffer = ReplayBuffer(5000, OBS, ACT, D, max_episode_length=100)
    rng = np.random.default_rng(0)
    for _ in range(7):
        buffer.start_episode(rng.standard_normal(OBS))
        for _ in range(100):
            buffer.add(rng.uniform(-1, 1, ACT), 0.0, 1.0, rng.standard_normal(OBS), rng.standard_normal(D))
    small = _lines_executed(buffer.sample, 8, need_future=True)
    large = _lines_executed(buffer.sample, 4096, need_future=True)
    assert small == large  # the same Python work for 8 or 4096 samples
    batch = buffer.sample(4096)
    assert batch.obs.shape == (4096, OBS) and batch.z.shape == (4096, D)


# ---------------------------------------------------------------------------------------------
# Precision, compilation, CUDA graphs


def test_perf_defaults_are_fp32_eager():
    config = PerfConfig()
    assert (config.precision, config.compile, config.cuda_graphs, config.tf32) == ("fp32", False, False, False)
    runner = NetRunner(None, "cpu")
    net = nn.Linear(3, 2)
    x = torch.randn(4, 3)
    assert torch.equal(runner(net, x), net(x))


def test_bf16_update_keeps_fp32_state_and_close_losses():
    torch.manual_seed(0)
    fp32 = DVFBAgent(OBS, ACT, small_config(), small_exploration())
    bf16 = copy.deepcopy(fp32)
    bf16.model.net_runner = NetRunner(PerfConfig(precision="bf16"), "cpu")
    batch = per_row_discount_batch(40, 0, torch.float32, obs_dim=OBS)
    torch.manual_seed(5)
    m32 = fp32.update(batch)
    torch.manual_seed(5)
    m16 = bf16.update(batch)
    for name, value in m16.items():
        assert value.dtype == torch.float32 and torch.isfinite(value), name
    for name in ("fb_loss", "ortho_loss", "rnd_loss", "nce_loss", "exploration_critic_loss"):
        torch.testing.assert_close(m16[name], m32[name], rtol=0.05, atol=0.05, msg=name)
    assert any(not torch.equal(m16[k], m32[k]) for k in m16)  # bf16 really was used
    for p in bf16.parameters():
        assert p.dtype == torch.float32
    for opt in bf16.optimizers().values():
        for state in opt.state.values():
            assert all(v.dtype == torch.float32 for v in state.values() if v.dim() > 0)


def test_bf16_runner_casts_matmuls_and_returns_fp32():
    runner = NetRunner(PerfConfig(precision="bf16"), "cpu")
    net = nn.Sequential(nn.Linear(8, 8), nn.ReLU())
    seen = []
    net[0].register_forward_hook(lambda m, i, o: seen.append(o.dtype))
    out = runner(net, torch.randn(5, 8))
    assert seen == [torch.bfloat16] and out.dtype == torch.float32
    # Reductions stay float32: B's sphere projection is exact to float32 precision.
    torch.manual_seed(0)
    agent = FBAgent(OBS, ACT, small_config(), perf=PerfConfig(precision="bf16"))
    b = agent.net_runner(agent.backward_map, torch.randn(64, OBS))
    assert b.dtype == torch.float32
    torch.testing.assert_close(b.norm(dim=-1), torch.full((64,), math.sqrt(D)), rtol=1e-6, atol=1e-6)


def test_cuda_graphs_on_cpu_is_a_config_error():
    with pytest.raises(ConfigError, match="cuda_graphs"):
        NetRunner(PerfConfig(cuda_graphs=True), "cpu")
    with pytest.raises(ConfigError, match="cuda_graphs"):
        FBAgent(OBS, ACT, small_config(), perf=PerfConfig(cuda_graphs=True))


def test_tf32_is_off_unless_asked_and_refused_off_cuda():
    # The switches are process-wide and settable without a GPU; a CUDA runner sets them from the
    # config (docs/performance.md), here set_tf32 itself is checked.
    from dvfb.nets.execution import set_tf32

    before = (torch.backends.cuda.matmul.fp32_precision, torch.backends.cudnn.conv.fp32_precision)
    try:
        set_tf32(True)
        assert (torch.backends.cuda.matmul.fp32_precision, torch.backends.cudnn.conv.fp32_precision) == ("tf32", "tf32")
        set_tf32(False)
        assert (torch.backends.cuda.matmul.fp32_precision, torch.backends.cudnn.conv.fp32_precision) == ("ieee", "ieee")
    finally:
        torch.backends.cuda.matmul.fp32_precision, torch.backends.cudnn.conv.fp32_precision = before
    with pytest.raises(ConfigError, match="perf.tf32 applies to CUDA"):
        NetRunner(PerfConfig(tf32=True), "cpu")


def test_compile_failure_falls_back_to_eager_with_a_warning(monkeypatch, caplog):
    class FakeCompileError(Exception):
        pass

    FakeCompileError.__module__ = "torch._dynamo.exc"

    def broken_compile(module, **kwargs):
        def call(*args):
            raise FakeCompileError("no C++ compiler")
        return call

    monkeypatch.setattr(torch, "compile", broken_compile)
    torch.manual_seed(0)
    agent = DVFBAgent(OBS, ACT, small_config(), small_exploration(), perf=PerfConfig(compile=True))
    reference = copy.deepcopy(agent)
    reference.model.net_runner = NetRunner(None, "cpu")
    assert agent.net_runner.compiled
    batch = per_row_discount_batch(40, 0, torch.float32, obs_dim=OBS)
    with caplog.at_level(logging.WARNING):
        torch.manual_seed(1)
        metrics = agent.update(batch)
    assert "torch.compile failed" in caplog.text and not agent.net_runner.compiled
    torch.manual_seed(1)
    expected = reference.update(batch)
    for name in expected:
        torch.testing.assert_close(metrics[name], expected[name], rtol=0, atol=0)


def test_errors_of_the_computation_are_not_swallowed(monkeypatch):
    monkeypatch.setattr(torch, "compile", lambda module, **kw: lambda *a: (_ for _ in ()).throw(ValueError("bad")))
    runner = NetRunner(PerfConfig(compile=True), "cpu")
    net = nn.Linear(2, 2)
    runner.compile([net])
    with pytest.raises(ValueError, match="bad"):
        runner(net, torch.randn(1, 2))


def test_perf_options_reach_the_cli_config_and_resume_rules():
    from dvfb.cli import build_parser
    from dvfb.cli.common import pretrain_config as _pretrain_config
    from dvfb.runs.presets import preset_config
    from dvfb.workflows.pretrain import PretrainSession
    from dvfb.workflows.session import config_changes

    args = build_parser().parse_args(["pretrain", "--perf.precision", "bf16", "--perf.compile", "true"])
    config = _pretrain_config(args)
    assert (config.perf.precision, config.perf.compile, config.perf.cuda_graphs) == ("bf16", True, False)
    stored = preset_config("small")
    # compile / cuda_graphs only change how the same operations run: a resume may change them ...
    assert config_changes(stored, merge_perf(stored, compile=True), PretrainSession.resumable) == []
    # ... but not the precision, which changes the numerics.
    assert config_changes(stored, merge_perf(stored, precision="bf16"), PretrainSession.resumable) == ["perf"]


def merge_perf(config, **perf):
    from dvfb.core.config import merge

    return merge(config, {"perf": perf})
