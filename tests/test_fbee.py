"""FBEE (docs/methods.md, "FBEE"): the ensemble's loss, the uncertainty scores by hand, the choice
of z on a planted ensemble, independent members, exact targets, and the z schedule of a real run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from dvfb.agents import make_agent
from dvfb.agents.fbee import choose_most_uncertain, ensemble_uncertainty
from tiny import ACT, OBS, random_batch, tiny_run_config


def _agents(ensemble: int = 3):
    config = tiny_run_config("fbee")
    from dvfb.core.config import merge

    config = merge(config, {"fbee": {"ensemble": ensemble}})
    torch.manual_seed(0)
    return config, make_agent("fbee", OBS, ACT, config)


def test_hand_scores_of_both_uncertainties():
    # FBEE^Q: members with F.z = 1, 2, 6 (z = e_1): the unbiased std is sqrt(7).
    z = torch.tensor([[1.0, 0.0]])
    forward = torch.tensor([[[1.0, 5.0]], [[2.0, -1.0]], [[6.0, 0.0]]])  # (E=3, C=1, d=2)
    assert ensemble_uncertainty(forward, z, "q").item() == pytest.approx(math.sqrt(7), rel=1e-6)
    # FBEE^F: vectors (1, 0), (0, 1), (-1, -1) have mean 0: trace of the covariance (1 + 1 + 2) / 2 = 2.
    vectors = torch.tensor([[[1.0, 0.0]], [[0.0, 1.0]], [[-1.0, -1.0]]])
    assert ensemble_uncertainty(vectors, z, "f").item() == pytest.approx(2.0, rel=1e-6)
    # Vectorised over candidates and a group's leading axis, each entry is its own hand value.
    batch = torch.randn(2, 4, 7, 3)  # (M, E, C, d)
    zs = torch.randn(2, 7, 3)
    scores = ensemble_uncertainty(batch, zs, "q")
    assert scores.shape == (2, 7)
    values = (batch[1, :, 5] * zs[1, 5]).sum(-1)
    assert scores[1, 5].item() == pytest.approx(float(values.std()), rel=1e-5)


def test_planted_disagreement_picks_the_largest_projection_for_both_scores():
    # F^e(z) = A z + eps_e (v.z) v: std(F.z) and the trace both grow with (v.z)^2.
    torch.manual_seed(1)
    d, c = 6, 40
    a = torch.randn(d, d)
    v = torch.nn.functional.normalize(torch.randn(d), dim=0)
    eps = torch.tensor([0.1, -0.3, 0.7, 0.2, -0.5])
    z = torch.randn(c, d)
    forward = (z @ a.T).unsqueeze(0) + eps.view(-1, 1, 1) * (z @ v).view(1, -1, 1) * v
    expected = int((z @ v).abs().argmax())
    for kind in ("q", "f"):
        assert choose_most_uncertain(ensemble_uncertainty(forward, z, kind)) == expected


def test_identical_members_score_zero_and_choose_uniformly():
    _, agent = _agents()
    with torch.no_grad():
        weights = [p for p in agent.forward_map.parameters()]
        for p in weights:
            p.copy_(p[0:1].expand_as(p))
    obs = torch.zeros(8, OBS)
    z = agent.sample_skill(8)
    assert torch.count_nonzero(agent.model.uncertainty(obs, z)) == 0
    g = torch.Generator().manual_seed(0)
    counts = np.bincount([choose_most_uncertain(torch.zeros(8), g) for _ in range(4000)], minlength=8)
    assert stats.chisquare(counts).pvalue > 1e-3


def test_chosen_z_is_on_the_sphere_and_is_the_most_uncertain_candidate():
    _, agent = _agents()
    g = torch.Generator().manual_seed(5)
    obs = np.linspace(-0.1, 0.1, OBS).astype(np.float32)
    z = agent.explore_skill(obs, g)
    assert z.norm().item() == pytest.approx(math.sqrt(z.numel()), rel=1e-5)
    # The same stream again: the candidates it drew, scored at this state; z is their argmax.
    g = torch.Generator().manual_seed(5)
    candidates = agent.sample_skill(agent.ensemble_config.candidates, generator=g)
    scores = agent.model.uncertainty(torch.as_tensor(obs).expand(len(candidates), OBS), candidates)
    assert torch.equal(z, candidates[scores.argmax()])


def test_ensemble_loss_is_the_mean_of_member_losses_and_fb_loss_with_identical_members():
    config, agent = _agents()
    from dvfb.agents import FBAgent

    fb = FBAgent.from_config(OBS, ACT, config)
    with torch.no_grad():  # every member = FB's F (and its target); B and the actor shared
        for mine, theirs in zip(agent.forward_map.net.parameters(), fb.forward_map.parameters()):
            mine.copy_(theirs.unsqueeze(0).expand_as(mine))
        for mine, theirs in zip(agent.forward_target.net.parameters(), fb.forward_target.parameters()):
            mine.copy_(theirs.unsqueeze(0).expand_as(mine))
        for name in ("backward_map", "backward_target", "actor"):
            getattr(agent, name).load_state_dict(getattr(fb, name).state_dict())
    batch = random_batch(32, seed=3)
    z = fb.sample_skill(32)
    next_action = torch.rand(32, ACT) * 2 - 1
    ours = agent.fb_losses(batch, z, next_action, agent.backward_map(batch.next_obs), batch.next_obs)
    theirs = fb.fb_losses(batch, z, next_action, fb.backward_map(batch.next_obs), batch.next_obs)
    for key in ("fb_loss", "fb_offdiag", "fb_diag", "ortho_loss", "fb_total"):
        assert ours[key].item() == pytest.approx(theirs[key].item(), rel=1e-6, abs=1e-6), key


def test_members_train_independently_and_b_learns_from_all():
    _, agent = _agents()
    batch = random_batch(32, seed=3)
    z = agent.sample_skill(32)
    next_action = torch.rand(32, ACT) * 2 - 1

    def grads():
        agent.zero_grad(set_to_none=True)
        losses = agent.fb_losses(batch, z, next_action, agent.backward_map(batch.next_obs), batch.next_obs)
        losses["fb_loss"].backward()
        weight = agent.forward_map.net.heads.second_weight
        return weight.grad.clone(), [p.grad.clone() for p in agent.backward_map.parameters()]

    before, b_before = grads()
    with torch.no_grad():  # perturb member 2 only
        for p in agent.forward_map.net.parameters():
            p[2].add_(0.05 * torch.randn_like(p[2]))
    after, b_after = grads()
    assert torch.equal(before[0], after[0]) and torch.equal(before[1], after[1])
    assert not torch.equal(before[2], after[2])
    # B's gradient is the members' together: it changes when one member changes.
    assert any(not torch.equal(x, y) for x, y in zip(b_before, b_after))


def test_targets_are_exact_copies_and_follow_each_member():
    _, agent = _agents()
    for online, target in zip(agent.forward_map.parameters(), agent.forward_target.parameters()):
        assert torch.equal(online, target)
    with torch.no_grad():
        for p in agent.forward_map.parameters():
            p[1].add_(1.0)
    targets = [t.clone() for t in agent.forward_target.parameters()]
    agent.soft_update_targets()
    tau = agent.config.tau
    for online, old, new in zip(agent.forward_map.parameters(), targets, agent.forward_target.parameters()):
        assert torch.allclose(new, old + tau * (online - old), atol=1e-6)


@pytest.mark.slow
def test_a_run_changes_z_only_at_episode_starts_and_every_period(tmp_path):
    from dvfb.data import ReplayBuffer
    from dvfb.runs.checkpoints import latest_checkpoint
    from dvfb.workflows.pretrain import pretrain

    config = tiny_run_config("fbee", frames=1200, seed_frames=400)
    from dvfb.core.config import merge

    config = merge(config, {"fb": {"skill_every": 100}})
    run = pretrain(config, tmp_path / "run", progress=False)
    state = torch.load(latest_checkpoint(run.path), weights_only=False)
    replay = ReplayBuffer.from_state(state["replay"])
    data = replay.transitions()
    skills = data.z.numpy()
    steps = np.arange(len(skills))
    change = np.nonzero(np.any(skills[1:] != skills[:-1], axis=1))[0] + 1
    # Episodes of 1000 steps: a new z at step 0 and the multiples of 100 (episode starts are among them).
    assert set(change.tolist()) <= set(steps[steps % 100 == 0].tolist())
    assert len(change) >= 8  # the candidates differ, so the choice moves
    assert np.allclose(np.linalg.norm(skills, axis=1), math.sqrt(skills.shape[1]), rtol=1e-5)
