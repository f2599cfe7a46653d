"""Conservative FB (docs/methods.md, "Conservative FB"): the VC-FB and MC-FB penalties against hand
computations with explicit loops, the action groups, and the dual ascent of alpha."""

import math

import pytest
import torch

from dvfb.agents import get_spec, make_agent
from dvfb.agents.conservative_fb import ConservativeConfig, MCFBAgent, VCFBAgent
from dvfb.core.errors import ConfigError
from dvfb.data import Batch
from tiny import ACT, OBS, filled_replay, tiny_config, tiny_run_config

N = 5


def agent_and_batch(penalty, samples=6, seed=0, **conservative):
    cls = {"value": VCFBAgent, "measure": MCFBAgent}[penalty]
    agent = cls(OBS, ACT, tiny_config(batch_size=N), ConservativeConfig(samples=samples, **conservative)).double()
    g = torch.Generator().manual_seed(seed)
    batch = Batch(obs=torch.randn(N, OBS, generator=g, dtype=torch.float64),
                  action=torch.rand(N, ACT, generator=g, dtype=torch.float64) * 2 - 1,
                  reward=torch.zeros(N, 1, dtype=torch.float64), discount=torch.full((N, 1), 0.99, dtype=torch.float64),
                  next_obs=torch.randn(N, OBS, generator=g, dtype=torch.float64), future_obs=None, z=None)
    z = agent.sample_skill(N).double()
    return agent, batch, z


def lse(values):
    top = max(values)
    return top + math.log(sum(math.exp(v - top) for v in values))


@pytest.mark.parametrize("penalty", ["value", "measure"])
def test_penalty_by_hand(penalty):
    agent, b, z = agent_and_batch(penalty, samples=6)
    term = agent.penalty_term
    assert (term.num_uniform, term.num_each) == (3, 1)
    agent.use_generator(torch.Generator().manual_seed(7))
    states, actions, zs = term.penalty_actions(agent, b, z)
    agent.use_generator(torch.Generator().manual_seed(7))
    forward = agent.forward_map(b.obs, b.action, z)
    backward = agent.backward_map(b.next_obs)
    got = float(term.conservative_penalty(agent, b, z, forward, backward).detach())

    # Groups, by construction: 3 uniform at s, pi(s) at s, pi(s') at s', then the dataset action.
    for j in range(3):
        assert torch.equal(states[j * N:(j + 1) * N], b.obs)
        assert actions[j * N:(j + 1) * N].abs().max() <= 1
    assert torch.equal(states[3 * N:4 * N], b.obs) and torch.equal(states[4 * N:5 * N], b.next_obs)
    assert torch.equal(zs, z.repeat(5, 1))
    with torch.no_grad():
        sampled = agent.forward_map(states, actions, zs)  # (2, 5N, d)
        forward, backward = forward.detach(), backward.detach()
    want = 0.0
    for k in range(2):
        if penalty == "value":
            terms, data = [], []
            for i in range(N):
                q_data = float(forward[k, i] @ z[i])
                values = [float(sampled[k, j * N + i] @ z[i]) for j in range(5)] + [q_data]
                terms.append(lse(values))
                data.append(q_data)
        else:
            terms, data = [], []
            for i in range(N):
                for l_ in range(N):
                    m_data = float(forward[k, i] @ backward[l_])
                    values = [float(sampled[k, j * N + i] @ backward[l_]) for j in range(5)] + [m_data]
                    terms.append(lse(values))
                    data.append(m_data)
        want += sum(terms) / len(terms) - sum(data) / len(data)
    assert got == pytest.approx(want, rel=1e-10)


def test_the_value_penalty_trains_f_only_and_the_measure_penalty_also_b():
    for penalty, b_grad in (("value", False), ("measure", True)):
        agent, b, z = agent_and_batch(penalty)
        p = agent.penalty_term.conservative_penalty(agent, b, z, agent.forward_map(b.obs, b.action, z),
                                                    agent.backward_map(b.next_obs))
        f_grads = torch.autograd.grad(p, list(agent.forward_map.parameters()), retain_graph=True, allow_unused=True)
        b_grads = torch.autograd.grad(p, list(agent.backward_map.parameters()), allow_unused=True)
        assert any(g is not None and g.abs().sum() > 0 for g in f_grads)
        assert any(g is not None and g.abs().sum() > 0 for g in b_grads) == b_grad


def test_alpha_rises_above_the_target_and_falls_below_it():
    agent, _, _ = agent_and_batch("value", target=50.0)
    assert float(agent.log_alpha.detach().exp()) == 1.0  # the authors' initial multiplier
    up = agent.penalty_term.alpha_step(agent, torch.tensor(80.0, dtype=torch.float64))
    assert float(up) > 1.0
    agent2, _, _ = agent_and_batch("value", target=50.0)
    down = agent2.penalty_term.alpha_step(agent2, torch.tensor(10.0, dtype=torch.float64))
    assert float(down) < 1.0
    fixed, _, _ = agent_and_batch("value", lagrange=False, alpha=0.25)
    assert float(fixed.penalty_term.alpha_step(fixed, torch.tensor(80.0))) == 0.25 and float(fixed.log_alpha.detach()) == 0.0


def test_sample_groups_must_split_evenly():
    with pytest.raises(ConfigError, match="three equal groups"):
        ConservativeConfig(samples=8).counts()
    assert ConservativeConfig().counts() == (6, 2)  # the authors' 12: 6 uniform, 2 + 2 + 2


@pytest.mark.parametrize("name,penalty", [("vcfb", "value"), ("mcfb", "measure")])
def test_registered_variants_update_with_the_penalty(name, penalty):
    config = tiny_run_config(name)
    assert get_spec(name).method_label(config) == name
    agent = make_agent(name, 4, 2, config)
    assert agent.penalty == penalty and agent.name == name
    metrics = agent.update(agent.replay_needs().sample(filled_replay(agent)))
    assert {"conservative_penalty", "conservative_alpha", "fb_loss"} <= set(metrics)
    assert torch.isfinite(metrics["conservative_penalty"])
    clone = make_agent(name, 4, 2, config)
    clone.load_training_state(agent.training_state())
    assert torch.equal(clone.log_alpha, agent.log_alpha)
    assert clone.alpha_optimizer.state_dict()["state"].keys() == agent.alpha_optimizer.state_dict()["state"].keys()
