"""Tests for dvfb.protocols.latent_search: LoLA's pieces by hand (leave-one-out, lookahead return,
score gradient, one Adam step on mu), its search through the real segment bookkeeping on a replay,
ReLA's reward model, residual target and z step, the frozen networks, and fine-tuning end to end
with an exact resume (docs/methods.md, "Latent search"; spec methods_2025 §2.7)."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
import torch

from dvfb.agents import make_agent
from dvfb.agents.fb import FBAgent
from dvfb.data import Batch, ReplayBuffer
from dvfb.core.errors import ConfigError
from dvfb.nets import ACTION_EPS, project_to_sphere, skill_values
from dvfb.protocols import finetuner_choices
from dvfb.protocols.latent_search import (
    LatentSearchConfig,
    LatentSearchFinetuner,
    leave_one_out,
    reward_model,
    search_loss,
    segment_return,
)
from dvfb.runs import load_checkpoint
from dvfb.workflows.finetune import finetune
from dvfb.workflows.pretrain import pretrain
from tiny import ACT, D, OBS, random_batch, tiny_config, tiny_run_config

# Walker: its rewards are dense (the maze's are ~1e-46 away from the goal, and mu would not move).
TASK = "walker_stand"


def make_model(**overrides):
    torch.manual_seed(0)
    return FBAgent(OBS, ACT, tiny_config(**overrides)).model


def inference_replay(model, steps: int = 200, seed: int = 0, reward=None, episode_length: int = 100) -> ReplayBuffer:
    """A replay holding ``steps`` labelled random transitions (episodes of ``episode_length``), with
    rewards ``reward(next_obs)`` (default: random)."""
    g = torch.Generator().manual_seed(seed)
    replay = ReplayBuffer(10_000, OBS, ACT, D, max_episode_length=episode_length)
    obs = torch.randn(OBS, generator=g)
    for t in range(steps):
        if t % episode_length == 0:
            replay.start_episode(obs.numpy())
        next_obs = obs + 0.3 * torch.randn(OBS, generator=g)
        r = float(torch.randn((), generator=g)) if reward is None else float(reward(next_obs))
        action = torch.rand(ACT, generator=g) * 2 - 1
        replay.add(action.numpy(), r, 1.0, next_obs.numpy(), np.zeros(D, np.float32))
        obs = next_obs
    return replay


def built(model, replay=None, z=None, **config):
    z = project_to_sphere(torch.randn(D, generator=torch.Generator().manual_seed(5))) if z is None else z
    finetuner = LatentSearchFinetuner(model, z, LatentSearchConfig(**config))
    finetuner.bind_replay(inference_replay(model) if replay is None else replay)
    return finetuner


class Rollout:
    """The fine-tuning loop's calls around a fine-tuner, by hand: a skill rule call before every step,
    then the step's transition into the replay, with ``reward(step, skill)`` and random states."""

    def __init__(self, finetuner, replay, episode_length: int, seed: int = 0):
        self.finetuner, self.replay, self.episode_length = finetuner, replay, episode_length
        finetuner.bind_replay(replay)  # its reward model is fitted already: this only binds the replay
        self.g = torch.Generator().manual_seed(seed)
        self.step, self.skill, self.obs = 0, None, None

    def run(self, steps: int, reward, after=None):
        for _ in range(steps):
            start = self.step % self.episode_length == 0
            if start:
                self.obs = torch.randn(OBS, generator=self.g)
                self.replay.start_episode(self.obs.numpy())
            self.skill = self.finetuner.rollout_skill(self.step, start, self.skill, self.g, obs=self.obs.numpy())
            next_obs = self.obs + 0.1 * torch.randn(OBS, generator=self.g)
            self.replay.add(np.zeros(ACT, np.float32), float(reward(self.step, self.skill)), 1.0, next_obs.numpy(),
                            self.skill.numpy())
            self.obs = next_obs
            self.step += 1
            if after is not None:
                after()


# ---------------------------------------------------------------------------------------------
# LoLA's pieces (spec §2.7 items 1-3)


def test_leave_one_out_baseline():
    a = leave_one_out(torch.tensor([1.0, 2.0, 3.0, 6.0], dtype=torch.float64))
    assert torch.allclose(a, torch.tensor([-8 / 3, -4 / 3, 0.0, 4.0], dtype=torch.float64), atol=1e-12)
    returns = torch.randn(7, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 10
    a = leave_one_out(returns)
    assert abs(float(a.sum())) < 1e-10
    assert float(a[2]) == pytest.approx(float(returns[2] - (returns.sum() - returns[2]) / 6), abs=1e-12)


@pytest.mark.parametrize("steps", [1, 7, 250])
def test_lookahead_return_with_an_exact_terminal_value_is_the_value(steps):
    assert segment_return(np.ones(steps), np.ones(steps), 0.98, 1 / (1 - 0.98)) == pytest.approx(50.0, abs=1e-11)


def test_lookahead_return_by_hand_and_no_terminal_value_after_termination():
    r = [1.0, -2.0, 0.5]
    assert segment_return(r, [1, 1, 1], 0.9, 10.0) == pytest.approx(1 - 1.8 + 0.405 + 0.729 * 10, abs=1e-12)
    assert segment_return(r, [1, 1, 0], 0.9, 10.0) == pytest.approx(1 - 1.8 + 0.405, abs=1e-12)


def test_score_gradient_follows_a_planted_linear_return():
    """R(z) = z . u with mu orthogonal to u: the Monte-Carlo mean of the ascent direction
    -grad_mu L (k = 64 samples, leave-one-out) points along u."""
    d, k, sigma = 8, 64, 0.2
    g = torch.Generator().manual_seed(0)
    u = torch.zeros(d)
    u[0] = 1.0
    mu0 = torch.zeros(d)
    mu0[1] = 1.0
    total = torch.zeros(d)
    for _ in range(200):
        samples = mu0 + sigma * torch.randn(k, d, generator=g)
        samples = samples / samples.norm(dim=-1, keepdim=True)
        mu = mu0.clone().requires_grad_(True)
        search_loss(mu, samples, leave_one_out(samples @ u), sigma).backward()
        total -= mu.grad
    assert float(total @ u / total.norm()) > 0.99


def test_search_through_segments_converges_to_a_planted_direction():
    """The real bookkeeping: segments of one step, each rewarded z_i . u (no terminal value), over
    episodes of 40 steps; mu stays a unit vector after every step and ends near u."""
    model = make_model()
    u = torch.nn.functional.normalize(torch.randn(D, generator=torch.Generator().manual_seed(3)), dim=0)
    start = project_to_sphere(-u + 0.5 * torch.randn(D, generator=torch.Generator().manual_seed(4)))
    finetuner = built(model, z=start, horizon=1, samples=8, terminal_value="none", lr=0.05)
    assert float(finetuner.mu.detach() @ u) < 0
    replay = ReplayBuffer(10_000, OBS, ACT, D, max_episode_length=40)
    norms = []

    def after():
        norms.append(float(finetuner.mu.detach().norm()))

    Rollout(finetuner, replay, 40).run(8 * 80 + 1, lambda step, skill: float(skill @ u) / math.sqrt(D), after)
    assert int(finetuner.update(None)["search_updates"]) == 80
    assert max(abs(n - 1) for n in norms) < 1e-6
    assert float(finetuner.mu.detach() @ u) > 0.95
    assert torch.allclose(finetuner.skill, project_to_sphere(finetuner.mu.detach()))


def test_one_mu_update_by_hand():
    """Fixed samples and returns: A by leave-one-out, g = mean_i A_i (mu - z_i) / sigma^2, Adam's
    first step mu - lr g / (|g| + eps), renormalised."""
    model = make_model()
    finetuner = built(model, sigma=0.3, lr=0.05, samples=4)
    g = torch.Generator().manual_seed(2)
    samples = torch.nn.functional.normalize(torch.randn(4, D, generator=g), dim=-1)
    returns = torch.tensor([3.0, -1.0, 0.5, 2.0], dtype=torch.float64)
    mu0 = finetuner.mu.detach().clone()
    finetuner.search_step(samples, returns)
    a = torch.tensor([3.0 - 1.5 / 3, -1.0 - 5.5 / 3, 0.5 - 4.0 / 3, 2.0 - 2.5 / 3])
    grad = (a[:, None] * (mu0 - samples)).mean(0) / 0.3 ** 2
    expected = mu0 - 0.05 * grad / (grad.abs() + 1e-8)
    expected = expected / expected.norm()
    assert torch.allclose(finetuner.mu.detach(), expected, atol=1e-6)
    assert float(finetuner.mu.detach().norm()) == pytest.approx(1.0, abs=1e-6)
    assert torch.allclose(finetuner.skill, math.sqrt(D) * expected, atol=1e-5)


def test_segments_sample_around_mu_end_with_their_episode_and_read_the_replay_exactly():
    """Segments of 5 steps in episodes of 12 (so 5, 5, 2): each acts with one proj(z_i); the
    returns pending after 3 segments are the hand-discounted rewards plus gamma^m V_i, with V_i
    the frozen value of the segment's last next state."""
    model = make_model(discount=0.9)
    finetuner = built(model, horizon=5, samples=4)
    replay = ReplayBuffer(10_000, OBS, ACT, D, max_episode_length=12)
    rollout = Rollout(finetuner, replay, 12)
    skills, rewards = [], []

    def reward(step, skill):
        skills.append(skill)
        rewards.append(0.1 * step + 1)
        return rewards[-1]

    rollout.run(13, reward)  # the 13th call closes the third segment at the episode's end
    assert [s is skills[0] for s in skills[:5]] == [True] * 5 and skills[5] is not skills[4]
    assert skills[10] is not skills[9] and skills[12] is not skills[11]
    for s in (skills[0], skills[5], skills[10], skills[12]):
        assert float(s.norm()) == pytest.approx(math.sqrt(D), abs=1e-5)
    data = replay.transitions(gamma=1.0)
    expected = []
    for begin, end, skill in ((0, 5, skills[0]), (5, 10, skills[5]), (10, 12, skills[10])):
        last = data.next_obs[end - 1: end]
        with torch.no_grad():
            value = float(model.skill_value(last, model.actor(last, skill[None]), skill[None], task=finetuner.w_r)[0])
        expected.append(sum(0.9 ** t * rewards[begin + t] for t in range(end - begin)) + 0.9 ** (end - begin) * value)
    assert finetuner._pending_returns == pytest.approx(expected, abs=1e-5)
    assert int(finetuner.update(None)["search_updates"]) == 0


@pytest.mark.parametrize("which", ["mu", "z"])
def test_terminal_values_read_mu_and_z_i_on_the_unit_sphere(which):
    """``terminal_value = mu`` or ``z``: ``V = min_k F_k(s, mean pi(s, proj z_i), proj z_i) . w`` with
    ``w`` the unit vector mu or z_i (spec methods_2025 §2.4), not its projection (sqrt(d) times it)."""
    model = make_model()
    finetuner = built(model, terminal_value=which, sigma=0.5)
    g = torch.Generator().manual_seed(4)
    sample = torch.nn.functional.normalize(torch.randn(D, generator=g), dim=0)
    finetuner.search_step(torch.nn.functional.normalize(torch.randn(2, D, generator=g), dim=-1),
                          torch.tensor([1.0, 2.0], dtype=torch.float64))  # mu moves off z_r's direction
    obs = torch.randn(OBS, generator=g)
    unit = finetuner.mu.detach() if which == "mu" else sample
    assert float(unit.norm()) == pytest.approx(1.0, abs=1e-6)
    skill = project_to_sphere(sample)
    with torch.no_grad():
        forward = model.forward_map(obs[None], model.actor(obs[None], skill[None]), skill[None])  # (heads, 1, d)
        expected = float((forward[:, 0] @ unit).min())
    assert finetuner.terminal_value(obs, sample) == pytest.approx(expected, rel=1e-5, abs=1e-6)
    assert abs(expected) > 1e-3  # a value whose scale the projection would change by sqrt(d)


# ---------------------------------------------------------------------------------------------
# The reward model and ReLA (spec §2.7 items 4-5)


def test_least_squares_on_whitened_features_equals_the_mean_of_r_b():
    model = make_model()
    batch = random_batch(500, 3)
    features = model.backward_features(batch.obs, batch.next_obs).double()
    reward = batch.reward[:, 0].double()
    w_r, coef = reward_model(features, reward, "measure")
    assert torch.allclose(w_r, features.T @ reward / 500, atol=1e-12)
    phi = features @ torch.linalg.inv(features.T @ features / 500)
    least_squares = torch.linalg.lstsq(phi, reward[:, None]).solution[:, 0]
    assert torch.allclose(least_squares, w_r, atol=1e-5)
    assert torch.allclose(features @ coef, phi @ w_r, atol=1e-8)  # phi . w_r = B . coef
    w_sf, coef_sf = reward_model(features, reward, "regression")
    assert torch.equal(w_sf, coef_sf)
    assert torch.allclose(w_sf, torch.linalg.lstsq(features, reward[:, None]).solution[:, 0], atol=1e-8)


def test_planted_linear_reward_has_no_residual():
    model = make_model()
    c = torch.randn(D, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        replay = inference_replay(model, 300, reward=lambda s: model.backward_map(s[None])[0] @ c)
    finetuner = built(model, replay, method="rela", rela_batch_size=64)
    assert torch.allclose(finetuner.residual_coef, c, atol=1e-4)
    batch = replay.sample(64, 0.99, generator=torch.Generator().manual_seed(0))
    _, residual = finetuner.residual_target(batch, finetuner.z.detach().expand(64, -1))
    assert residual.abs().max() < 1e-4


def test_residual_target_and_critic_loss_by_hand():
    model = make_model(stddev=0.0)  # training samples are then the clamped means
    replay = inference_replay(model, 300)
    finetuner = built(model, replay, method="rela", rela_batch_size=64)
    with torch.no_grad():  # a target that differs from the online critic
        for p in finetuner.residual_critic_target.parameters():
            p.add_(0.05)
    critic = copy.deepcopy(finetuner.residual_critic)
    batch = replay.sample(64, 0.99, generator=torch.Generator().manual_seed(1))
    z = finetuner.z.detach().expand(64, -1)
    with torch.no_grad():
        features = model.backward_map(batch.next_obs)
        residual = batch.reward - (features @ finetuner.residual_coef)[:, None]
        next_action = model.actor(batch.next_obs, z).clamp(-1 + ACTION_EPS, 1 - ACTION_EPS)
        none = batch.obs.new_zeros(64, 0)
        next_q = finetuner.residual_critic_target(batch.next_obs, none, next_action).min(0).values
        target = residual + batch.discount * next_q
        q = critic(batch.obs, none, batch.action)
        loss = sum(((q[k] - target) ** 2).mean() for k in range(2))
    got, got_residual = finetuner.residual_target(batch, z)
    assert torch.allclose(got, target, atol=1e-6) and torch.allclose(got_residual, residual, atol=1e-6)
    metrics = finetuner.update(batch)
    assert float(metrics["residual_critic_loss"]) == pytest.approx(float(loss), rel=1e-5)
    assert float(metrics["residual_reward"]) == pytest.approx(float(residual.mean()), abs=1e-6)


def test_with_a_zero_residual_critic_the_z_step_follows_f_dot_w_r_alone():
    """r_res = 0 and Q_res = 0 (all its weights zero): the critic stays zero, and z takes Adam's
    first step on -mean min_k F_k(s, pi(s, z), z) . w_r, then the projection."""
    model = make_model(stddev=0.0)
    c = torch.randn(D, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        replay = inference_replay(model, 300, reward=lambda s: model.backward_map(s[None])[0] @ c)
    finetuner = built(model, replay, method="rela", rela_batch_size=64, rela_z_lr=0.01)
    with torch.no_grad():
        for p in [*finetuner.residual_critic.parameters(), *finetuner.residual_critic_target.parameters()]:
            p.zero_()
    batch = replay.sample(64, 0.99, generator=torch.Generator().manual_seed(2))
    batch = Batch(batch.obs, batch.action, (model.backward_map(batch.next_obs) @ finetuner.residual_coef)[:, None]
                  .detach(), batch.discount, batch.next_obs, None, None)
    z0 = finetuner.z.detach().clone().requires_grad_(True)
    rows = z0.expand(64, -1)
    mean = model.actor(batch.obs, rows)
    action = mean + (mean.clamp(-1 + ACTION_EPS, 1 - ACTION_EPS) - mean).detach()  # straight-through clamp
    value = skill_values(model.forward_map(batch.obs, action, rows), finetuner.w_r.expand(64, -1)).min(0).values
    (-value.mean()).backward()
    expected = project_to_sphere(z0.detach() - 0.01 * z0.grad / (z0.grad.abs() + 1e-8))
    metrics = finetuner.update(batch)
    assert float(metrics["residual_critic_loss"]) < 1e-8
    assert all(float(p.detach().abs().max()) == 0 for p in finetuner.residual_critic.parameters())
    assert torch.allclose(finetuner.z.detach(), expected, atol=1e-5)
    assert torch.equal(finetuner.skill, finetuner.z.detach())
    assert float(finetuner.z.detach().norm()) == pytest.approx(math.sqrt(D), abs=1e-5)


@pytest.mark.parametrize("method", ["lola", "rela"])
def test_pretrained_networks_stay_bit_identical(method):
    model = make_model()
    before = {k: copy.deepcopy(m.state_dict()) for k, m in model.snapshot_modules().items()}
    replay = inference_replay(model, 300)
    finetuner = built(model, replay, method=method, horizon=3, samples=2, rela_batch_size=32)
    start = finetuner.skill.clone()
    assert all(not p.requires_grad for m in model.snapshot_modules().values() for p in m.parameters())
    rollout = Rollout(finetuner, replay, 20)
    for _ in range(5):
        rollout.run(6, lambda step, skill: float(skill.sum()))
        finetuner.update(replay.sample(32, 0.99, generator=torch.Generator().manual_seed(0)))
    assert not torch.equal(finetuner.skill, start)  # the skill moved ...
    for key, module in model.snapshot_modules().items():  # ... and nothing else did
        for name, tensor in module.state_dict().items():
            assert torch.equal(tensor, before[key][name]), (key, name)


def test_training_state_round_trip_continues_identically():
    """A LoLA fine-tuner rebuilt from its training state mid-segment (with pending samples) goes on
    exactly as the original."""
    model = make_model()
    replay = inference_replay(model, 300)
    finetuner = built(model, replay, horizon=4, samples=3)
    rollout = Rollout(finetuner, replay, 10)
    rollout.run(20, lambda step, skill: float(skill[0]))  # segments [0, 4), [4, 8), [8, 10), [10, 14), ...
    state = copy.deepcopy(finetuner.training_state())
    assert len(state["search"]["pending_returns"]) == 2 and state["search"]["segment_start"] == 18
    twin = LatentSearchFinetuner(model, torch.zeros(D) + 1, LatentSearchConfig(horizon=4, samples=3))
    twin.load_training_state(state)
    rollout_twin = Rollout(twin, ReplayBuffer.from_state(replay.state_dict()), 10)
    rollout_twin.g.set_state(rollout.g.get_state())
    rollout_twin.step, rollout_twin.skill, rollout_twin.obs = rollout.step, rollout.skill, rollout.obs
    for r in (rollout, rollout_twin):
        r.run(30, lambda step, skill: float(skill[0]))
    assert torch.equal(twin.mu, finetuner.mu) and torch.equal(twin.skill, finetuner.skill)
    assert twin._pending_returns == finetuner._pending_returns
    for key, value in finetuner.training_state()["optimizers"]["search"]["state"][0].items():
        assert torch.equal(value, twin.training_state()["optimizers"]["search"]["state"][0][key]), key


def test_which_models_and_runs_it_takes():
    """The FB family and the successor features (whose w_r is the regression on phi); not DDPG
    agents, nor groups."""
    with pytest.raises(ConfigError, match="one run at a time"):
        LatentSearchFinetuner.check_group(LatentSearchConfig())
    assert "latent_search" in finetuner_choices("fb") and "latent_search" in finetuner_choices("sf")
    assert "latent_search" not in finetuner_choices("rnd")
    config = LatentSearchConfig()
    torch.manual_seed(0)
    sf = make_agent("sf", OBS, ACT, tiny_run_config("sf"), "cpu").model
    LatentSearchFinetuner.check(sf, config)
    replay = inference_replay(sf, 200)
    finetuner = built(sf, replay)
    data = replay.transitions(gamma=1.0)
    phi = sf.backward_features(data.obs, data.next_obs).double()
    expected = torch.linalg.lstsq(phi, data.reward.double()).solution[:, 0]
    assert torch.allclose(finetuner.w_r.double(), expected, atol=1e-4)
    with pytest.raises(ConfigError, match="skill value"):
        LatentSearchFinetuner.check(make_agent("rnd", OBS, ACT, tiny_run_config("rnd"), "cpu").model, config)


# ---------------------------------------------------------------------------------------------
# End to end through the fine-tuning workflow


FAST_INFERENCE = {"steps": 300, "random_action_steps": 100, "samples": 300, "eval_episodes": 1}
SCHEDULE = {"eval_every": 1000, "eval_episodes": 1, "checkpoint_every": 1000, "update_every": 4}


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory):
    run = tmp_path_factory.mktemp("latent") / "fb"
    pretrain(tiny_run_config("fb", domain="walker", frames=600, seed_frames=500), run, progress=False)
    return run


def _finetune(run, name, frames, resume=False, **options):
    return finetune(run, TASK, inference=FAST_INFERENCE, name=name, resume=resume, progress=False,
                    protocol="latent_search", finetune={**SCHEDULE, "frames": frames, **options})


def _same_state(a, b, path="state"):
    assert type(a) is type(b), path
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for key in a:
            _same_state(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _same_state(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), path
    else:
        assert a == b, path


def test_lola_fine_tunes_end_to_end_and_resumes_exactly(pretrained):
    """Episodes of 1000 steps in segments of 200: 5 per episode, a mu step every 3 segments; the
    resume at 1000 steps has one pending sample and continues as if uninterrupted."""
    options = {"horizon": 200, "samples": 3}
    full = _finetune(pretrained, "full", 2000, **options)
    _finetune(pretrained, "split", 1000, **options)
    split = _finetune(pretrained, "split", 2000, resume=True, **options)
    curve = json.loads((full.path / "curve.json").read_text())
    assert [p["frames"] for p in curve["curve"]] == [0, 1000, 2000]
    assert [e["frames"] for e in curve["episodes"]] == [1000, 2000]  # every training episode, the last one too
    assert json.loads((full.path / "config.json").read_text())["protocol"] == "latent_search"
    records = [json.loads(line) for line in (full.path / "metrics" / "train.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1000, 2000] and 1 < records[-1]["search_updates"] < 3
    assert json.loads((split.path / "curve.json").read_text()) == curve
    _same_state(load_checkpoint(full.path)["finetuner"], load_checkpoint(split.path)["finetuner"])
    state = load_checkpoint(full.path)["finetuner"]
    assert float(state["finetuner"]["mu"].norm()) == pytest.approx(1.0, abs=1e-6)
    # Segments closed at 200, 400, ..., 1800 (the last one still open at 2000): three mu steps.
    search = state["search"]
    assert int(search["metrics"]["search_updates"]) == 3 and len(search["pending_returns"]) == 0
    assert search["segment_start"] == 1800 and 0 < float(search["metrics"]["search_step_angle"]) < math.pi


def test_rela_fine_tunes_end_to_end_on_its_own_steps_with_w_r_from_the_inference_steps(pretrained):
    """ReLA's replay holds only its fine-tuning steps (spec methods_2025 §2.3): 1000 of them after
    1000 frames, where the option that mixes the 300 labelled inference steps in holds 1300. Both
    fit the same reward model w_r on those 300 steps, bit for bit, and both move z."""
    options = dict(method="rela", rela_batch_size=32, rela_hidden_dim=16)
    run = _finetune(pretrained, "rela", 1000, **options)
    mixed = _finetune(pretrained, "rela_mixed", 1000, rela_inference_replay=True, **options)
    curve = json.loads((run.path / "curve.json").read_text())
    assert [p["frames"] for p in curve["curve"]] == [0, 1000]
    record = json.loads((run.path / "metrics" / "train.jsonl").read_text().splitlines()[-1])
    assert {"residual_critic_loss", "fb_value", "residual_value", "z_start_cos"} <= set(record)
    assert all(math.isfinite(v) for v in record.values() if isinstance(v, float))
    own, both = load_checkpoint(run.path), load_checkpoint(mixed.path)
    assert int(own["replay"]["lengths"].sum()) == 1000
    assert int(both["replay"]["lengths"].sum()) == 1000 + FAST_INFERENCE["steps"]
    state, state_mixed = own["finetuner"]["finetuner"], both["finetuner"]["finetuner"]
    assert torch.equal(state["w_r"], state_mixed["w_r"]) and float(state["w_r"].abs().sum()) > 0
    assert torch.equal(state["residual_coef"], state_mixed["residual_coef"])
    for s in (state, state_mixed):
        assert float(s["z"].norm()) == pytest.approx(math.sqrt(D), abs=1e-4)
        assert not torch.allclose(s["z"], s["start"] * math.sqrt(D))  # z moved from z_r
    assert not torch.equal(state["z"], state_mixed["z"])  # the two learned from different data


def test_rela_without_the_inference_steps_waits_for_a_batch_of_its_own():
    assert LatentSearchConfig(method="rela", rela_batch_size=64).first_update() == 64
    assert LatentSearchConfig(method="rela", rela_batch_size=64, seed_frames=100).first_update() == 100
    assert LatentSearchConfig(method="rela", rela_batch_size=64, rela_inference_replay=True).first_update() == 0
    assert LatentSearchConfig(rela_batch_size=64).first_update() == 0  # LoLA: its update only reports
    assert LatentSearchFinetuner.replays_inference_data(LatentSearchConfig())
    assert not LatentSearchFinetuner.replays_inference_data(LatentSearchConfig(method="rela"))
    with pytest.raises(ConfigError, match="rela-batch-size 1024") as info:
        LatentSearchConfig(method="rela", frames=1000).check()
    assert "\n" not in str(info.value)
    LatentSearchConfig(method="rela", frames=1000, rela_inference_replay=True).check()


def test_the_report_draws_the_episodes_of_interaction_beside_the_fine_tuning_curves(pretrained, tmp_path):
    from dvfb.analysis.report import make_report

    run = _finetune(pretrained, "report_lola", 1000, horizon=200, samples=3)
    out = tmp_path / "report"
    make_report([str(run.path)], str(out))  # this run alone: the module's other runs are fb+lola too
    text = (out / "report.md").read_text()
    assert "## Returns of the episodes of interaction" in text
    task = json.loads((pretrained / "finetune" / "report_lola" / "config.json").read_text())["task"]
    assert (out / "curves" / f"episodes_{task}.png").stat().st_size > 0
    table = (out / "table2_finetune.csv").read_text()
    assert "fb+lola" in table  # a chosen fine-tuner's runs are their own method
