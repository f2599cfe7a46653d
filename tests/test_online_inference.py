"""Tests for dvfb.protocols.online_inference (OpTI-BFM, docs/methods.md "Online task inference";
spec methods_2025.md §3.6): the Bayesian linear regression against hand and batch computations,
the optimism of the UCB against its closed form, planted rewards and a planted bandit, FB's identity
``phi = Cov^-1 B``, the label gate, the protocol's bookkeeping on a replay, and the protocol end to end
on the fine-tuning workflow with an exact resume."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny import D, tiny_config, tiny_flags

from dvfb.agents.fb import FBAgent
from dvfb.data import ReplayBuffer
from dvfb.core.errors import ConfigError
from dvfb.nets import project_to_sphere
from dvfb.protocols import finetuner_choices
from dvfb.protocols.online_inference import (
    BayesianLinearRegression,
    OnlineInference,
    OnlineInferenceConfig,
    ball_samples,
    thompson_choice,
    ucb_choice,
)

F64 = torch.float64


def generator(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------------------------------------
# The regression (§3.6 items 1, 2, 4, 7)


def test_hand_regression_and_its_ucb():
    blr = BayesianLinearRegression(2, ridge=1.0)
    blr.observe(torch.tensor([1.0, 0.0]), 2.0)
    torch.testing.assert_close(blr.precision, torch.diag(torch.tensor([2.0, 1.0], dtype=F64)))
    torch.testing.assert_close(blr.mean, torch.tensor([1.0, 0.0], dtype=F64))
    assert float(blr.ucb(torch.tensor([0.0, 1.0]), beta=1.0)) == pytest.approx(1.0, abs=1e-12)
    assert float(blr.ucb(torch.tensor([1.0, 0.0]), beta=1.0)) == pytest.approx(1 + math.sqrt(0.5), abs=1e-12)


@pytest.mark.parametrize("noise", [1.0, 0.01])
def test_rank_one_updates_equal_batch_ridge_least_squares(noise):
    g = generator(1)
    d, n, ridge = 6, 500, 0.7
    x = torch.randn(n, d, generator=g, dtype=F64)
    r = torch.randn(n, generator=g, dtype=F64)
    blr = BayesianLinearRegression(d, ridge=ridge, noise=noise)
    for row, reward in zip(x, r):
        blr.observe(row, reward)
    precision = ridge * torch.eye(d, dtype=F64) + x.T @ x / noise**2
    torch.testing.assert_close(blr.precision, precision, rtol=0, atol=1e-5 * precision.abs().max())
    # The posterior mean is the ridge estimate with lambda sigma^2 in the data's units.
    ridge_ls = torch.linalg.solve(x.T @ x + ridge * noise**2 * torch.eye(d, dtype=F64), x.T @ r)
    torch.testing.assert_close(blr.mean, ridge_ls, rtol=0, atol=1e-5)
    assert int(blr.count) == n and int(blr.skipped) == 0


def test_decay_equals_explicit_weights_with_the_prior_decayed_too():
    g = generator(2)
    d, n, ridge, rho = 4, 300, 2.0, 0.99
    x = torch.randn(n, d, generator=g, dtype=F64)
    r = torch.randn(n, generator=g, dtype=F64)
    blr = BayesianLinearRegression(d, ridge=ridge, decay=rho)
    for row, reward in zip(x, r):
        blr.observe(row, reward)
    weights = rho ** torch.arange(n - 1, -1, -1, dtype=F64)  # the datum of step s weighs rho^(t - s)
    precision = rho**n * ridge * torch.eye(d, dtype=F64) + (x * weights[:, None]).T @ x
    moment = (x * (weights * r)[:, None]).sum(0)
    torch.testing.assert_close(blr.precision, precision, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(blr.moment, moment, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(blr.mean, torch.linalg.solve(precision, moment), rtol=0, atol=1e-5)


def test_planted_linear_reward_is_recovered():
    g = generator(3)
    d = 10
    w_star = torch.randn(d, generator=g, dtype=F64)
    blr = BayesianLinearRegression(d)
    for _ in range(2000):
        phi = torch.randn(d, generator=g, dtype=F64)
        phi = phi / phi.norm()
        blr.observe(phi, phi @ w_star + 0.01 * torch.randn((), generator=g, dtype=F64))
    assert float(torch.nn.functional.cosine_similarity(blr.mean, w_star, dim=0)) > 0.999


def test_thompson_samples_have_the_posterior_covariance():
    g = generator(4)
    d = 3
    blr = BayesianLinearRegression(d, noise=0.01)
    for _ in range(5):
        blr.observe(torch.randn(d, generator=g, dtype=F64) * 0.01, float(torch.randn((), generator=g)))
    samples = blr.posterior_samples(40_000, generator(5))
    covariance = torch.linalg.inv(blr.precision)
    torch.testing.assert_close(samples.mean(0), blr.mean, rtol=0, atol=0.03 * covariance.diag().sqrt().max())
    assert float((torch.cov(samples.T) - covariance).norm() / covariance.norm()) < 0.05
    # The choice is the projection of a draw, on the model's sphere.
    assert float(thompson_choice(blr, generator(6)).norm()) == pytest.approx(math.sqrt(d))


def test_gate_always_never_and_by_leverage():
    g = generator(7)
    x = torch.randn(20, 3, generator=g, dtype=F64)
    for gate, added in ((0.0, 20), (50.0, 0)):
        blr = BayesianLinearRegression(3, gate=gate)
        for row in x:
            inverse = torch.linalg.inv(blr.precision)
            h, _ = blr.observe(row, 1.0)
            assert float(h) == pytest.approx(float(row @ inverse @ row), rel=1e-10)  # before its own update
        assert int(blr.count) == added and int(blr.skipped) == 20 - added
    torch.testing.assert_close(blr.precision, torch.eye(3, dtype=F64))  # kappa = 50 never adds
    # e^kappa - 1 = 0.4: one datum repeated has leverage 1, 1/2, 1/3: added twice, then gated out.
    blr = BayesianLinearRegression(2, gate=math.log(1.4))
    added = [bool(blr.observe(torch.tensor([1.0, 0.0]), 1.0)[1]) for _ in range(3)]
    assert added == [True, True, False]
    torch.testing.assert_close(blr.precision, torch.diag(torch.tensor([3.0, 1.0], dtype=F64)))


def test_state_round_trip():
    g = generator(8)
    blr = BayesianLinearRegression(3, decay=0.9)
    for _ in range(10):
        blr.observe(torch.randn(3, generator=g), 1.0)
    copy = BayesianLinearRegression(3, decay=0.9)
    copy.load_state_dict(blr.state_dict())
    x = torch.randn(3, generator=g)
    blr.observe(x, 0.5)
    copy.observe(x, 0.5)
    assert torch.equal(copy.precision, blr.precision) and torch.equal(copy.mean, blr.mean)
    with pytest.raises(ValueError, match="shape"):
        BayesianLinearRegression(4).load_state_dict(blr.state_dict())


# ---------------------------------------------------------------------------------------------
# Optimism (§3.6 item 3) and the candidates


def trained_regression(d: int, n: int, seed: int) -> BayesianLinearRegression:
    g = generator(seed)
    blr = BayesianLinearRegression(d)
    for _ in range(n):
        blr.observe(torch.randn(d, generator=g, dtype=F64), float(torch.randn((), generator=g)))
    return blr


def test_optimism_closed_form_on_the_ellipsoid_boundary():
    d, beta = 3, 0.5
    blr = trained_regression(d, 20, seed=9)
    psi = torch.tensor([0.3, -1.2, 0.8], dtype=F64)
    u = torch.randn(100_000, d, generator=generator(10), dtype=F64)
    boundary = blr.mean + beta * torch.linalg.solve_triangular(blr.factor.T, (u / u.norm(dim=1, keepdim=True)).T,
                                                                upper=True).T
    offset = boundary - blr.mean
    distance = ((offset @ blr.precision) * offset).sum(1).sqrt()
    torch.testing.assert_close(distance, torch.full_like(distance, beta))  # on the boundary ||w - w_hat||_V = beta
    best = float((boundary @ psi).max())
    closed = float(blr.ucb(psi, beta))
    width = beta * float(blr.norms(psi))
    assert best <= closed + 1e-12 and closed - best < 1e-3 * width  # approached from below
    argmax = blr.mean + beta * torch.linalg.solve(blr.precision, psi) / blr.norms(psi)
    assert float(psi @ argmax) == pytest.approx(closed, rel=1e-12)
    assert float(((argmax - blr.mean) @ blr.precision @ (argmax - blr.mean)).sqrt()) == pytest.approx(beta)


def test_candidates_are_uniform_in_the_ellipsoid():
    d, radius = 4, 0.2
    blr = trained_regression(d, 30, seed=11)
    w = blr.ellipsoid_samples(20_000, radius, generator(12))
    distance = ((w - blr.mean) @ blr.precision * (w - blr.mean)).sum(1).sqrt()
    assert float(distance.max()) <= radius * (1 + 1e-9)
    # Uniform in volume: a fraction (1/2)^d lies within half the radius.
    assert float((distance <= radius / 2).double().mean()) == pytest.approx(0.5**d, abs=0.01)
    ball = ball_samples(20_000, d, 1.0, generator(13))
    assert float(ball.norm(dim=1).max()) <= 1.0 and float((ball.norm(dim=1) <= 0.5).double().mean()) == \
        pytest.approx(0.5**d, abs=0.01)


def test_ucb_takes_the_best_candidate_pessimistic_over_heads():
    blr = trained_regression(3, 10, seed=14)
    beta = 0.3

    def psi(z):  # two heads that disagree: the second is half the first
        return torch.stack([z, 0.5 * z])

    z, score = ucb_choice(blr, psi, beta, 64, generator(15))
    # Replay the draws: the chosen z has the largest min over heads.
    draws = project_to_sphere(blr.ellipsoid_samples(64, 2 * beta, generator(15)))
    scores = blr.ucb(psi(draws), beta).amin(0)
    assert torch.equal(z, draws[scores.argmax()]) and float(score) == float(scores.max())


def test_planted_bandit_converges_with_sublinear_regret():
    """A fake BFM with psi(s, z) = proj(z)/sqrt(d): each choice visits a state whose features are
    its psi, with reward psi . w* + N(0, 0.01^2). UCB's z turns to w*, its regret flattens."""
    d, steps, beta = 8, 1500, 0.1
    g = generator(16)
    w_star = torch.randn(d, generator=g, dtype=F64)
    blr = BayesianLinearRegression(d)
    regret = []
    for _ in range(steps):
        z, _ = ucb_choice(blr, lambda zs: (zs / math.sqrt(d)).expand(2, -1, -1), beta, 128, g)
        x = z / math.sqrt(d)
        regret.append(float(w_star.norm() - x @ w_star))
        blr.observe(x, x @ w_star + 0.01 * torch.randn((), generator=g, dtype=F64))
    cosine = float(torch.nn.functional.cosine_similarity(z, w_star, dim=0))
    assert cosine > 0.99
    cumulative = np.cumsum(regret)
    t = np.arange(100, steps + 1)
    slope = np.polyfit(np.log(t), np.log(cumulative[t - 1]), 1)[0]
    assert slope < 1.0, slope
    assert np.mean(regret[-100:]) < 0.05 * np.mean(regret[:100])


# ---------------------------------------------------------------------------------------------
# The protocol on a model


def tiny_model(cov: torch.Tensor | None = None):
    torch.manual_seed(0)
    model = FBAgent(5, 3, tiny_config()).model
    model.use_generator(generator(0))
    model.statistics = {} if cov is None else {"cov_backward": cov}
    return model


def covariance_of(model, n: int = 500, seed: int = 17) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = generator(seed)
    obs, next_obs = torch.randn(n, 5, generator=g), torch.randn(n, 5, generator=g)
    b = model.backward_features(obs, next_obs).double()
    return b.T @ b / n, obs, next_obs


def test_fb_identity_phi_is_cov_inverse_b():
    """With phi = Cov^-1 B over a batch and lambda -> 0, the regression's w_hat is FB's z_r = B^T r / N."""
    model = tiny_model()
    cov, obs, next_obs = covariance_of(model)
    model.statistics = {"cov_backward": cov}
    protocol = OnlineInference(model, None, OnlineInferenceConfig(ridge=1e-9))
    phi = protocol.features(obs, next_obs)
    b = model.backward_features(obs, next_obs).double()
    torch.testing.assert_close(phi, torch.linalg.solve(cov, b.T).T)
    reward = torch.randn(len(obs), generator=generator(18), dtype=F64)
    for x, r in zip(phi, reward):
        protocol.regression.observe(x, r)
    torch.testing.assert_close(protocol.regression.mean, b.T @ reward / len(obs), rtol=0, atol=1e-5)


def test_check_refuses_snapshots_without_cov_and_groups():
    with pytest.raises(ConfigError, match="Cov\\(B\\).*older dvfb"):
        OnlineInference.check(tiny_model(), OnlineInferenceConfig())
    with pytest.raises(ConfigError, match="positive-definite"):
        OnlineInference.check(tiny_model(torch.zeros(D, D, dtype=F64)), OnlineInferenceConfig())
    with pytest.raises(ConfigError, match="positive-definite"):
        OnlineInference.check(tiny_model(torch.eye(D + 1, dtype=F64)), OnlineInferenceConfig())
    OnlineInference.check(tiny_model(torch.eye(D, dtype=F64)), OnlineInferenceConfig())
    with pytest.raises(ConfigError, match="one run at a time"):
        OnlineInference.check_group(OnlineInferenceConfig())
    assert "online_inference" in finetuner_choices("fb") and "online_inference" in finetuner_choices("dvfb")


def test_successor_features_regress_on_phi_itself_and_other_methods_are_refused():
    from tiny import TINY_SECTIONS

    from dvfb.agents.sf import SFAgent, SFConfig

    torch.manual_seed(0)
    model = SFAgent(5, 3, SFConfig(**TINY_SECTIONS["sf"])).model
    model.statistics = {}
    OnlineInference.check(model, OnlineInferenceConfig())  # no Cov needed: SF's reward of z is phi . z
    protocol = OnlineInference(model, None, OnlineInferenceConfig())
    obs, next_obs = torch.randn(4, 5), torch.randn(4, 5)
    torch.testing.assert_close(protocol.features(obs, next_obs), model.backward_features(obs, next_obs).double())
    other = tiny_model(torch.eye(D, dtype=F64))
    other.name = "rnd"  # a method whose skills are not linear in reward features
    with pytest.raises(ConfigError, match="FB family or the successor features"):
        OnlineInference.check(other, OnlineInferenceConfig())


@pytest.mark.parametrize("staged", [False, True])  # True: an accelerator's path (steps staged on the host)
def test_the_replays_newest_transition_across_episodes_and_evictions(staged):
    replay = ReplayBuffer(4, 2, 1, 0, max_episode_length=4, stage_on_host=staged)
    assert replay.newest() is None
    replay.start_episode(np.zeros(2))
    assert replay.newest() is None
    keys = []
    for episode in range(3):
        if episode:
            replay.start_episode(np.full(2, 10.0 * episode))
            # After the reset the newest is still the previous episode's last step.
            assert replay.newest()[0] == keys[-1]
        for step in range(4):
            replay.add(np.zeros(1), 100 * episode + step, 1.0, np.full(2, 100.0 * episode + step + 1))
            key, obs, reward, next_obs = replay.newest()
            assert float(reward) == 100 * episode + step and float(next_obs[0]) == 100 * episode + step + 1
            assert float(obs[0]) == (10.0 * episode if step == 0 else 100 * episode + step)
            keys.append(key)
    assert keys == [(e, s) for e in range(3) for s in range(4)]  # each named once, evictions included


def drive(protocol: OnlineInference, replay: ReplayBuffer, steps: range, rng: np.random.Generator,
          obs: np.ndarray | None = None, episode_length: int = 5) -> tuple[list[torch.Tensor], np.ndarray]:
    """Steps of a fake task by hand, in the loop's order: the skill of the step at its observation,
    then the transition into the replay (reward = the first coordinate of the next state). Returns
    the skills and the observation the next step starts from."""
    chosen = []
    for t in steps:
        start = t % episode_length == 0
        if start:
            obs = rng.standard_normal(5).astype(np.float32)
            replay.start_episode(obs)
        z = protocol.rollout_skill(t, start, chosen[-1] if chosen else None, obs=obs)
        chosen.append(z)
        next_obs = rng.standard_normal(5).astype(np.float32)
        replay.add(rng.uniform(-1, 1, 3), float(next_obs[0]), 1.0, next_obs)
        obs = next_obs
    return chosen, obs


@pytest.mark.parametrize("rule", ["ucb", "ts", "random"])
def test_protocol_takes_every_transition_once_and_chooses_by_period(rule):
    model = tiny_model(torch.eye(D, dtype=F64))
    config = OnlineInferenceConfig(rule=rule, period=3, candidates=16)
    protocol = OnlineInference(model, None, config)
    replay = ReplayBuffer(10, 5, 3, 0, max_episode_length=5)
    protocol.bind_replay(replay)
    prior = protocol.skill
    assert float(prior.norm()) == pytest.approx(math.sqrt(D), rel=1e-6)  # a prior draw before any datum
    chosen, _ = drive(protocol, replay, range(12), np.random.default_rng(0))
    # A new z at steps 0, 3 and every episode start (5, 10), held in between (the same tensor).
    new = [t for t in range(1, 12) if chosen[t] is not chosen[t - 1]]
    assert new == [3, 5, 8, 10]
    assert all(float(z.norm()) == pytest.approx(math.sqrt(D), rel=1e-5) for z in chosen)
    # Transitions 0..10 are in, the 12th (step 11) comes with the next read; reading twice adds nothing.
    assert int(protocol.regression.count) == 11
    final = protocol.skill
    assert int(protocol.regression.count) == 12 and torch.equal(protocol.skill, final)
    torch.testing.assert_close(final, project_to_sphere(protocol.regression.mean).float())
    metrics = protocol.update(None)
    assert set(metrics) == {"w_norm", "data", "gated_out", "leverage", "reward"} | ({"ucb"} if rule == "ucb" else set())
    assert float(metrics["data"]) == 12 and float(metrics["reward"]) == float(replay.newest()[2])


@pytest.mark.parametrize("scale", [1e-30, 1e6])
def test_evaluation_skill_is_the_direction_of_w_hat_at_any_reward_scale(scale):
    g = generator(19)
    x, r = torch.randn(30, D, generator=g, dtype=F64), torch.randn(30, generator=g, dtype=F64)
    skills = []
    for factor in (1.0, scale):
        protocol = OnlineInference(tiny_model(torch.eye(D, dtype=F64)), None, OnlineInferenceConfig())
        for row, reward in zip(x, r):
            protocol.regression.observe(row, factor * reward)
        skills.append(protocol.skill)
    torch.testing.assert_close(skills[1], skills[0], rtol=1e-5, atol=1e-6)
    assert float(skills[0].norm()) == pytest.approx(math.sqrt(D), rel=1e-6)
    # Rewards all 0: no direction, the prior draw stays.
    protocol = OnlineInference(tiny_model(torch.eye(D, dtype=F64)), None, OnlineInferenceConfig())
    prior = protocol.skill
    protocol.regression.observe(x[0], 0.0)
    assert torch.equal(protocol.skill, prior)


def test_protocol_state_resumes_exactly_and_acts_with_means():
    model = tiny_model(torch.eye(D, dtype=F64))
    config = OnlineInferenceConfig(candidates=16, decay=0.99)
    protocol = OnlineInference(model, None, config)
    replay = ReplayBuffer(10, 5, 3, 0, max_episode_length=5)
    protocol.bind_replay(replay)
    rng = np.random.default_rng(1)
    _, obs = drive(protocol, replay, range(7), rng)
    state = protocol.training_state()
    replay_state, rng_state, gen_state = replay.state_dict(), rng.bit_generator.state, model.generator.get_state()
    first, _ = drive(protocol, replay, range(7, 15), rng, obs)

    twin_model = tiny_model(torch.eye(D, dtype=F64))
    twin = OnlineInference(twin_model, None, config)
    twin.load_training_state(state)
    twin_replay = ReplayBuffer(10, 5, 3, 0, max_episode_length=5)
    twin_replay.load_state_dict(replay_state)
    twin.bind_replay(twin_replay)
    rng.bit_generator.state = rng_state
    twin_model.generator.set_state(gen_state)
    second, _ = drive(twin, twin_replay, range(7, 15), rng, obs)
    assert all(torch.equal(a, b) for a, b in zip(first, second))
    assert torch.equal(twin.skill, protocol.skill)
    assert torch.equal(twin.regression.precision, protocol.regression.precision)

    obs = np.random.default_rng(2).standard_normal((2, 5)).astype(np.float32)
    skills = torch.stack(first[:2])
    np.testing.assert_array_equal(protocol.act(obs, skills, explore=True), model.act(obs, skills, False))


# ---------------------------------------------------------------------------------------------
# End to end on the fine-tuning workflow


TASK = "point_mass_maze_reach_top_left"


@pytest.fixture(scope="module")
def pretrained(tmp_path_factory) -> Path:
    from dvfb.cli import main

    run = tmp_path_factory.mktemp("online") / "fb_maze"
    assert main(["pretrain", "--agent", "fb", "--domain", "point_mass_maze", "--frames", "520", "--seed-frames",
                 "500", "--update-every", "4", "--checkpoint-every", "1000", "--log-every", "250", "--run-dir",
                 str(run), "--no-progress", *tiny_flags("fb")]) == 0
    return run


@pytest.mark.slow
@pytest.mark.e2e
def test_workflow_records_episodes_evaluates_and_resumes_exactly(pretrained: Path):
    """``finetune(..., protocol="online_inference")``: evaluations at 0 (the prior draw), at 1000 and at
    the end; every training episode's return in the curve; a run stopped at 1000 steps and resumed
    gives the uninterrupted run's curve, episodes and logged regression."""
    from dvfb.runs import load_checkpoint
    from dvfb.workflows.finetune import finetune

    options = {"eval_every": 1000, "eval_episodes": 1, "candidates": 8}
    full = finetune(pretrained, TASK, protocol="online_inference", name="full", progress=False,
                    finetune=dict(frames=1200, **options))
    stopped = finetune(pretrained, TASK, protocol="online_inference", name="split", progress=False,
                       finetune=dict(frames=1000, **options))
    # The episode that ends with the run is in its curve too (it ends after the last evaluation).
    assert [e["frames"] for e in json.loads((stopped.path / "curve.json").read_text())["episodes"]] == [1000]
    split = finetune(pretrained, TASK, protocol="online_inference", name="split", progress=False, resume=True,
                     finetune=dict(frames=1200, **options))
    a, b = (json.loads((run.path / "curve.json").read_text()) for run in (full, split))
    assert [p["frames"] for p in a["curve"]] == [0, 1000, 1200] and a["protocol"] == "online_inference"
    assert a["curve"] == b["curve"] and a["episodes"] == b["episodes"]
    assert [e["frames"] for e in a["episodes"]] == [1000]  # every finished training episode's return
    logged = [[json.loads(line) for line in (run.path / "metrics" / "train.jsonl").read_text().splitlines()]
              for run in (full, split)]
    assert [r["step"] for r in logged[0]] == [1000, 1200] and logged[0] == logged[1]
    assert {"w_norm", "data", "gated_out", "leverage", "reward", "ucb"} <= set(logged[0][-1])
    # The checkpoint at the episode's end: every transition is in the regression, the 1000th too
    # (taken before the evaluation at 1000), in both runs alike.
    states = [load_checkpoint(run.path)["finetuner"] for run in (full, split)]
    assert int(states[0]["regression"]["count"]) == 1000
    for key in ("precision", "moment"):
        assert torch.equal(states[0]["regression"][key], states[1]["regression"][key])


@pytest.mark.slow
@pytest.mark.e2e
def test_zeroshot_with_the_protocol_runs_it_in_the_task_and_prints_each_episode(pretrained: Path, capsys):
    from dvfb.cli import main

    argv = ["zeroshot", str(pretrained), "--task", TASK, "--protocol", "online_inference", "--online-inference.frames",
            "1000", "--online-inference.eval-every", "1000", "--online-inference.eval-episodes", "1",
            "--online-inference.candidates", "8", "--no-progress"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    run = pretrained / "finetune" / f"{TASK}.online_inference"
    curve = json.loads((run / "curve.json").read_text())
    assert f"episode returns: {curve['episodes'][0]['return']:.1f}" in out
    assert len(curve["z"]) == 8 and [p["frames"] for p in curve["curve"]] == [0, 1000]
    assert not (pretrained / "zeroshot").exists()  # not a labelled zero-shot result
