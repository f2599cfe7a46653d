"""The Python API: dvfb.load(run) -> infer a skill (samples, reward function, goal) and act."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import dvfb
from dvfb import envs
from dvfb.cli import main
from dvfb.core.errors import ConfigError
from dvfb.workflows.pretrain import pretrain
from tiny import tiny_run_config


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("api")
    for agent in ("dvfb", "rnd", "sf"):
        pretrain(tiny_run_config(agent), root / agent, progress=False)
    return root


@pytest.mark.slow
def test_load_infer_and_act(runs):
    model = dvfb.load(runs / "dvfb")
    assert model.name == "dvfb" and model.snapshot == 1000
    env = envs.make("point_mass_maze_reach_top_left", seed=0)
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    samples = rng.normal(size=(64, obs.shape[0])).astype(np.float32)
    rewards = samples[:, 0]
    z = model.infer_z(samples, samples, rewards, reward_quantile=None)
    expected, _ = model.model.infer_skill(torch.as_tensor(samples), torch.as_tensor(samples), torch.as_tensor(rewards),
                                          SimpleNamespace(reward_quantile=None))
    torch.testing.assert_close(z, expected)
    assert z.shape == (model.model.skill_dim,) and not hasattr(model.model, "optimizers")
    torch.testing.assert_close(model.infer_z(goal=obs), model.model.skill_from_goal(torch.as_tensor(obs)))
    z_fn = model.infer_z(reward_fn=lambda next_obs: -np.abs(next_obs[:, 0]))
    assert z_fn.shape == z.shape and torch.isfinite(z_fn).all()
    policy = model.policy(z)
    action = policy(obs)
    assert action.shape == env.action_space.shape and np.all(np.abs(action) < 1)
    np.testing.assert_array_equal(action, model.model.act(obs[None], z[None], explore=False)[0])


def test_single_policy_method_and_bad_calls(runs):
    model = dvfb.load(runs / "rnd")
    obs, _ = envs.make("point_mass_maze_reach_top_left", seed=0).reset(seed=0)
    assert model.policy()(obs).shape == (2,)
    with pytest.raises(ConfigError, match="single policy"):
        model.infer_z(goal=obs)
    skilled = dvfb.load(runs / "dvfb")
    with pytest.raises(ConfigError, match="exactly one"):
        skilled.infer_z()
    with pytest.raises(ConfigError, match="pass z"):
        skilled.act(obs)
    with pytest.raises(ConfigError, match="rows"):
        skilled.infer_z(np.zeros((3, 4)), np.zeros((2, 4)), np.zeros(3))


def test_the_old_name_agent_still_gives_the_model_with_a_deprecation_warning(runs):
    loaded = dvfb.load(runs / "rnd")
    with pytest.warns(DeprecationWarning, match=r"\.agent is deprecated.*use \.model"):
        old = loaded.agent
    assert old is loaded.model
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new name warns of nothing
        assert loaded.model is old


MAZE_TASK = "point_mass_maze_reach_top_left"


@pytest.mark.parametrize("agent, extra, message", [
    # SF infers skills from rewards, not from goals: not "needs a method that infers skills from data".
    ("sf", [], "'sf' has no goal inference (--skill-source goal): its feature_regression protocol finds the skill "
               "from --skill-source rewards, reward_fn or dataset"),
    # A single policy's protocol has no --inference.steps: the missing goal inference is what to say.
    ("rnd", ["--inference.steps", "100"], "'rnd' has no goal inference (--skill-source goal): it has a single policy"),
])
def test_a_goal_for_a_method_without_goal_inference_says_so(runs, capsys, agent, extra, message):
    argv = ["zeroshot", str(runs / agent), "--task", MAZE_TASK, "--skill-source", "goal", "--goal", "0,0,0,0", *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not (runs / agent / "zeroshot").exists()
    obs, _ = envs.make(MAZE_TASK, seed=0).reset(seed=0)
    if agent == "sf":
        with pytest.raises(ConfigError, match="'sf' has no goal inference"):
            dvfb.load(runs / agent).infer_z(goal=obs)


def test_a_device_torch_cannot_use_is_one_line(runs):
    with pytest.raises(ConfigError, match="device 'tpu' is not one of auto, cpu, cuda"):
        dvfb.load(runs / "rnd", device="tpu")  # was torch's RuntimeError listing its device types
    if not torch.cuda.is_available():  # was torch's AssertionError
        with pytest.raises(ConfigError, match="device 'cuda' was requested but torch sees no CUDA device"):
            dvfb.load(runs / "rnd", device="cuda")
    assert dvfb.load(runs / "rnd", device="cpu").model.device == torch.device("cpu")
