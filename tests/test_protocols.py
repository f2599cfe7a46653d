"""Skills declared by the agents and the registered protocols (docs/methods.md, "Skills", "Protocols").

The skill priors have their declared shapes and distributions; skill selection keeps the best
candidate, records every one, and reproduces the authors' off-by-one when asked; the registry of
protocols is what the run configs, the fine-tuning loop and the CLI read.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dvfb import envs
from dvfb.agents import AGENTS, get_spec, make_agent
from dvfb.agents.base import Agent
from dvfb.core.errors import ConfigError
from dvfb.nets.learner import Learner
from dvfb.nets.members import member_training_state, stack_agents
from dvfb.protocols import FINETUNERS, ZERO_SHOT_PROTOCOLS, Finetuner, finetuner_choices, protocols_of, \
    resolve_finetuner
from dvfb.protocols.zeroshot import SkillSelection, SkillSelectionConfig, best_candidate
from dvfb.nets.skills import SkillSpec
from dvfb.runs.run_config import run_config_class
from tiny import tiny_run_config

MAZE = "point_mass_maze_reach_top_left"


def test_one_hot_prior_is_uniform_over_the_skills():
    spec = SkillSpec("one_hot", 16, every=50)
    draws = spec.sample(16_000, generator=torch.Generator().manual_seed(0))
    assert draws.shape == (16_000, 16) and draws.dtype == torch.float32
    assert torch.equal(draws.sum(-1), torch.ones(16_000)) and set(draws.unique().tolist()) == {0.0, 1.0}
    counts = draws.sum(0)
    assert counts.min() > 900 and counts.max() < 1100  # 1000 expected per skill, sd ~31


def test_sphere_prior_has_the_declared_radius_and_no_preferred_direction():
    fb_like = SkillSpec("sphere", 50, every=300).sample(4000, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(fb_like.norm(dim=-1), torch.full((4000,), 50 ** 0.5))
    unit = SkillSpec("sphere", 10, every=5, radius=1.0).sample(4000, generator=torch.Generator().manual_seed(2))
    assert torch.allclose(unit.norm(dim=-1), torch.ones(4000))
    assert unit.mean(0).abs().max() < 0.05  # a uniform direction has mean 0 (sd of the mean ~0.005)


def test_box_prior_is_uniform_in_the_box():
    draws = SkillSpec("box", 64, every=50).sample(5000, generator=torch.Generator().manual_seed(3))
    assert draws.min() >= 0 and draws.max() < 1
    assert abs(float(draws.mean()) - 0.5) < 0.01 and abs(float(draws.var()) - 1 / 12) < 0.005


def test_generators_make_draws_reproducible_and_independent_of_the_global_stream():
    spec = SkillSpec("one_hot", 8, every=50)
    a = spec.sample(5, generator=torch.Generator().manual_seed(7))
    torch.manual_seed(123)
    torch.rand(10)
    b = spec.sample(5, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


def test_resampling_rule():
    spec = SkillSpec("one_hot", 4, every=50)
    assert spec.due(0, False) and spec.due(100, False) and not spec.due(99, False) and spec.due(99, True)
    per_episode = SkillSpec("one_hot", 4, every=None)
    assert per_episode.due(7, True) and not per_episode.due(100, False)
    assert not SkillSpec().due(0, True)
    with pytest.raises(ValueError):
        SkillSpec("one_hot", 0)
    with pytest.raises(ValueError):
        SkillSpec("cube", 3)


def test_every_registered_method_names_registered_protocols_and_its_configs_follow_them():
    for name in AGENTS:
        zero_shot, finetuner = protocols_of(name)
        assert zero_shot.name in ZERO_SHOT_PROTOCOLS and finetuner.name in FINETUNERS
        config = run_config_class(name)()
        assert type(config.inference) is zero_shot.config_cls and type(config.finetune) is finetuner.config_cls


def test_the_fine_tuner_resolves_to_a_registered_name():
    for name in AGENTS:
        own = resolve_finetuner(name)
        assert own in FINETUNERS and own == get_spec(name).finetuner == protocols_of(name)[1].name
        for choice in finetuner_choices(name):
            assert resolve_finetuner(name, choice) == choice and choice in FINETUNERS
    # "" meant the method's own in older configs only (dvfb.runs.migrations); it is not a name.
    with pytest.raises(ConfigError, match="choose one of dual_value, latent_search, online_inference"):
        resolve_finetuner("fb", "")
    with pytest.raises(ConfigError, match="--protocol latent_search is not a protocol of 'rnd'; choose one of urlb"):
        resolve_finetuner("rnd", "latent_search")


# The hooks that delegate to the model or hold the random stream: written once, on Learner.
SHARED_HOOKS = ("generator", "net_runner", "use_generator", "nonfinite_hint")


def test_agents_and_finetuners_are_learners_that_share_the_default_hooks():
    learner_classes = [get_spec(name).agent_cls for name in AGENTS] + list(FINETUNERS.values())
    for cls in learner_classes:
        assert issubclass(cls, Learner) and issubclass(cls, (Agent, Finetuner))
        for hook in SHARED_HOOKS:
            assert getattr(cls, hook) is getattr(Learner, hook), f"{cls.__name__} redefines {hook}"


class _ScaleFinetuner(Finetuner):
    """A fine-tuner with only the hooks it must write: its own network and optimiser."""

    def __init__(self, model, skill, config):
        super().__init__(model, skill, config)
        self.scale = torch.nn.Linear(2, 2)
        self.optimizer = torch.optim.Adam(self.scale.parameters(), lr=0.1)

    def optimizers(self):
        return {"scale": self.optimizer}

    def update(self, batch):
        loss = self.scale(batch).square().mean()
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        return {"loss": loss.detach()}


def test_a_finetuner_gets_the_learner_defaults_for_its_state_stream_and_group():
    models = [_skill_agent().model for _ in range(2)]
    tuners = [_ScaleFinetuner(model, None, None) for model in models]
    tuners[0].update(torch.ones(3, 2))
    state = tuners[0].training_state()
    assert "scale.weight" in state["modules"] and any(k.startswith("model.") for k in state["modules"])
    tuners[1].load_training_state(state)
    assert torch.equal(tuners[1].scale.weight, tuners[0].scale.weight)
    generator = torch.Generator()
    tuners[0].use_generator(generator)
    assert tuners[0].generator is generator and models[0].generator is generator
    tuners[1].use_generator(torch.Generator())
    group = stack_agents(tuners)
    assert group.members == 2 and group.scale.weight.shape == (2, 2, 2)
    # Member 1's state is the one its own fine-tuner held: the state it loaded.
    assert torch.equal(member_training_state(group, 1)["modules"]["scale.weight"], state["modules"]["scale.weight"])


def test_best_candidate_is_the_first_highest_return():
    assert best_candidate([3.0, 9.5, -1.0, 9.5, 2.0]) == 1
    assert best_candidate([-5.0]) == 0
    with pytest.raises(ConfigError, match="whole episode"):
        best_candidate([])


def _skill_agent():
    torch.manual_seed(0)
    return make_agent("cic", 4, 2, tiny_run_config("cic"), "cpu")


@pytest.mark.parametrize("candidates,steps,expected", [("completed", 2000, 2), ("authors", 2000, 1),
                                                       ("completed", 2500, 2)])
def test_skill_selection_keeps_the_best_episode_and_records_every_candidate(candidates, steps, expected):
    agent = _skill_agent()
    protocol = SkillSelection(SkillSelectionConfig(steps=steps, candidates=candidates, eval_episodes=1))
    env = envs.make(MAZE, seed=0)
    skill, info = protocol.task_skill(agent, env, np.random.default_rng(0), 1000)
    returns = [c["return"] for c in info["candidates"]]
    assert len(returns) == expected and info["selection_steps"] == steps
    assert info["chosen"] == int(np.argmax(returns)) and info["chosen_return"] == max(returns)
    assert skill.tolist() == info["candidates"][info["chosen"]]["skill"]
    # Each candidate's return is what its skill scores with mean actions from the same episode
    # start: replay the episodes in a fresh environment of the same seed.
    replay_env = envs.make(MAZE, seed=0)
    for candidate in info["candidates"]:
        obs, _ = replay_env.reset()
        z = torch.tensor(candidate["skill"])
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = replay_env.step(agent.act(obs[None], z[None], explore=False)[0])
            total += float(reward)
            done = terminated or truncated
        assert total == pytest.approx(candidate["return"], abs=1e-9)


def test_skill_selection_needs_a_whole_episode():
    protocol = SkillSelection(SkillSelectionConfig(steps=500, eval_episodes=1))
    with pytest.raises(ConfigError, match="whole episode"):
        protocol.task_skill(_skill_agent(), envs.make(MAZE, seed=0), np.random.default_rng(0), 1000)


def test_urlb_fine_tuning_skill_modes():
    from dvfb.agents.base import ReplayNeeds
    from dvfb.protocols.urlb import DDPGFinetuneConfig, DDPGFinetuner
    def finetuner(agent_name, **options):
        torch.manual_seed(0)
        config = tiny_run_config(agent_name)
        agent = make_agent(agent_name, 4, 2, config, "cpu")
        return agent, DDPGFinetuner(agent.model, agent.sample_skill(1)[0], DDPGFinetuneConfig(**options))

    agent, selected = finetuner("diayn")
    chosen = selected.skill.clone()
    assert all(torch.equal(selected.rollout_skill(t, t == 0, chosen), chosen) for t in range(0, 200, 7))
    agent, resample = finetuner("diayn", skill="resample")
    g = torch.Generator().manual_seed(0)
    drawn = resample.rollout_skill(0, True, None, g)
    assert torch.equal(resample.rollout_skill(1, False, drawn, g), drawn)  # not due: kept
    assert torch.equal(resample.rollout_skill(50, False, drawn, torch.Generator().manual_seed(9)),
                       agent.sample_skill(1, generator=torch.Generator().manual_seed(9))[0])  # due every 50
    _agent, box = finetuner("cic", skill="prior_mean")
    assert torch.equal(box.skill, torch.full((64,), 0.5))
    with pytest.raises(ConfigError, match="box prior"):
        finetuner("diayn", skill="prior_mean")
    with pytest.raises(ConfigError, match="no task regression"):
        finetuner("diayn", skill="regressed")

    agent, regressed = finetuner("aps", skill="regressed", regress_after=100, regress_samples=64)
    from dvfb.data import ReplayBuffer

    rng = np.random.default_rng(0)
    replay = ReplayBuffer(1000, 4, 2, agent.skill_dim)  # dense random rewards: a direction to find
    replay.start_episode(rng.normal(size=4).astype(np.float32))
    for _ in range(300):
        replay.add(rng.uniform(-1, 1, 2).astype(np.float32), float(rng.uniform()), 1.0,
                   rng.normal(size=4).astype(np.float32), agent.sample_skill(1)[0].numpy())
    regressed.bind_replay(replay)
    before = regressed.skill.clone()
    assert torch.equal(regressed.rollout_skill(50, False, before), before)  # before regress_after
    torch.manual_seed(3)
    skill = regressed.rollout_skill(100, False, before)
    torch.manual_seed(3)
    batch = ReplayNeeds(64, 0.99, nstep=3).sample(replay)
    expected = agent.intrinsic.regress_task(batch.obs, batch.reward)
    torch.testing.assert_close(skill, expected / expected.norm())
    zero = ReplayBuffer(1000, 4, 2, agent.skill_dim)  # all-zero rewards: no direction, the skill stays
    zero.start_episode(np.zeros(4, np.float32))
    for _ in range(10):
        zero.add(np.zeros(2, np.float32), 0.0, 1.0, np.ones(4, np.float32), agent.sample_skill(1)[0].numpy())
    regressed.bind_replay(zero)
    assert torch.equal(regressed.rollout_skill(105, False, skill), skill)
    regressed.bind_replay(replay)
    regressed.skill = skill
    assert torch.equal(regressed.skill, skill) and abs(float(skill.norm()) - 1) < 1e-5  # evaluations use it


@pytest.mark.parametrize("agent_name", ["dvfb", "cesd", "smm"])
def test_an_agent_with_a_run_generator_draws_nothing_from_the_global_stream(agent_name):
    """Skills, policy noise, the update's noise and the reward modules' samples all come from the
    run's generator: with the same generator state, changing torch's global stream changes nothing."""
    from tiny import filled_replay

    results = []
    for global_seed in (1, 2):
        torch.manual_seed(0)
        agent = make_agent(agent_name, 4, 2, tiny_run_config(agent_name), "cpu")
        replay = filled_replay(agent)
        generator = torch.Generator().manual_seed(5)
        agent.use_generator(generator)
        torch.manual_seed(global_seed)
        obs = np.zeros((1, 4), np.float32)
        skill = agent.sample_skill(1)
        action = agent.act(obs, skill, explore=True)
        agent.update(agent.replay_needs().sample(replay, generator))
        results.append((skill, action, [p.detach().clone() for p in agent.parameters()]))
    (s1, a1, p1), (s2, a2, p2) = results
    assert torch.equal(s1, s2) and np.array_equal(a1, a2)
    assert all(torch.equal(x, y) for x, y in zip(p1, p2))


def test_a_resume_checkpoint_of_the_old_format_is_refused_in_one_line(tmp_path):
    from dvfb.core.errors import CheckpointError
    from dvfb.runs import RunDir, latest_checkpoint
    from dvfb.workflows.pretrain import pretrain

    config = tiny_run_config("rnd", frames=1000)
    pretrain(config, tmp_path / "run", progress=False)
    run = RunDir(tmp_path / "run")
    path = latest_checkpoint(run)
    state = torch.load(path, weights_only=False)
    state.pop("format"), state.pop("generator")  # as written before runs owned their streams
    torch.save(state, path)
    import dataclasses

    with pytest.raises(CheckpointError, match="format 1.*format 2"):
        pretrain(dataclasses.replace(config, frames=2000), tmp_path / "run", resume=True, progress=False)


@pytest.mark.parametrize("skill_mode", ["selected", "resample"])
@pytest.mark.slow
def test_skill_discovery_fine_tuning_resumes_as_if_uninterrupted(skill_mode, tmp_path):
    """Selection, then URLB fine-tuning with a fixed or resampled skill, interrupted at an episode
    end and resumed: the curve, the skill and every parameter equal the uninterrupted run's."""
    from dvfb.runs import load_checkpoint
    from dvfb.workflows.finetune import finetune
    from dvfb.workflows.pretrain import pretrain

    run = tmp_path / "diayn"
    pretrain(tiny_run_config("diayn"), run, progress=False)
    inference = {"steps": 1000, "eval_episodes": 1}
    options = {"seed_frames": 400, "eval_every": 1000, "eval_episodes": 1, "checkpoint_every": 1000,
               "update_every": 4, "skill": skill_mode}
    finetune(run, MAZE, name="full", inference=inference, finetune={**options, "frames": 2000}, progress=False)
    finetune(run, MAZE, name="split", inference=inference, finetune={**options, "frames": 1000}, progress=False)
    finetune(run, MAZE, name="split", inference=inference, finetune={**options, "frames": 2000}, resume=True,
             progress=False)
    import json

    full = json.loads((run / "finetune" / "full" / "curve.json").read_text())
    split = json.loads((run / "finetune" / "split" / "curve.json").read_text())
    assert [p["frames"] for p in split["curve"]] == [0, 1000, 2000] and full["curve"] == split["curve"]
    assert full["inference_info"]["protocol"] == "skill_selection" and len(full["inference_info"]["candidates"]) == 1
    a = load_checkpoint(run / "finetune" / "full")
    b = load_checkpoint(run / "finetune" / "split")
    assert torch.equal(a["generator"], b["generator"]) and torch.equal(a["finetuner"]["skill"], b["finetuner"]["skill"])
    for key, value in a["finetuner"]["core"].items():
        assert torch.equal(value, b["finetuner"]["core"][key]), key
    replay_a, replay_b = a["replay"], b["replay"]
    width = agent_skill_width("diayn")
    skills_a, skills_b = replay_a["rows"][:, -width:], replay_b["rows"][:, -width:]
    assert torch.equal(skills_a, skills_b)
    distinct = {tuple(row.tolist()) for row in skills_a.reshape(-1, skills_a.shape[-1]) if row.sum() == 1}
    assert (len(distinct) == 1) == (skill_mode == "selected")  # resampled every 50 steps: several skills


def agent_skill_width(agent_name: str) -> int:
    return make_agent(agent_name, 4, 2, tiny_run_config(agent_name), "cpu").skill_dim
