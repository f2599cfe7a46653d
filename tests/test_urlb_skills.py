"""Tests for the URLB skill-discovery baselines DIAYN, SMM and APS (docs/methods.md, "DIAYN",
"SMM", "APS"): every loss and reward against a hand computation on a fixed batch (explicit loops
over rows, layers written out), the skill priors, APS's successor-feature critic and task
regression, and one agent-level update test per method."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from torch import nn

from dvfb.agents.aps import APSAgent, APSCore
from dvfb.agents.ddpg import DDPGConfig
from dvfb.agents.diayn import DIAYNAgent
from dvfb.agents.registry import get_spec
from dvfb.agents.smm import SMMAgent
from dvfb.data import Batch
from dvfb.rewards.aps import APSConfig, APSReward
from dvfb.rewards.diayn import DIAYNConfig, DIAYNReward
from dvfb.rewards.knn import KNNConfig
from dvfb.rewards.smm import SMMConfig, SMMReward
from dvfb.nets.skills import SkillSpec
from tiny import ACT, OBS, skill_batch

H, N = 32, 16


def relu_mlp(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """A plain ReLU MLP written out layer by layer from its Linear modules."""
    linears = [m for m in net if isinstance(m, nn.Linear)]
    for i, lin in enumerate(linears):
        x = x @ lin.weight.T + lin.bias
        if i < len(linears) - 1:
            x = torch.clamp(x, min=0.0)
    return x


def row_cross_entropy(logits: torch.Tensor, index: int) -> float:
    """-log softmax(logits)[index] of one row, from plain floats."""
    values = [float(v) for v in logits]
    top = max(values)
    log_sum = top + math.log(sum(math.exp(v - top) for v in values))
    return log_sum - values[index]


def one_hot_index(row: torch.Tensor) -> int:
    return [i for i, v in enumerate(row.tolist()) if v == 1.0][0]


def assert_orthogonal_zero_bias(net: nn.Module) -> None:
    for lin in (m for m in net.modules() if isinstance(m, nn.Linear)):
        w = lin.weight
        small = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
        torch.testing.assert_close(small, torch.eye(small.shape[0]), atol=1e-5, rtol=0)
        assert torch.equal(lin.bias, torch.zeros_like(lin.bias))


def test_config_defaults_are_urlb():
    d = DIAYNConfig()
    assert (d.skill_dim, d.skill_every, d.hidden_dim, d.scale, d.lr) == (16, 50, 1024, 1.0, 1e-4)
    s = SMMConfig()
    assert (s.skill_dim, s.hidden_dim, s.vae_hidden_dim, s.code_dim, s.vae_beta) == (4, 1024, 150, 128, 0.5)
    assert (s.disc_lr, s.vae_lr, s.state_ent, s.latent_ent, s.latent_cond_ent) == (1e-3, 1e-2, 1.0, 1.0, 1.0)
    a = APSConfig()
    assert (a.skill_dim, a.skill_every, a.hidden_dim, a.lr) == (10, 5, 1024, 1e-4)
    assert a.knn() == KNNConfig(k=12, average=True, clip=1e-4, normaliser="mean")


# ---------------------------------------------------------------------------------------------
# DIAYN

DIAYN_SKILL = SkillSpec("one_hot", 4, every=50)


def tiny_diayn(scale: float = 1.0, seed: int = 0) -> tuple[DIAYNReward, DIAYNConfig]:
    torch.manual_seed(seed)
    config = DIAYNConfig(skill_dim=4, hidden_dim=H, scale=scale)
    module = DIAYNReward(OBS, 4, config)
    module.make_optimizer(config.lr, fused=False)
    return module, config


def test_diayn_loss_and_reward_by_hand():
    module, _ = tiny_diayn(scale=2.0)
    assert_orthogonal_zero_bias(module)
    batch = skill_batch(N, DIAYN_SKILL.sample, step=0.5)
    with torch.no_grad():
        logits = relu_mlp(module.discriminator, batch.next_obs)  # s_{t+n}, not s_t
        ce = [row_cross_entropy(logits[i], one_hot_index(batch.z[i])) for i in range(N)]
        accuracy = sum(int(logits[i].argmax()) == one_hot_index(batch.z[i]) for i in range(N)) / N
    metrics = {}
    reward = module.update_and_score(batch, metrics)
    torch.testing.assert_close(metrics["diayn_loss"], torch.tensor(sum(ce) / N))
    torch.testing.assert_close(metrics["diayn_accuracy"], torch.tensor(accuracy))
    # The reward uses the discriminator after its step.
    with torch.no_grad():
        logits_after = relu_mlp(module.discriminator, batch.next_obs)
    expected = [[2.0 * (-row_cross_entropy(logits_after[i], one_hot_index(batch.z[i])) + math.log(4))]
                for i in range(N)]
    assert reward.shape == (N, 1) and not reward.requires_grad
    torch.testing.assert_close(reward, torch.tensor(expected), rtol=1e-5, atol=1e-5)
    before_step = torch.tensor([[2.0 * (-c + math.log(4))] for c in ce])
    assert not torch.allclose(reward, before_step, atol=1e-6)


def test_diayn_reward_is_zero_for_a_uniform_discriminator():
    module, _ = tiny_diayn()
    with torch.no_grad():
        module.discriminator[-1].weight.zero_()
    reward = module.score(skill_batch(N, DIAYN_SKILL.sample, seed=1, step=0.5))
    torch.testing.assert_close(reward, torch.zeros(N, 1))


# ---------------------------------------------------------------------------------------------
# SMM

SMM_SKILL = SkillSpec("one_hot", 4, every=None)
CODE = 6


def tiny_smm(seed: int = 0, **overrides) -> SMMReward:
    torch.manual_seed(seed)
    kw = dict(skill_dim=4, hidden_dim=H, vae_hidden_dim=12, code_dim=CODE, state_ent=1.5, latent_ent=0.7,
              latent_cond_ent=0.3)
    kw.update(overrides)
    module = SMMReward(OBS, 4, SMMConfig(**kw))
    module.make_optimizer(1.0, fused=False)
    return module


def smm_by_hand(module: SMMReward, batch: Batch, noise: torch.Tensor) -> dict:
    """VAE and discriminator terms with explicit layers and loops over rows."""
    c = module.config
    vae = module.vae
    with torch.no_grad():
        v = torch.cat([batch.obs, batch.z], -1)
        features = torch.clamp(relu_mlp(vae["encoder"], v), min=0.0)  # ReLU after the last layer too
        mean = features @ vae["mean"].weight.T + vae["mean"].bias
        log_var = features @ vae["log_var"].weight.T + vae["log_var"].bias
        recon = relu_mlp(vae["decoder"], mean + noise * torch.sqrt(torch.exp(log_var)))
        logits = relu_mlp(module.discriminator, batch.obs)
    kl, h_sz, h_zs = [], [], []
    for i in range(N):
        kl.append(sum(-0.5 * (1 + float(log_var[i, j]) - float(mean[i, j]) ** 2 - math.exp(float(log_var[i, j])))
                      for j in range(CODE)))
        h_sz.append(sum((float(recon[i, j]) - float(v[i, j])) ** 2 for j in range(v.shape[1])))
        h_zs.append(row_cross_entropy(logits[i], one_hot_index(batch.z[i])))
    vae_loss = c.vae_beta * sum(kl) / N + sum(h_sz) / (N * v.shape[1])
    reward = [[c.state_ent * h_sz[i] + c.latent_ent * math.log(4) + c.latent_cond_ent * h_zs[i]] for i in range(N)]
    return {"vae_loss": vae_loss, "disc_loss": sum(h_zs) / N, "h_sz": h_sz, "h_zs": h_zs, "reward": reward}


def test_smm_losses_and_terms_by_hand():
    module = tiny_smm()
    assert_orthogonal_zero_bias(module)
    batch = skill_batch(N, SMM_SKILL.sample, step=0.5)
    noise = torch.randn(N, CODE, generator=torch.Generator().manual_seed(7))
    hand = smm_by_hand(module, batch, noise)
    terms = module.terms(batch, noise=noise)
    torch.testing.assert_close(terms["vae_loss"], torch.tensor(hand["vae_loss"]), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(terms["disc_loss"], torch.tensor(hand["disc_loss"]), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(terms["h_sz"], torch.tensor(hand["h_sz"]).unsqueeze(-1), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(terms["h_zs"], torch.tensor(hand["h_zs"]).unsqueeze(-1), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(module.reward(terms["h_sz"], terms["h_zs"]), torch.tensor(hand["reward"]),
                               rtol=1e-5, atol=1e-5)


def test_smm_reward_is_the_update_pass_before_the_step():
    module = tiny_smm(seed=1)
    batch = skill_batch(N, SMM_SKILL.sample, seed=2, step=0.5)
    torch.manual_seed(11)
    noise = torch.randn(N, CODE)  # the draw update_and_score makes after the same seeding
    hand = smm_by_hand(module, batch, noise)
    before = copy.deepcopy(module.state_dict())
    metrics = {}
    torch.manual_seed(11)
    reward = module.update_and_score(batch, metrics)
    assert reward.shape == (N, 1) and not reward.requires_grad
    torch.testing.assert_close(reward, torch.tensor(hand["reward"]), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(metrics["smm_vae_loss"], torch.tensor(hand["vae_loss"]), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(metrics["smm_disc_loss"], torch.tensor(hand["disc_loss"]), rtol=1e-5, atol=1e-6)
    assert all(not torch.equal(before[k], v) for k, v in module.state_dict().items())


def test_smm_one_optimiser_with_two_learning_rates_equals_two_adams():
    module = tiny_smm(seed=3)
    twin = copy.deepcopy(module)
    lrs = sorted(group["lr"] for group in module.optimizer.param_groups)
    assert lrs == [1e-3, 1e-2]  # the defaults disc_lr and vae_lr, whatever lr the agent passes
    disc_opt = torch.optim.Adam(twin.discriminator.parameters(), lr=1e-3)
    vae_opt = torch.optim.Adam(twin.vae.parameters(), lr=1e-2)
    for step in range(3):
        batch = skill_batch(N, SMM_SKILL.sample, seed=10 + step, step=0.5)
        noise = torch.randn(N, CODE, generator=torch.Generator().manual_seed(step))
        module._step(module.terms(batch, noise=noise))
        terms = twin.terms(batch, noise=noise)  # URLB: VAE step, then discriminator step
        vae_opt.zero_grad()
        terms["vae_loss"].backward()
        vae_opt.step()
        disc_opt.zero_grad()
        terms["disc_loss"].backward()
        disc_opt.step()
    for (name, a), (_, b) in zip(module.named_parameters(), twin.named_parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)


# ---------------------------------------------------------------------------------------------
# APS

APS_SKILL = SkillSpec("sphere", 4, every=5, radius=1.0)


def tiny_aps(seed: int = 0, **overrides) -> APSReward:
    torch.manual_seed(seed)
    kw = dict(skill_dim=4, hidden_dim=H, knn_k=3)
    kw.update(overrides)
    config = APSConfig(**kw)
    module = APSReward(OBS, 4, config)
    module.make_optimizer(config.lr, fused=False)
    return module


def unit(row: list[float]) -> list[float]:
    norm = math.sqrt(sum(v * v for v in row))
    return [v / norm for v in row]


def test_aps_loss_and_reward_by_hand():
    module = tiny_aps()
    assert_orthogonal_zero_bias(module)
    batch = skill_batch(N, APS_SKILL.sample, step=0.5)
    w = batch.z.tolist()
    with torch.no_grad():
        phi = relu_mlp(module.features, batch.next_obs).tolist()  # s_{t+n}
    loss = -sum(sum(a * b for a, b in zip(w[i], unit(phi[i]))) for i in range(N)) / N
    metrics = {}
    reward = module.update_and_score(batch, metrics)
    torch.testing.assert_close(metrics["aps_loss"], torch.tensor(loss), rtol=1e-5, atol=1e-6)
    # Reward with the updated features.
    with torch.no_grad():
        h = relu_mlp(module.features, batch.next_obs).tolist()
    k, clip = 3, 1e-4
    nearest = [sorted(math.dist(h[i], h[j]) for j in range(N))[:k] for i in range(N)]  # self included
    flat = [d for row in nearest for d in row]
    count = 1e-4 + len(flat)  # running mean from its prior (mean 0, count 1e-4)
    running_mean = (sum(flat) / len(flat)) * len(flat) / count
    entropy = [math.log(1 + sum(max(d / running_mean - clip, 0.0) for d in row) / k) for row in nearest]
    sf = [sum(a * b for a, b in zip(w[i], unit(h[i]))) for i in range(N)]
    assert reward.shape == (N, 1) and not reward.requires_grad
    torch.testing.assert_close(reward, torch.tensor([[e + s] for e, s in zip(entropy, sf)]), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(metrics["aps_entropy_reward"], torch.tensor(sum(entropy) / N), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(metrics["aps_sf_reward"], torch.tensor(sum(sf) / N), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(module.entropy.stats.mean, torch.tensor(running_mean, dtype=torch.float64))


def test_aps_regress_task_hand_example():
    module = tiny_aps()
    module.features = nn.Identity()  # phi(s) = s: features known by hand (obs width 2 = d here)
    obs = torch.tensor([[3.0, 4.0], [1.0, 0.0], [0.0, 2.0]])
    reward = torch.tensor([[1.0], [2.0], [-1.0]])
    # phî = (0.6, 0.8), (1, 0), (0, 1); sum_i R_i phî_i = (2.6, -0.2)
    expected = torch.tensor([2.6, -0.2]) / math.sqrt(2.6 ** 2 + 0.2 ** 2)
    task = module.regress_task(obs, reward)
    torch.testing.assert_close(task, expected)
    torch.testing.assert_close(module.regress_task(obs, reward[:, 0]), expected)  # (N,) rewards too
    # The same as URLB's least-squares solve R x = Phî, normalised.
    x = torch.linalg.lstsq(reward, torch.nn.functional.normalize(obs, dim=-1)).solution[0]
    torch.testing.assert_close(task, x / x.norm())
    assert torch.equal(module.regress_task(obs, torch.zeros(3, 1)), torch.zeros(2))


def test_aps_regress_task_uses_normalised_features_of_s_t():
    module = tiny_aps(seed=4)
    batch = skill_batch(64, APS_SKILL.sample, seed=5, step=0.5)
    with torch.no_grad():
        phi = relu_mlp(module.features, batch.obs)  # s_t, not s_{t+n}
    x = torch.linalg.lstsq(batch.reward, phi / phi.norm(dim=-1, keepdim=True)).solution[0]
    task = module.regress_task(batch.obs, batch.reward)
    assert task.shape == (4,)
    torch.testing.assert_close(task, x / x.norm(), rtol=1e-5, atol=1e-6)


def test_aps_successor_feature_critic_by_hand():
    torch.manual_seed(0)
    core = APSCore(OBS, 4, ACT, DDPGConfig(hidden_dim=H, batch_size=N, fused_adam=False))
    assert core.critic.heads.out_dim == 4 and core.critic_target.heads.out_dim == 4
    batch = skill_batch(N, APS_SKILL.sample, step=0.5)
    with torch.no_grad():
        q = core.critic_values(core.critic, batch.obs, batch.z, batch.action)
        psi = core.critic(batch.obs, batch.z, batch.action)  # (2, N, d)
    expected = torch.tensor([[[sum(float(psi[k, i, j]) * float(batch.z[i, j]) for j in range(4))]
                              for i in range(N)] for k in range(2)])
    assert q.shape == (2, N, 1)
    torch.testing.assert_close(q, expected, rtol=1e-5, atol=1e-6)
    # A fresh critic (fine-tuning's) is a successor-feature critic as well, with the same trunk.
    fresh = core.build_critic()
    assert fresh.heads.out_dim == 4 and type(fresh.trunk) is type(core.critic.trunk)


# ---------------------------------------------------------------------------------------------
# Skill priors


@pytest.mark.parametrize("agent_cls, config, dim, every", [
    (DIAYNAgent, DIAYNConfig(hidden_dim=H), 16, 50),
    (SMMAgent, SMMConfig(hidden_dim=H), 4, None),
])
def test_one_hot_priors(agent_cls, config, dim, every):
    torch.manual_seed(0)
    agent = agent_cls(OBS, ACT, DDPGConfig(hidden_dim=H, batch_size=N, fused_adam=False), config)
    assert agent.skill.kind == "one_hot" and agent.skill.dim == dim and agent.skill.every == every
    assert agent.skill.at_episode_start
    skills = agent.sample_skill(4000)
    assert skills.shape == (4000, dim) and skills.dtype == torch.float32
    assert set(skills.unique().tolist()) == {0.0, 1.0}
    assert torch.equal(skills.sum(-1), torch.ones(4000))
    counts = skills.sum(0)
    assert counts.min() > 0.7 * 4000 / dim  # every skill drawn, roughly uniformly
    if every is None:  # SMM: per episode only
        assert not agent.skill.due(50, episode_start=False) and agent.skill.due(7, episode_start=True)
    else:
        assert agent.skill.due(every, episode_start=False) and not agent.skill.due(every + 1, episode_start=False)


def test_aps_prior_is_unit_norm_every_five_steps():
    torch.manual_seed(0)
    agent = APSAgent(OBS, ACT, DDPGConfig(hidden_dim=H, batch_size=N, fused_adam=False), APSConfig(hidden_dim=H))
    assert agent.skill.kind == "sphere" and agent.skill.dim == 10 and agent.skill.every == 5
    skills = agent.sample_skill(2000)
    assert skills.shape == (2000, 10)
    torch.testing.assert_close(skills.norm(dim=-1), torch.ones(2000))
    # Isotropic: the mean direction is near 0 and every coordinate's second moment near 1/d.
    assert skills.mean(0).abs().max() < 0.05
    torch.testing.assert_close(skills.pow(2).mean(0), torch.full((10,), 0.1), atol=0.015, rtol=0)


# ---------------------------------------------------------------------------------------------
# Agents


AGENT_CASES = [
    (DIAYNAgent, DIAYNConfig(skill_dim=4, hidden_dim=H)),
    (SMMAgent, SMMConfig(hidden_dim=H, vae_hidden_dim=12, code_dim=CODE)),
    (APSAgent, APSConfig(skill_dim=4, hidden_dim=H, knn_k=4)),
]


@pytest.mark.parametrize("agent_cls, config", AGENT_CASES, ids=lambda v: getattr(v, "name", ""))
def test_agent_update_moves_every_optimised_parameter(agent_cls, config):
    torch.manual_seed(0)
    agent = agent_cls(OBS, ACT, DDPGConfig(hidden_dim=H, batch_size=32, fused_adam=False), config)
    assert agent.replay_needs().nstep == 3
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    optimised = {id(p) for opt in agent.optimizers().values() for g in opt.param_groups for p in g["params"]}
    assert "reward_optimizer" in agent.optimizers()
    for step in range(3):
        g = torch.Generator().manual_seed(step)
        obs = torch.randn(32, OBS, generator=g)
        batch = Batch(obs, torch.rand(32, ACT, generator=g) * 2 - 1, torch.zeros(32, 1),
                      torch.full((32, 1), 0.99 ** 3), obs + 0.3 * torch.randn(32, OBS, generator=g), None,
                      agent.sample_skill(32, generator=g))
        metrics = agent.update(batch)
        assert metrics and all(isinstance(v, torch.Tensor) and v.dim() == 0 for v in metrics.values())
        assert all(torch.isfinite(v) for v in metrics.values()), metrics
    for name, p in agent.named_parameters():
        if p.requires_grad:
            assert id(p) in optimised, f"{name} belongs to no optimiser"
        if id(p) in optimised:
            assert not torch.equal(before[name], p), f"{name} did not change"


@pytest.mark.parametrize("name, section", [("diayn", DIAYNConfig), ("smm", SMMConfig), ("aps", APSConfig)])
def test_registration(name, section):
    spec = get_spec(name)
    assert spec.family == "skill_discovery" and spec.finetuner == "urlb" and spec.zero_shot == "skill_selection"
    assert spec.sections == {"ddpg": DDPGConfig, name: section}
    assert spec.presets["small"][name] == {"hidden_dim": 256}
