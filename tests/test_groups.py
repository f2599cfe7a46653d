"""Pre-training a group (docs/members.md): N members in one process, each in an ordinary run
directory; exact resume of the whole group; a member that goes non-finite stops alone; and the
errors of a bad --seeds command."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from dvfb import envs
from dvfb.core.errors import NonFiniteLossError
from dvfb.nets.members import drop_members, member_training_state, stack_agents
from dvfb.data import Batch
from dvfb.runs import RunDir, load_checkpoint, load_snapshot, save_checkpoint
from dvfb.training.metric_windows import MetricWindow
from dvfb.workflows.pretrain import pretrain
from dvfb.runs.snapshots import load_model
from dvfb.workflows.resources import open_run
from tiny import member_agents, run_cli, tiny_flags, tiny_run_config, tree_bytes

SEEDS = [0, 1]
# `dvfb pretrain` of FB on the maze, 600 frames unless a later --frames says otherwise.
PRETRAIN = ["pretrain", "--agent", "fb", "--domain", "point_mass_maze", "--frames", "600", "--seed-frames", "500"]


def _snapshot_modules(path, frames):
    return load_snapshot(RunDir(path), f"snapshot_{frames}")["modules"]


def _replay_rows(path):
    return load_checkpoint(RunDir(path), None)["replay"]["rows"]


def test_group_members_are_ordinary_runs_close_to_their_separate_runs(tmp_path):
    config = tiny_run_config("dvfb", frames=1000, seed_frames=960)
    paths = [tmp_path / f"group_s{seed}" for seed in SEEDS]
    runs = pretrain(config, paths, seeds=SEEDS, progress=False)
    assert [r.path for r in runs] == paths
    separate = tmp_path / "separate_s1"
    pretrain(dataclasses.replace(config, seed=1), separate, progress=False)
    # An ordinary run: its config has its own seed and its snapshot loads through the registry.
    run = open_run(paths[1])
    assert run.config.seed == 1
    agent, frames = load_model(run)
    assert frames == 1000 and agent.members == 0
    # The uniform phase is the same data bit for bit; the policy's steps and 10 updates agree to
    # float32 rounding (the stacked products round differently from the separate run's).
    grouped, alone = _replay_rows(paths[1]), _replay_rows(separate)
    seed_rows = config.seed_frames  # row t holds s_t and the action taken in it
    assert torch.equal(grouped[:seed_rows], alone[:seed_rows])
    torch.testing.assert_close(grouped, alone, rtol=1e-3, atol=1e-3)
    a, b = _snapshot_modules(paths[1], 1000), _snapshot_modules(separate, 1000)
    for key in b:
        for name, tensor in b[key].items():
            torch.testing.assert_close(a[key][name], tensor, rtol=1e-3, atol=1e-3)
    # Member 0 is not member 1.
    assert not torch.equal(_replay_rows(paths[0])[:seed_rows], grouped[:seed_rows])


@pytest.mark.parametrize("agent_name", ["dvfb", "diayn", "rnd"])
@pytest.mark.slow
def test_group_zeroshot_equals_each_members_own(tmp_path, agent_name):
    from dvfb.workflows.zeroshot import zeroshot

    config = tiny_run_config(agent_name, frames=1000)
    paths = [tmp_path / f"z_s{s}" for s in SEEDS]
    pretrain(config, paths, seeds=SEEDS, progress=False)
    task = "point_mass_maze_reach_top_left"
    fast = {"steps": 300, "random_action_steps": 100, "samples": 300, "eval_episodes": 2}
    if agent_name == "diayn":
        fast = {"steps": 1000, "eval_episodes": 2}
    elif agent_name == "rnd":
        fast = {"eval_episodes": 2}
    alone = [zeroshot(p, task, inference=fast, progress=False) for p in paths]
    together = zeroshot(paths, task, inference=fast, overwrite=True, progress=False)
    for a, b in zip(alone, together):
        assert a["z"] == b["z"] and a["seed"] == b["seed"]  # each member's own inference, bit for bit
        # The actions come from the stacked actor (float32 rounding apart from the separate one's).
        assert b["returns"] == pytest.approx(a["returns"], rel=1e-3, abs=1e-2)
        assert b["group"] == [str(p) for p in paths]


@pytest.mark.slow
def test_group_resume_equals_uninterrupted_group(tmp_path):
    config = tiny_run_config("fb", frames=2000)
    full = [tmp_path / f"full_s{s}" for s in SEEDS]
    split = [tmp_path / f"split_s{s}" for s in SEEDS]
    pretrain(config, full, seeds=SEEDS, progress=False)
    pretrain(dataclasses.replace(config, frames=1000), split, seeds=SEEDS, progress=False)
    pretrain(config, split, seeds=SEEDS, resume=True, progress=False)
    for a_path, b_path in zip(full, split):
        a, b = _snapshot_modules(a_path, 2000), _snapshot_modules(b_path, 2000)
        for key in a:
            for name, tensor in a[key].items():
                assert torch.equal(tensor, b[key][name]), (a_path.name, key, name)


@pytest.mark.slow
def test_a_non_finite_member_stops_alone(tmp_path, capsys):
    config = tiny_run_config("fb", frames=1000)
    paths = [tmp_path / f"m_s{s}" for s in SEEDS]
    pretrain(config, paths, seeds=SEEDS, progress=False)
    # Poison member 1's checkpoint (a real file): its networks hold NaN when the group resumes.
    run = RunDir(paths[1])
    state = load_checkpoint(run, None)
    for name, tensor in state["agent_state"]["modules"].items():
        if name.startswith("forward_map.") and tensor.is_floating_point():
            tensor.fill_(float("nan"))
    save_checkpoint(run, state, f"resume_{state['step']}")
    with pytest.raises(NonFiniteLossError, match=r"1 of 2 members stopped.*seed 1") as failure:
        pretrain(dataclasses.replace(config, frames=1500), paths, seeds=SEEDS, resume=True, progress=False)
    assert str(paths[1]) in str(failure.value) and "\n" not in str(failure.value)
    assert "member seed 1" in capsys.readouterr().err
    # Member 0 finished; member 1 kept its intact checkpoint and wrote no snapshot after it.
    assert (paths[0] / "pretrain_summary.json").is_file()
    assert (paths[0] / "snapshots" / "snapshot_1500.pt").is_file()
    assert not (paths[1] / "snapshots" / "snapshot_1500.pt").exists()


def test_group_window_and_drop_keep_the_healthy_members_exact():
    agents, twins, replays = member_agents("fb", torch.float32)
    group = stack_agents(agents)
    with torch.no_grad():
        group.forward_map.heads.second_weight[1].fill_(float("nan"))
    faults = []
    window = MetricWindow(None, lambda: [0, 1, 2], lambda member, message: faults.append((member, message)))
    needs = group.replay_needs()
    batches = [needs.sample(r, torch.Generator().manual_seed(k)) for k, r in enumerate(replays)]
    window.add(7, group.update(Batch.stack(batches)))
    window.flush()
    assert [m for m, _ in faults] == [1] and "at step 7" in faults[0][1]
    for k in (0, 2):
        twins[k].update(batches[k])
        state = member_training_state(group, k)["modules"]
        for name, tensor in twins[k].state_dict().items():
            torch.testing.assert_close(state[name], tensor, rtol=1e-4, atol=1e-5)
    drop_members(group, [0, 2])
    assert group.members == 2 and group.forward_map.heads.second_weight.shape[0] == 2
    batches = [needs.sample(replays[k], torch.Generator().manual_seed(10 + k)) for k in (0, 2)]
    metrics = group.update(Batch.stack(batches))
    assert all(torch.isfinite(v).all() for v in metrics.values())


@pytest.mark.parametrize("args, message", [
    (["--seeds", "0,1", "--run-dir", "{tmp}/plain"], "needs {seed} in it"),
    (["--seeds", "0,0", "--run-dir", "{tmp}/r_{seed}"], "lists a seed twice"),
    (["--seeds", "0,x", "--run-dir", "{tmp}/r_{seed}"], "invalid seeds"),
])
@pytest.mark.slow
def test_bad_seeds_are_one_line_and_create_nothing(tmp_path, args, message):
    done = run_cli(*PRETRAIN, *[a.replace("{tmp}", str(tmp_path)) for a in args])
    assert done.returncode != 0
    # argparse's own type errors come after its usage lines; the error itself is one line.
    assert message in done.stderr.strip().splitlines()[-1], done.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_group_refuses_an_existing_member_directory_before_creating_any(tmp_path):
    pretrain(tiny_run_config("fb", frames=600, seed=1), tmp_path / "r_1", progress=False)
    before = sorted(p.name for p in (tmp_path / "r_1").iterdir())
    done = run_cli(*PRETRAIN, "--seeds", "0,1", "--run-dir", str(tmp_path / "r_{seed}"))
    assert done.returncode != 0 and "already exists" in done.stderr
    assert not (tmp_path / "r_0").exists()
    assert sorted(p.name for p in (tmp_path / "r_1").iterdir()) == before


@pytest.mark.slow
def test_a_group_resume_with_finished_and_unfinished_members_is_refused_and_changes_nothing(tmp_path):
    template = str(tmp_path / "r_{seed}")
    tiny = [*tiny_flags("fb"), "--update-every", "4", "--replay-capacity", "2000", "--torch-threads", "1"]
    # Checkpoints come at episode ends: the maze's are every 1000 steps.
    assert run_cli(*PRETRAIN, "--seeds", "0,1", "--run-dir", template, "--frames", "1000", *tiny).returncode == 0
    alone = run_cli(*PRETRAIN, "--seed", "0", "--run-dir", str(tmp_path / "r_0"), "--frames", "2000", "--resume",
                    *tiny)
    assert alone.returncode == 0, alone.stderr
    before = tree_bytes(tmp_path)
    done = run_cli(*PRETRAIN, "--seeds", "0,1", "--run-dir", template, "--frames", "2000", "--resume", *tiny)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == ("dvfb pretrain: error: some members of the group have finished "
                                                    "and others not: resume the others alone")
    assert tree_bytes(tmp_path) == before  # no TensorBoard file, no lock, no checkpoint


@pytest.mark.slow
def test_a_group_that_does_not_fit_is_refused_before_anything_is_built(tmp_path):
    from dvfb.data import ReplayBuffer
    from dvfb.workflows.resources import available_memory_bytes

    # A replay that fits once but not twice: the estimate covers every member.
    available = available_memory_bytes()
    assert available is not None
    env = envs.make("point_mass_maze_reach_top_left")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    per_transition = ReplayBuffer.estimate_nbytes(1_000_000, obs_dim, action_dim, 10, 1000) / 1_000_000
    capacity = int(0.6 * available / per_transition)
    done = run_cli(*PRETRAIN, "--seeds", "0,1", "--run-dir", str(tmp_path / "r_{seed}"), "--replay-capacity",
                   str(capacity), "--fb.z-dim", "10")
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert "(2 members)" in last and "needs about" in last, done.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_group_zeroshot_skip_existing_evaluates_only_the_members_without_a_result(tmp_path):
    from dvfb.workflows.zeroshot import zeroshot

    paths = [tmp_path / f"k_s{s}" for s in SEEDS]
    pretrain(tiny_run_config("rnd", frames=1000), paths, seeds=SEEDS, progress=False)
    task = "point_mass_maze_reach_top_left"
    zeroshot(paths[0], task, inference={"eval_episodes": 1}, progress=False)
    first = (paths[0] / "zeroshot" / f"{task}.json").read_bytes()

    def cli(*extra):
        return run_cli("zeroshot", *map(str, paths), "--task", task, "--inference.eval-episodes", "1", "--no-progress",
                       *extra)

    refused = cli()  # an existing result is an error: one line, nothing written
    assert refused.returncode != 0 and len(refused.stderr.strip().splitlines()) == 1
    assert "exists; pass --overwrite" in refused.stderr and not (paths[1] / "zeroshot").exists()
    done = cli("--skip-existing")
    assert done.returncode == 0, done.stderr
    assert (paths[0] / "zeroshot" / f"{task}.json").read_bytes() == first  # left as it was
    assert (paths[1] / "zeroshot" / f"{task}.json").is_file()
    assert str(paths[1]) in done.stdout and str(paths[0]) not in done.stdout
