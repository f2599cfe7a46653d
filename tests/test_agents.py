"""One test set over every registered method (the registry decides what runs here).

For each agent: a tiny update changes exactly its optimisers' parameters and returns finite device
metrics; a snapshot round trip through the registry gives the same networks and actions; a resumed
pre-training equals an uninterrupted one; zero-shot and fine-tuning run end to end on real MuJoCo
physics and real run directories. Plus the interface rules that every later family relies on:
snapshots of another method, domain or shape are refused naming both sides, and legacy runs load.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from dvfb import envs
from dvfb.agents import agent_names, get_spec, make_agent
from dvfb.cli import main
from dvfb.core.errors import CheckpointError
from dvfb.protocols import finetuner_class, protocols_of
from dvfb.runs import RunDir, load_snapshot
from dvfb.runs.layout import PretrainRun
from dvfb.runs.snapshots import model_from_snapshot, check_snapshot, load_model, snapshot_state
from dvfb.runs.run_config import load_run_config, run_config_class
from dvfb.workflows.finetune import finetune
from dvfb.workflows.pretrain import pretrain
from dvfb.workflows.zeroshot import zeroshot
from tiny import filled_replay, replayed_return, tiny_run_config

AGENTS = agent_names()
DVFB_REWARDS = ("rnd_ce", "icm_apt", "proto", "cic")
# Skill selection needs whole episodes: one maze episode of 1000 steps.
FAST_INFERENCE = {"steps": 300, "random_action_steps": 100, "samples": 300, "eval_episodes": 1}
FAST_SELECTION = {"steps": 1000, "eval_episodes": 1}
MAZE = envs.make("point_mass_maze_reach_top_left")
OBS, ACT = MAZE.observation_space.shape[0], MAZE.action_space.shape[0]


def build(agent_name: str, **sections):
    torch.manual_seed(0)
    config = tiny_run_config(agent_name)
    if sections:
        from dvfb.core.config import merge

        config = merge(config, sections)
    return make_agent(agent_name, OBS, ACT, config, "cpu"), config


def agent_cases():
    cases = [(name, {}) for name in AGENTS]
    cases += [("dvfb", {"exploration": {"reward": r}}) for r in DVFB_REWARDS if r != "rnd_ce"]
    return cases


@pytest.mark.parametrize("agent_name,sections", agent_cases(),
                         ids=lambda v: v if isinstance(v, str) else "-".join(d["reward"] for d in v.values()) or "")
def test_update_changes_exactly_the_optimised_parameters(agent_name, sections):
    agent, _config = build(agent_name, **sections)
    replay = filled_replay(agent)
    needs = agent.replay_needs()
    before = {n: p.detach().clone() for n, p in agent.named_parameters()}
    optimised = {id(p) for opt in agent.optimizers().values() for group in opt.param_groups for p in group["params"]}
    for _ in range(3):
        metrics = agent.update(needs.sample(replay))
    assert metrics and all(isinstance(v, torch.Tensor) and v.dim() == 0 for v in metrics.values())
    assert all(torch.isfinite(v) for v in metrics.values())
    changed = {n for n, p in agent.named_parameters() if not torch.equal(before[n], p)}
    for name, p in agent.named_parameters():
        if id(p) in optimised:
            assert name in changed, f"{agent_name}: optimised parameter {name} did not change"
        elif p.requires_grad:
            raise AssertionError(f"{agent_name}: trainable parameter {name} belongs to no optimiser")
    # Frozen networks (RND's target) never move; targets move only by their EMA.
    assert changed, agent_name


@pytest.mark.parametrize("agent_name", AGENTS)
def test_snapshot_round_trip_through_the_registry(agent_name):
    agent, config = build(agent_name)
    replay = filled_replay(agent)
    for _ in range(2):
        agent.update(agent.replay_needs().sample(replay))
    state = snapshot_state(agent, config, frames=123)
    assert state["format"] == 2 and state["agent"] == agent_name and state["domain"] == "point_mass_maze"
    state = torch.load(_roundtrip(state), weights_only=False)
    check_snapshot(state, config, "snap")
    loaded = model_from_snapshot(state, config, "cpu", "snap")
    assert type(loaded) is type(agent.model) and not hasattr(loaded, "optimizers")
    for key, module in loaded.snapshot_modules().items():
        for (n1, t1), (n2, t2) in zip(agent.pretrained_modules()[key].state_dict().items(), module.state_dict().items()):
            same = torch.equal(t1, t2) if isinstance(t1, torch.Tensor) else t1 == t2  # Proto's queue pointer
            assert n1 == n2 and same, (key, n1)
    obs = MAZE.reset(seed=3)[0][None]
    skill = agent.sample_skill(1)
    assert np.array_equal(agent.act(obs, skill, explore=False), loaded.act(obs, skill, explore=False))


def _roundtrip(state):
    import io

    buffer = io.BytesIO()
    torch.save(state, buffer)
    buffer.seek(0)
    return buffer


@pytest.mark.parametrize("agent_name", AGENTS)
@pytest.mark.slow
def test_resume_equals_uninterrupted_zeroshot_and_finetune(agent_name, tmp_path):
    full, split = tmp_path / "full", tmp_path / "split"
    # An update every 8 steps: about 190 updates, half of them after the resume, are enough to
    # see a difference, and the resume tests of all the methods cost about half as much.
    config = tiny_run_config(agent_name, frames=2000, update_every=8)
    pretrain(config, full, progress=False)
    pretrain(dataclasses.replace(config, frames=1000), split, progress=False)
    pretrain(config, split, resume=True, progress=False)
    a = load_snapshot(RunDir(full), "snapshot_2000")["modules"]
    b = load_snapshot(RunDir(split), "snapshot_2000")["modules"]
    assert a.keys() == b.keys()
    for key in a:
        for name, tensor in a[key].items():
            same = torch.equal(tensor, b[key][name]) if isinstance(tensor, torch.Tensor) else tensor == b[key][name]
            assert same, (agent_name, key, name)

    zero_shot, _finetuner = protocols_of(agent_name)
    # Only the options of the method's protocol: the others are errors (strict configs).
    fast = FAST_SELECTION if zero_shot.name == "skill_selection" else FAST_INFERENCE
    inference = {k: v for k, v in fast.items() if k in {f.name for f in dataclasses.fields(zero_shot.config_cls)}}
    result = zeroshot(full, "point_mass_maze_reach_top_left", inference=inference)
    assert result["agent"] == agent_name and result["eval_episodes"] == 1
    assert result["protocol"] == zero_shot.name
    assert (result["z"] is None) == (zero_shot.name == "single_policy")
    # The recorded return is the episode's: the stored skill replayed by hand gives it again.
    assert result["mean_return"] == pytest.approx(
        replayed_return(full, "point_mass_maze_reach_top_left", result["z"], result["seed"]), rel=1e-6)

    ft = finetune(full, "point_mass_maze_reach_top_left", inference=inference,
                  finetune={"frames": 600, "seed_frames": 300, "eval_every": 600, "eval_episodes": 1,
                            "update_every": 4, "checkpoint_every": 1000}, progress=False)
    curve = json.loads((ft.path / "curve.json").read_text())["curve"]
    assert [p["frames"] for p in curve] == [0, 600]
    metrics = (ft.path / "metrics" / "train.jsonl").read_text().splitlines()
    assert metrics and all(np.isfinite(v) for v in json.loads(metrics[-1]).values() if isinstance(v, float))


def test_ddpg_finetuner_copies_the_trunk_and_keeps_the_random_target():
    agent, config = build("rnd")
    replay = filled_replay(agent)
    agent.update(agent.replay_needs().sample(replay))
    pretrained_critic = {k: v.clone() for k, v in agent.core.critic.state_dict().items()}
    finetuner = finetuner_class(get_spec("rnd").finetuner)(agent, None, config.finetune)
    critic, target = agent.core.critic, agent.core.critic_target
    for key, value in critic.state_dict().items():
        copied = torch.equal(value, pretrained_critic[key])
        assert copied == key.startswith("trunk."), key  # heads are fresh, the trunk is pre-trained
        if key.startswith("trunk.0.weight"):  # the target is the fresh critic before the copy (URLB)
            assert not torch.equal(target.state_dict()[key], value)
    before = {k: v.clone() for k, v in agent.core.actor.state_dict().items()}
    metrics = finetuner.update(finetuner.replay_needs().sample(replay))
    assert {"critic_loss", "actor_loss", "reward"} <= set(metrics)
    assert any(not torch.equal(before[k], v) for k, v in agent.core.actor.state_dict().items())
    # Proto copies the whole critic.
    proto, proto_config = build("proto")
    assert proto_config.finetune.init_critic == "all"
    whole = {k: v.clone() for k, v in proto.core.critic.state_dict().items()}
    finetuner_class(get_spec("proto").finetuner)(proto, None, proto_config.finetune)
    assert all(torch.equal(v, whole[k]) for k, v in proto.core.critic.state_dict().items())


def test_ddpg_critic_loss_by_hand():
    """y = r + gamma^n min_k Q'_k(s_{t+n}, a'), loss = sum_k mean (Q_k(s, a) - y)^2, with the
    noise of a' replayed from the same seed."""
    agent, _config = build("disagreement")
    core = agent.core
    replay = filled_replay(agent)
    batch = agent.replay_needs().sample(replay)
    assert batch.z is None and torch.allclose(batch.discount, torch.full_like(batch.discount, 0.99 ** 3))
    reward = torch.rand(batch.obs.shape[0], 1)
    skill = batch.obs.new_zeros(batch.obs.shape[0], 0)
    torch.manual_seed(5)
    loss = core.critic_loss(batch, skill, reward)
    torch.manual_seed(5)
    with torch.no_grad():
        mean = core.actor(batch.next_obs, skill)
        noise = (torch.randn_like(mean) * 0.2).clamp(-0.3, 0.3)
        next_action = (mean + noise).clamp(-1 + 1e-6, 1 - 1e-6)
        q_next = [core.critic_target(batch.next_obs, skill, next_action)[k] for k in range(2)]
        y = reward + 0.99 ** 3 * torch.minimum(q_next[0], q_next[1])
    q = core.critic(batch.obs, skill, batch.action)
    expected = ((q[0] - y) ** 2).mean() + ((q[1] - y) ** 2).mean()
    torch.testing.assert_close(loss, expected)


def test_snapshot_of_another_method_domain_or_shape_names_both_sides():
    rnd, rnd_config = build("rnd")
    state = snapshot_state(rnd, rnd_config, 10)
    proto_config = tiny_run_config("proto")
    with pytest.raises(CheckpointError, match="agent 'rnd'.*agent 'proto'"):
        check_snapshot(state, proto_config, "snap")
    walker = dataclasses.replace(rnd_config, domain="walker")
    with pytest.raises(CheckpointError, match="domain 'point_mass_maze'.*domain 'walker'"):
        check_snapshot(state, walker, "snap")
    wider = tiny_run_config("rnd")
    wider = dataclasses.replace(wider, ddpg=dataclasses.replace(wider.ddpg, hidden_dim=64))
    with pytest.raises(CheckpointError, match="ddpg.hidden_dim: snapshot 32, run 64"):
        check_snapshot(state, wider, "snap")
    state["obs_dim"] = OBS + 1
    with pytest.raises(CheckpointError, match="does not fit"):
        model_from_snapshot(state, rnd_config, "cpu", "snap")


def test_legacy_fb_run_still_loads(tmp_path):
    """Runs written before the registry: FB configs carried an ignored exploration section and
    snapshots had no format, domain or full config check; both still load."""
    run = tmp_path / "fb"
    pretrain(tiny_run_config("fb"), run, progress=False)
    config = json.loads((run / "config.json").read_text())
    config["exploration"] = {"alpha": 5.0, "use_ce": True}
    (run / "config.json").write_text(json.dumps(config))
    snap = run / "snapshots" / "snapshot_1000.pt"
    state = torch.load(snap, weights_only=False)
    for key in ("format", "domain"):
        state.pop(key)
    state["config"]["exploration"] = {"alpha": 5.0}
    torch.save(state, snap)
    loaded = load_run_config(run / "config.json")
    assert not hasattr(loaded, "exploration") and type(loaded) is run_config_class("fb")
    model, frames = load_model(PretrainRun(run, loaded))
    assert frames == 1000 and model.name == "fb"


def test_cli_lists_agents_and_their_flags(capsys):
    assert main(["agents"]) == 0
    out = capsys.readouterr().out
    for name in AGENTS:
        assert f"\n{name} " in "\n" + out
    with pytest.raises(SystemExit) as exc:
        main(["pretrain", "--agent", "rnd", "--help"])
    assert exc.value.code == 0
    help_text = capsys.readouterr().out
    assert "--rnd.rep-dim" in help_text and "--ddpg.nstep" in help_text and "--fb.z-dim" not in help_text
    with pytest.raises(SystemExit) as exc:
        main(["pretrain", "--agent", "rnd", "--fb.z-dim", "8"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main(["pretrain", "--agent", "moonwalker"])
    assert exc.value.code == 2
    assert "invalid choice: 'moonwalker'" in capsys.readouterr().err
