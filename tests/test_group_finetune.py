"""Fine-tuning a group (docs/members.md): the stacked fine-tuner of every registered method equals
its members' separate fine-tuners after several updates (float64 to 1e-10, float32 bit for bit);
``finetune_group`` writes each member's ordinary fine-tuning run, close to its separate run; a
group resumes exactly; a member that goes non-finite stops alone; and bad groups are one line."""

from __future__ import annotations

import json

import pytest
import torch

from dvfb.agents import agent_names, get_spec
from dvfb.core.errors import NonFiniteLossError
from dvfb.nets.members import member_slice, stack_agents
from dvfb.protocols import finetuner_class
from dvfb.data import Batch
from dvfb.runs import RunDir, load_checkpoint, save_checkpoint
from dvfb.workflows.finetune import finetune
from dvfb.workflows.pretrain import pretrain
from tiny import MEMBERS, NOT_BITWISE, cast_batch, member_agents, run_cli, tiny_run_config

UPDATES = 3
MAZE = "point_mass_maze_reach_top_left"
SEEDS = [0, 1]


def _finetuners(name: str, dtype: torch.dtype):
    """Each member's fine-tuner and its twin's, built from the same global stream (a fresh critic's
    initialisation) on the same skill, and the members' replays."""
    agents, twins, replays = member_agents(name, dtype)
    config = tiny_run_config(name).finetune
    cls = finetuner_class(get_spec(name).finetuner)
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        built, twin_built = [], []
        for k, (agent, twin) in enumerate(zip(agents, twins)):
            skill = None
            if agent.skill.has_skill:
                skill = agent.sample_skill(1, generator=torch.Generator().manual_seed(50 + k))[0].to(dtype)
            torch.manual_seed(200 + k)
            built.append(cls(agent.model, skill, config))
            torch.manual_seed(200 + k)
            twin_built.append(cls(twin.model, None if skill is None else skill.clone(), config))
    finally:
        torch.set_default_dtype(previous)
    return built, twin_built, replays


def _run(name: str, dtype: torch.dtype):
    finetuners, twins, replays = _finetuners(name, dtype)
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        group = stack_agents(finetuners)
        assert group.members == MEMBERS and group.model.members == MEMBERS
        needs = twins[0].replay_needs()
        group_metrics, twin_metrics = [], []
        for u in range(UPDATES):
            batches = [cast_batch(needs.sample(replay, torch.Generator().manual_seed(7 + k + 10 * u)), dtype)
                       for k, replay in enumerate(replays)]
            group_metrics.append(group.update(Batch.stack(batches)))
            twin_metrics.append([twin.update(batch) for twin, batch in zip(twins, batches)])
    finally:
        torch.set_default_dtype(previous)
    return group, twins, group_metrics, twin_metrics


def _tensors(state, prefix=""):
    if isinstance(state, dict):
        for key, value in state.items():
            yield from _tensors(value, f"{prefix}/{key}")
    elif isinstance(state, torch.Tensor) and state.is_floating_point():
        yield prefix, state


def _assert_close(group, twins, group_metrics, twin_metrics, rtol, atol, moment_rtol=None):
    full = group.training_state()
    for k, twin in enumerate(twins):
        member = dict(_tensors(member_slice(full, k)))
        separate = dict(_tensors(twin.training_state()))
        assert member.keys() == separate.keys()
        for key, value in separate.items():
            tolerance = moment_rtol if moment_rtol is not None and "/exp_avg" in key else rtol
            torch.testing.assert_close(member[key].double(), value.double(), rtol=tolerance, atol=atol,
                                       msg=lambda m, key=key, k=k: f"member {k}, {key}: {m}")
        for u, (stacked, alone) in enumerate(zip(group_metrics, twin_metrics)):
            assert stacked.keys() == alone[k].keys()
            for key, value in alone[k].items():
                assert stacked[key].shape == (MEMBERS,), (key, stacked[key].shape)
                torch.testing.assert_close(stacked[key][k], value, rtol=rtol, atol=atol,
                                           msg=lambda m, key=key, k=k, u=u: f"update {u}, member {k}, {key}: {m}")


@pytest.mark.parametrize("name", agent_names())
def test_group_finetuner_member_equals_separate_finetuner_in_float64(name):
    _assert_close(*_run(name, torch.float64), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("name", agent_names())
def test_group_finetuner_member_equals_separate_finetuner_bit_for_bit_in_float32(name):
    # The same blocks as pre-training's (docs/members.md); a few Adam moments of ensemble heads
    # differ in their last bit without changing any parameter.
    _assert_close(*_run(name, torch.float32), rtol=0.0, atol=NOT_BITWISE.get(name, 0.0), moment_rtol=1e-6)


def _fast(agent: str) -> dict:
    if agent in ("dvfb", "fb"):
        return {"steps": 300, "random_action_steps": 100, "samples": 300, "eval_episodes": 1}
    if agent == "diayn":
        return {"steps": 1000, "eval_episodes": 1}
    return {"eval_episodes": 1}


SCHEDULE = {"seed_frames": 300, "eval_every": 500, "eval_episodes": 1, "update_every": 4, "checkpoint_every": 1000}


@pytest.mark.parametrize("agent_name, skill", [("dvfb", None), ("diayn", "resample"), ("rnd", None)])
@pytest.mark.slow
def test_group_finetuning_writes_each_members_own_run_close_to_its_separate_run(tmp_path, agent_name, skill):
    paths = [tmp_path / f"p_s{s}" for s in SEEDS]
    pretrain(tiny_run_config(agent_name), paths, seeds=SEEDS, progress=False)
    # Ten updates at the end of one episode (its end writes the checkpoint compared here).
    options = {**SCHEDULE, "frames": 1000, "seed_frames": 960, "eval_every": 1000,
               **({"skill": skill} if skill else {})}
    for path in paths:
        finetune(path, MAZE, name="alone", inference=_fast(agent_name), finetune=options, progress=False)
    runs = finetune(paths, MAZE, name="group", inference=_fast(agent_name), finetune=options, progress=False)
    assert [r.path for r in runs] == [p / "finetune" / "group" for p in paths]
    for path in paths:
        alone = json.loads((path / "finetune" / "alone" / "curve.json").read_text())
        grouped = json.loads((path / "finetune" / "group" / "curve.json").read_text())
        assert grouped["z"] == alone["z"] and grouped["seed"] == alone["seed"]
        assert [p["frames"] for p in grouped["curve"]] == [0, 1000]
        assert grouped["curve"][0]["returns"] == pytest.approx(alone["curve"][0]["returns"], rel=1e-3, abs=1e-2)
        a, b = load_checkpoint(RunDir(path / "finetune" / "alone")), load_checkpoint(RunDir(path / "finetune" / "group"))
        # Before the first update (URLB: the uniform phase; FB: the pre-trained actor) the data are
        # the same bit for bit.
        assert torch.equal(a["replay"]["rows"][:960], b["replay"]["rows"][:960])
        assert torch.equal(a["generator"], b["generator"])
        separate, member = dict(_tensors(a["finetuner"])), dict(_tensors(b["finetuner"]))
        assert separate.keys() == member.keys()
        for key, value in separate.items():
            if "/exp_avg" not in key:  # moments of near-zero gradients are relatively noisy
                torch.testing.assert_close(member[key], value, rtol=1e-3, atol=1e-3, msg=key)
        assert json.loads((path / "finetune" / "group" / "finetune_summary.json").read_text())["frames"] == 1000
    # Member 0 is not member 1.
    z0 = json.loads((paths[0] / "finetune" / "group" / "curve.json").read_text())["z"]
    z1 = json.loads((paths[1] / "finetune" / "group" / "curve.json").read_text())["z"]
    assert z0 != z1 or agent_name == "rnd"


@pytest.fixture(scope="module")
def fb_group(tmp_path_factory):
    root = tmp_path_factory.mktemp("fb_group")
    paths = [root / f"fb_s{s}" for s in SEEDS]
    pretrain(tiny_run_config("fb"), paths, seeds=SEEDS, progress=False)
    return paths


def _finetuner_state(path):
    return load_checkpoint(RunDir(path))["finetuner"]


@pytest.mark.slow
def test_group_finetuning_resume_equals_uninterrupted_group(fb_group):
    inference, options = _fast("fb"), dict(SCHEDULE)
    finetune(fb_group, MAZE, name="full", inference=inference, finetune={**options, "frames": 2000},
                   progress=False)
    finetune(fb_group, MAZE, name="split", inference=inference, finetune={**options, "frames": 1000},
                   progress=False)
    finetune(fb_group, MAZE, name="split", inference=inference, finetune={**options, "frames": 2000},
                   resume=True, progress=False)
    for path in fb_group:
        full = json.loads((path / "finetune" / "full" / "curve.json").read_text())
        split = json.loads((path / "finetune" / "split" / "curve.json").read_text())
        assert [p["frames"] for p in split["curve"]] == [0, 500, 1000, 1500, 2000]
        assert split["curve"] == full["curve"]
        a, b = dict(_tensors(_finetuner_state(path / "finetune" / "full"))), \
            dict(_tensors(_finetuner_state(path / "finetune" / "split")))
        for key, value in a.items():
            assert torch.equal(value, b[key]), (path.name, key)


@pytest.mark.slow
def test_a_non_finite_member_stops_its_fine_tuning_alone(fb_group, capsys):
    inference, options = _fast("fb"), dict(SCHEDULE)
    finetune(fb_group, MAZE, name="nan", inference=inference, finetune={**options, "frames": 1000},
                   progress=False)
    poisoned = RunDir(fb_group[1] / "finetune" / "nan")
    state = load_checkpoint(poisoned)
    for key in state["finetuner"]["finetuner"]:
        if key.startswith("task_critic.") and key.endswith("weight"):
            state["finetuner"]["finetuner"][key].fill_(float("nan"))
    save_checkpoint(poisoned, state, "resume_1000")
    with pytest.raises(NonFiniteLossError, match="1 of 2 members stopped"):
        finetune(fb_group, MAZE, name="nan", inference=inference, finetune={**options, "frames": 2000},
                       resume=True, progress=False)
    err = capsys.readouterr().err
    assert f"member seed 1 ({poisoned.path})" in err and "its fine-tuning stopped" in err
    healthy = fb_group[0] / "finetune" / "nan"
    assert json.loads((healthy / "finetune_summary.json").read_text())["frames"] == 2000
    # The stopped member's run stays as its last finished part left it.
    assert json.loads((poisoned.path / "finetune_summary.json").read_text())["frames"] == 1000


@pytest.mark.slow
def test_bad_group_fine_tunings_are_one_line_and_create_nothing(tmp_path, fb_group):
    aps = [tmp_path / f"aps_s{s}" for s in SEEDS]  # APS has a task regression
    pretrain(tiny_run_config("aps", frames=1000), aps, seeds=SEEDS, progress=False)
    cases = [
        ([*map(str, aps), "--task", MAZE, "--finetune.skill", "regressed"], "regressed fits each run's skill"),
        ([str(fb_group[0]), str(aps[0]), "--task", MAZE], "is not the same method and configuration"),
        ([str(fb_group[0]), str(fb_group[0]), "--task", MAZE], "a run is listed twice"),
    ]
    for args, message in cases:
        done = run_cli("finetune", *args, "--name", "bad", "--no-progress")
        assert done.returncode != 0
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], done.stderr
    for path in [*aps, *fb_group]:
        assert not (path / "finetune" / "bad").exists()
    for path in aps:  # not even the empty folder of fine-tuning runs
        assert not (path / "finetune").exists()


def test_a_member_in_use_is_refused_and_no_members_directory_is_left(fb_group):
    from dvfb.core.errors import RunDirError
    from dvfb.runs import RunLock

    busy = fb_group[1] / "finetune" / "busy"
    with RunLock(busy):  # another writer holds member 1's fine-tuning run
        with pytest.raises(RunDirError, match="in use"):
            finetune(fb_group, MAZE, name="busy", inference=_fast("fb"), finetune=dict(SCHEDULE), progress=False)
    assert not (fb_group[0] / "finetune" / "busy").exists()
