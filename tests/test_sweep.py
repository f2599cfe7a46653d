"""`dvfb sweep`: the grid and its cells, bad input, and the executors on real runs -- local worker
processes and a real single-node SLURM cluster (tests/slurm_cluster.py): equal results, a job
requeued mid-run, a killed submitter, a failing cell."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from dvfb.cli import main
from dvfb.runs import list_snapshots, load_snapshot
from dvfb.sweep import spec, units

from slurm_cluster import slurm_cluster  # noqa: F401 - the session fixture

# Tiny networks and budgets on walker (its tasks give non-zero returns even untrained).
TINY = ["--seed-frames", "300", "--update-every", "4", "--checkpoint-every", "1000", "--log-every", "200",
        "--fb.z-dim", "16", "--fb.hidden-dim", "32", "--fb.feature-dim", "16", "--fb.backward-hidden-dim", "32",
        "--fb.batch-size", "64", "--inference.steps", "300", "--inference.random-action-steps", "100",
        "--inference.samples", "300", "--inference.eval-episodes", "1", "--torch-threads", "1"]
# DVFB's own section (a sweep refuses an option that none of its methods has).
TINY_DVFB = ["--exploration.contrastive-hidden-dim", "32", "--exploration.rnd-rep-dim", "16", "--exploration.ce-k", "4"]


def sweep_args(sweep_dir: Path, executor: str, *, agents=("dvfb", "fb"), seeds=("0", "1"), frames=600,
               extra=()) -> list[str]:
    return ["sweep", "run", "--dir", str(sweep_dir), "--executor", executor, "--agents", *agents,
            "--domains", "walker", "--seeds", *seeds, "--frames", str(frames), "--slurm.poll-s", "1",
            "--slurm.zeroshot.time-min", "30", "--slurm.pretrain.time-min", "30", *TINY,
            *(TINY_DVFB if "dvfb" in agents else ()), *extra]


def unit_state(sweep_dir: Path, cell: str, unit: str) -> dict:
    return json.loads((sweep_dir / "state" / cell / f"{unit}.json").read_text())


def assert_same_results(a: Path, b: Path, cell: str) -> None:
    """Same agent weights at every snapshot and the same zero-shot results (task vector, returns)."""
    run_a, run_b = a / "runs" / cell, b / "runs" / cell
    snapshots = list_snapshots(run_a)
    assert snapshots and snapshots == list_snapshots(run_b)
    for name in snapshots:
        state_a, state_b = load_snapshot(run_a, name), load_snapshot(run_b, name)
        tensors_a = {k: v for k, v in _flatten(state_a) if isinstance(v, torch.Tensor)}
        tensors_b = dict((k, v) for k, v in _flatten(state_b) if isinstance(v, torch.Tensor))
        assert tensors_a and tensors_a.keys() == tensors_b.keys()
        for key in tensors_a:
            assert torch.equal(tensors_a[key], tensors_b[key]), f"{cell} {name}: {key} differs"
    results_a = sorted((run_a / "zeroshot").glob("*.json"))
    assert len(results_a) == 4
    for file in results_a:
        ra, rb = json.loads(file.read_text()), json.loads((run_b / "zeroshot" / file.name).read_text())
        assert (ra["z"], ra["returns"]) == (rb["z"], rb["returns"]), f"{cell} {file.name} differs"


def _flatten(state, prefix=""):
    if isinstance(state, dict):
        for key, value in state.items():
            yield from _flatten(value, f"{prefix}{key}/")
    elif isinstance(state, (list, tuple)):
        for i, value in enumerate(state):
            yield from _flatten(value, f"{prefix}{i}/")
    else:
        yield prefix, state


def wait_until(condition, what: str, limit_s: float = 600.0, poll_s: float = 0.5) -> None:
    deadline = time.monotonic() + limit_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(poll_s)


def sweep_jobs(sweep_dir: Path) -> dict[str, str]:
    path = sweep_dir / "jobs.json"
    return json.loads(path.read_text()) if path.exists() else {}


def squeue_ids() -> set[str]:
    out = subprocess.run(["squeue", "-h", "-r", "-o", "%i"], capture_output=True, text=True, check=True).stdout
    return set(out.split())


# ---------------------------------------------------------------------------------------------
# the grid, without running anything


def test_cells_named_from_their_values_and_axes_apply_to_methods_that_have_them():
    config = spec.build({}, {"agents": ["dvfb", "fb"], "domains": ["walker"], "seeds": [0, 1],
                             "overrides": {"frames": 5000}},
                        {}, {"exploration.alpha": "1,5", "fb.lr": "0.0001"})
    names = [cell.name for cell in spec.cells(config)]
    assert names == ["dvfb_walker_exploration.alpha=1.0_s0", "dvfb_walker_exploration.alpha=1.0_s1",
                     "dvfb_walker_exploration.alpha=5.0_s0", "dvfb_walker_exploration.alpha=5.0_s1",
                     "fb_walker_s0", "fb_walker_s1"]
    dvfb_cell = spec.cells(config)[2]
    resolved = spec.cell_config(config, dvfb_cell)
    assert (resolved.exploration.alpha, resolved.fb.lr, resolved.frames, resolved.seed) == (5.0, 0.0001, 5000, 0)
    assert config.overrides == {"frames": [5000], "exploration.alpha": [1.0, 5.0], "fb.lr": [0.0001]}


@pytest.mark.parametrize("extra, message", [
    (["--nope.x", "1"], "unrecognized arguments"),
    (["--fb.hidden-dim", "wide"], "--fb.hidden-dim: 'wide' is not a valid int"),
    (["--agents", "fb", "--exploration.alpha", "5"], "no method of the sweep (fb) has the option --exploration.alpha"),
    (["--domains", "mars"], "unknown domain 'mars'"),
    (["--fb.actor-arch", "mlp,cnn"], "'cnn' is not one of"),
    (["--phases", "pretrain", "finetune"], "the finetune phase needs finetune_tasks"),
])
def test_bad_input_is_one_line_exit_2_and_creates_nothing(tmp_path, capsys, extra, message):
    sweep_dir = tmp_path / "sweep"
    with pytest.raises(SystemExit) if "unrecognized" in message else _no_raise():
        code = main(["sweep", "run", "--dir", str(sweep_dir), "--executor", "debug", *extra])
        assert code == 2
    err = capsys.readouterr().err
    assert message in err
    if "unrecognized" not in message:
        assert len(err.strip().splitlines()) == 1
    assert not sweep_dir.exists()


@pytest.mark.parametrize("body, message", [
    ("seeds = 5", "SweepConfig.seeds: expected a list, got 5"),
    ('agents = "dvfb"', "SweepConfig.agents: expected a list, got 'dvfb'"),
    ("[slurm]\npretrain = 3", "SlurmConfig.pretrain: expected a mapping, got 3"),
    ("overrides = 3", "overrides must be a table"),
    ('[overrides]\nframes = "many"', "frames: expected int, got 'many'"),
    ("[overrides]\nsnapshot_frames = 5", "--snapshot-frames takes a list of values"),
    ("[overrides]\nfb = 3", "--fb is a section of options, not an option"),
    ('[overrides.fb]\nz_dim = "x"', "z_dim: expected int, got 'x'"),
])
def test_sweep_files_of_the_wrong_shape_are_one_line(tmp_path, capsys, body, message):
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(body + "\n")
    sweep_dir = tmp_path / "sweep"
    assert main(["sweep", "run", str(sweep_file), "--dir", str(sweep_dir), "--executor", "debug"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not sweep_dir.exists()


@pytest.mark.parametrize("body, message", [
    ('[overrides.fb]\nlr = "fast"', "lr: expected float, got 'fast'"),
    ('[overrides]\n"fb.lr" = "1e-4"', "lr: expected float, got '1e-4'"),
    ("[overrides]\nfb.lr = true", "lr: expected float, got True"),
])
def test_a_float_option_given_as_text_is_refused_by_the_dry_run_and_the_run(tmp_path, capsys, body, message):
    """It passed every check, and the sweep directory was made, before its pre-training refused it
    (exit 1, nothing on the sweep's stderr)."""
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text('agents = ["fb"]\ndomains = ["point_mass_maze"]\nseeds = [0]\nphases = ["pretrain"]\n'
                          + body + "\n")
    sweep_dir = tmp_path / "sweep"
    for dry_run in (["--dry-run"], []):  # the dry run first: it starts nothing even where the check is missing
        assert main(["sweep", "run", str(sweep_file), "--dir", str(sweep_dir), "--executor", "debug", *dry_run]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
        assert not sweep_dir.exists()


def test_a_nested_table_of_overrides_is_its_dotted_options():
    from dvfb.sweep.spec import SweepConfig, normalise_overrides

    config = SweepConfig(agents=["fb"], domains=["point_mass_maze"], seeds=[0])
    nested = normalise_overrides(config, {"fb": {"z_dim": [8, 16]}, "frames": 600}, from_text=False)
    assert nested == normalise_overrides(config, {"fb.z_dim": [8, 16], "frames": 600}, from_text=False)
    assert nested == {"fb.z_dim": [8, 16], "frames": [600]}


@pytest.mark.parametrize("text, message", [("[0, 1]", "not a list"), ('{"seeds": null}', "expected a list, got None")])
def test_json_sweep_files_of_the_wrong_shape_are_one_line(tmp_path, capsys, text, message):
    sweep_file = tmp_path / "sweep.json"
    sweep_file.write_text(text)
    assert main(["sweep", "run", str(sweep_file), "--dir", str(tmp_path / "sweep")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "sweep").exists()


def test_a_waiting_phase_is_stopped_with_sigterm_and_killed_after_the_grace(tmp_path):
    """The runner's stop path, with real processes: the phase ignores USR2 (SLURM's warning goes
    to the runner), gets SIGTERM once a stop is asked for, and is killed if it ignores that too."""
    code = ("import signal, sys, time\n"
            "if sys.argv[1] == 'ignores': signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
            "print('ready', flush=True); time.sleep(120)\n")
    for behaviour, expected in (("obeys", -signal.SIGTERM), ("ignores", -signal.SIGKILL)):
        child = subprocess.Popen([sys.executable, "-c", code, behaviour], stdout=subprocess.PIPE, text=True,
                                 preexec_fn=units._die_with_parent_and_ignore_usr2)
        assert child.stdout.readline().strip() == "ready"
        child.send_signal(signal.SIGUSR2)  # ignored: SLURM's time-limit warning
        time.sleep(0.3)
        assert child.poll() is None
        started = time.monotonic()
        returncode = units._wait_for_phase(child, lambda: True, grace_s=1.0)
        assert returncode == expected and time.monotonic() - started < 30


def test_status_of_a_sweep_that_is_not_running_says_its_units_wait(tmp_path, capsys):
    sweep_dir = tmp_path / "sweep"
    args = sweep_args(sweep_dir, "debug", agents=("fb",), seeds=("0",), frames=400)
    assert main(args + ["--phases", "pretrain"]) == 0
    capsys.readouterr()
    # A grid whose pre-training is done but whose zero-shot never started: not "stopped".
    config = json.loads((sweep_dir / "sweep.json").read_text())
    config["phases"] = ["pretrain", "zeroshot"]
    (sweep_dir / "sweep.json").write_text(json.dumps(config))
    assert main(["sweep", "status", str(sweep_dir)]) == 0
    row = capsys.readouterr().out.splitlines()[1]
    assert row.split()[:2] == ["fb_walker_s0", "queued"] and "not started; run the sweep command to continue" in row


def test_a_killed_local_sweep_leaves_no_unit_running(tmp_path):
    import socket

    from dvfb.sweep import runner

    sweep_dir = tmp_path / "sweep"
    assert main(sweep_args(sweep_dir, "debug", agents=("fb",), seeds=("0",), frames=400) + ["--phases", "pretrain"]) == 0
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    path = sweep_dir / "state" / "fb_walker_s0" / "pretrain.json"
    state = json.loads(path.read_text())
    state.update(state="running", pid=dead.pid, host=socket.gethostname(), job_id=None)
    path.write_text(json.dumps(state))
    config = spec.load_stored(sweep_dir)
    assert runner.close_dead_units(units.SweepDir(sweep_dir), config) == ["fb_walker_s0/pretrain"]
    closed = unit_state(sweep_dir, "fb_walker_s0", "pretrain")
    assert closed["state"] == "failed" and "ended without recording" in closed["reason"]


@pytest.mark.e2e
def test_ctrl_c_stops_a_local_sweep_and_a_rerun_continues_it(tmp_path, capsys):
    """SIGINT to the sweep process alone: the running phase is stopped (it checkpoints), the queued
    units never start, the sweep exits with 130; the same command continues from the checkpoint."""
    sweep_dir = tmp_path / "sweep"
    args = sweep_args(sweep_dir, "local", agents=("fb",), seeds=("0", "1"), frames=3000,
                      extra=["--workers", "1", "--phases", "pretrain"])
    submitter = subprocess.Popen([sys.executable, "-m", "dvfb", *args], stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True)
    try:
        run = sweep_dir / "runs" / "fb_walker_s0"
        wait_until(lambda: (run / "checkpoints" / "latest").exists(), "the first checkpoint")
        assert not (run / "pretrain_summary.json").exists(), "the run finished before it could be stopped"
        submitter.send_signal(signal.SIGINT)
        output, _ = submitter.communicate(timeout=120)
    finally:
        if submitter.poll() is None:
            submitter.kill()
            submitter.wait()
    assert submitter.returncode == 130, output
    assert "stopped by SIGINT" in output and "repeat the command to continue" in output
    assert unit_state(sweep_dir, "fb_walker_s0", "pretrain")["state"] == "interrupted"
    assert not (sweep_dir / "state" / "fb_walker_s1").exists() and not (sweep_dir / "runs" / "fb_walker_s1").exists()
    assert main(args) == 0
    assert "2 unit(s) run, 0 already done" in capsys.readouterr().out
    log = (sweep_dir / "logs" / "fb_walker_s0" / "pretrain.log").read_text()
    assert log.split("=== attempt 2")[1].splitlines()[0].endswith("--resume")
    assert json.loads((run / "pretrain_summary.json").read_text())["resumed_from"] > 0


class _no_raise:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


# ---------------------------------------------------------------------------------------------
# local and debug


def test_a_phase_that_argparse_refuses_in_the_debug_executor_is_a_recorded_failure(tmp_path, monkeypatch, capsys):
    def refusing_main(argv):
        print("dvfb pretrain: error: argument --x: invalid choice", file=sys.stderr)
        raise SystemExit(2)

    monkeypatch.setattr(units, "_in_process_main", refusing_main)
    log = tmp_path / "unit.log"
    assert units._run_in_process(["pretrain", "--x"], log) == 2
    assert "invalid choice" in log.read_text() and "invalid choice" in capsys.readouterr().err


@pytest.mark.e2e
def test_debug_sweep_rerun_changes_nothing_and_other_grid_is_refused(tmp_path, capsys):
    sweep_dir = tmp_path / "sweep"
    args = sweep_args(sweep_dir, "debug", agents=("fb",), seeds=("0",), frames=400)
    assert main(args) == 0
    run = sweep_dir / "runs" / "fb_walker_s0"
    files = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in run.rglob("*") if p.is_file()}
    assert (run / "pretrain_summary.json").exists() and len(list((run / "zeroshot").glob("*.json"))) == 4
    table = (sweep_dir / "report" / "table1_zeroshot.md").read_text()
    stand = next(line for line in table.splitlines() if "walker_stand" in line)
    assert "±" not in stand  # one seed: the mean alone
    capsys.readouterr()
    assert main(args) == 0
    assert "0 unit(s) run, 2 already done" in capsys.readouterr().out
    assert files == {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in run.rglob("*") if p.is_file()}
    stored = (sweep_dir / "sweep.json").read_text()
    assert main(sweep_args(sweep_dir, "debug", agents=("fb",), seeds=("0",), frames=800)) == 2
    assert "holds another sweep (overrides differ" in capsys.readouterr().err
    assert (sweep_dir / "sweep.json").read_text() == stored
    assert unit_state(sweep_dir, "fb_walker_s0", "pretrain")["attempts"] == 1


def test_a_cell_with_results_but_no_checkpoint_or_summary_is_never_started_over(tmp_path):
    run = tmp_path / "cell"
    (run / "metrics").mkdir(parents=True)
    assert units._continue_flags(run) == ["--overwrite"]  # stopped before its first checkpoint: nothing to lose
    (run / "zeroshot").mkdir()
    (run / "zeroshot" / "walker_walk.json").write_text("{}")
    with pytest.raises(units.UnitFailed, match=r"holds results \(zeroshot\) but no checkpoint"):
        units._continue_flags(run)
    assert units._continue_flags(tmp_path / "new") == []


@pytest.mark.e2e
def test_a_damaged_result_is_never_counted_and_a_lost_summary_is_rebuilt(tmp_path, capsys):
    """A zero-shot result cut short (a full disk, an editor) or another task's moved over it is set
    aside and evaluated again; a finished cell whose pretrain_summary.json was deleted is done again
    without a failure (its summary rebuilt from the final checkpoint), and nothing else runs."""
    sweep_dir = tmp_path / "sweep"
    args = sweep_args(sweep_dir, "debug", agents=("fb",), seeds=("0",), frames=400)
    assert main(args) == 0
    run = sweep_dir / "runs" / "fb_walker_s0"
    walk, run_result = run / "zeroshot" / "walker_walk.json", run / "zeroshot" / "walker_run.json"
    whole_walk = walk.read_bytes()
    numbers = {k: v for k, v in json.loads(whole_walk).items() if k != "wall_clock_s"}
    walk.write_bytes(whole_walk[: len(whole_walk) // 2])
    run_result.write_bytes(whole_walk)  # walker_walk's result under walker_run's name
    capsys.readouterr()
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert "1 unit(s) run, 1 already done" in out
    assert f"{walk} is corrupt or unreadable" in err and "set aside as walker_walk.json.damaged" in err
    assert "holds a result of 'walker_walk', not of 'walker_run'" in err
    assert {k: v for k, v in json.loads(walk.read_text()).items() if k != "wall_clock_s"} == numbers  # again, the same
    assert json.loads(run_result.read_text())["task"] == "walker_run"
    assert (run / "zeroshot" / "walker_walk.json.damaged").stat().st_size == len(whole_walk) // 2
    summary = run / "pretrain_summary.json"
    first = json.loads(summary.read_text())
    summary.unlink()
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert "0 unit(s) run, 2 already done" in out, out
    assert "had lost its pretrain_summary.json; rebuilt it from its records" in err
    rebuilt = json.loads(summary.read_text())
    assert rebuilt["frames"] == first["frames"] == 400 and rebuilt["rebuilt"] is True
    assert rebuilt["episodes"] == first["episodes"]


# ---------------------------------------------------------------------------------------------
# on the SLURM cluster


def test_slurm_sweep_equals_local_and_reports_over_seeds(tmp_path, slurm_cluster, capsys):  # noqa: F811
    local_dir, slurm_dir = tmp_path / "local", tmp_path / "slurm"
    assert main(sweep_args(local_dir, "local", extra=["--workers", "2"])) == 0
    assert main(sweep_args(slurm_dir, "slurm")) == 0
    out = capsys.readouterr().out
    assert "slurm: 8 job(s) submitted" in out
    cells = ["dvfb_walker_s0", "dvfb_walker_s1", "fb_walker_s0", "fb_walker_s1"]
    assert sorted(p.name for p in (slurm_dir / "runs").iterdir()) == cells
    for cell in cells:
        assert unit_state(slurm_dir, cell, "pretrain")["job_id"] in sweep_jobs(slurm_dir).values()
        assert_same_results(local_dir, slurm_dir, cell)
    table = (slurm_dir / "report" / "table1_zeroshot.md").read_text()
    assert "walker_run" in table and "±" in table and "dvfb" in table and "fb" in table
    assert table == (local_dir / "report" / "table1_zeroshot.md").read_text()
    assert main(["sweep", "status", str(slurm_dir)]) == 0
    status = capsys.readouterr().out
    rows = status.splitlines()[1:-1]
    assert [row.split()[:2] for row in rows] == [[cell, "done"] for cell in cells] and "4 done (4 cells" in status


def test_a_cells_seeds_run_as_one_group_job_on_slurm_as_locally(tmp_path, slurm_cluster, capsys):  # noqa: F811
    # --seeds-per-job 2: each cell's two seeds pre-train in one process and one SLURM job
    # (dvfb pretrain --seeds, docs/members.md), then zero-shot as one group in one job; each seed
    # still has its own run directory and results.
    group = ["--seeds-per-job", "2"]
    local_dir, slurm_dir = tmp_path / "local", tmp_path / "slurm"
    assert main(sweep_args(local_dir, "local", agents=("fb",), extra=["--workers", "2", *group])) == 0
    assert main(sweep_args(slurm_dir, "slurm", agents=("fb",), extra=group)) == 0
    assert "slurm: 2 job(s) submitted" in capsys.readouterr().out  # one pre-training, one zero-shot
    jobs = sweep_jobs(slurm_dir)
    assert {"fb_walker_s0/pretrain", "fb_walker_s0/zeroshot"} <= set(jobs)
    assert "fb_walker_s1/pretrain" not in jobs and "fb_walker_s1/zeroshot" not in jobs
    log = (slurm_dir / "logs" / "fb_walker_s0" / "pretrain.log").read_text()
    assert "--seeds 0,1" in log and str(slurm_dir / "runs" / "fb_walker_s{seed}") in log
    log = (slurm_dir / "logs" / "fb_walker_s0" / "zeroshot.log").read_text()
    runs = [str(slurm_dir / "runs" / f"fb_walker_s{seed}") for seed in (0, 1)]
    assert f"zeroshot {runs[0]} {runs[1]} --task" in log and "--skip-existing" in log
    for cell in ("fb_walker_s0", "fb_walker_s1"):
        assert_same_results(local_dir, slurm_dir, cell)
    assert main(["sweep", "status", str(slurm_dir)]) == 0
    assert "2 done (2 cells" in capsys.readouterr().out


@pytest.mark.e2e
def test_a_groups_fine_tuning_runs_as_one_unit_and_each_seed_gets_its_own_run(tmp_path, capsys):
    # --seeds-per-job 2 with a fine-tuning phase: one dvfb finetune process for both seeds, in the
    # group leader's unit; each seed's run holds its own fine-tuning run.
    sweep_dir = tmp_path / "ft"
    finetune = ["--phases", "pretrain", "finetune", "--finetune-tasks", "walker_walk", "--finetune.frames", "400",
                "--finetune.eval-every", "400", "--finetune.eval-episodes", "1", "--finetune.seed-frames", "300",
                "--finetune.update-every", "4", "--seeds-per-job", "2"]
    assert main(sweep_args(sweep_dir, "debug", agents=("fb",), extra=finetune)) == 0
    runs = [sweep_dir / "runs" / f"fb_walker_s{seed}" for seed in (0, 1)]
    for run in runs:
        summary = json.loads((run / "finetune" / "walker_walk" / "finetune_summary.json").read_text())
        assert summary["frames"] == 400
    log = (sweep_dir / "logs" / "fb_walker_s0" / "finetune-walker_walk.log").read_text()
    assert f"finetune {runs[0]} {runs[1]} --task walker_walk" in log
    assert not (sweep_dir / "state" / "fb_walker_s1" / "finetune-walker_walk.json").exists()
    capsys.readouterr()
    assert main(["sweep", "status", str(sweep_dir)]) == 0
    status = capsys.readouterr().out
    assert [row.split()[:2] for row in status.splitlines()[1:-1]] == [["fb_walker_s0", "done"], ["fb_walker_s1", "done"]]


def test_requeued_job_resumes_and_ends_equal_to_an_uninterrupted_run(tmp_path, slurm_cluster):  # noqa: F811
    one_cell = dict(agents=("fb",), seeds=("0",), frames=4000)
    reference = tmp_path / "reference"
    assert main(sweep_args(reference, "debug", **one_cell)) == 0
    sweep_dir = tmp_path / "requeued"
    submitter = subprocess.Popen([sys.executable, "-m", "dvfb", *sweep_args(sweep_dir, "slurm", **one_cell)],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        run = sweep_dir / "runs" / "fb_walker_s0"
        wait_until(lambda: (run / "checkpoints" / "latest").exists(), "the first checkpoint")
        assert not (run / "pretrain_summary.json").exists(), "the run finished before it could be requeued"
        job = sweep_jobs(sweep_dir)["fb_walker_s0/pretrain"]
        subprocess.run(["scontrol", "requeue", job], check=True, capture_output=True)
        wait_until(lambda: job_state(job) == "PENDING", "the requeued job to wait", limit_s=120)
        release_requeued(job)
        output, _ = submitter.communicate(timeout=900)
    finally:
        if submitter.poll() is None:
            submitter.kill()
            submitter.wait()
    assert submitter.returncode == 0, output
    state = unit_state(sweep_dir, "fb_walker_s0", "pretrain")
    assert state["state"] == "done" and state["attempts"] == 2
    log = (sweep_dir / "logs" / "fb_walker_s0" / "pretrain.log").read_text()
    assert "=== attempt 2" in log and log.split("=== attempt 2")[1].splitlines()[0].endswith("--resume")
    assert json.loads((run / "pretrain_summary.json").read_text())["resumed_from"] > 0
    assert_same_results(reference, sweep_dir, "fb_walker_s0")


def job_state(job: str) -> str:
    out = subprocess.run(["squeue", "-h", "-j", job, "-o", "%T"], capture_output=True, text=True).stdout
    return out.strip()


def job_run_time_s(job: str) -> int:
    """How long the job has been running, from ``scontrol``'s RunTime ([D-]HH:MM:SS)."""
    out = subprocess.run(["scontrol", "show", "job", "-o", job], capture_output=True, text=True, check=True).stdout
    text = out.split("RunTime=", 1)[1].split()[0]
    days, _, clock = text.rpartition("-")
    hours, minutes, seconds = (int(x) for x in clock.split(":"))
    return ((int(days or 0) * 24 + hours) * 60 + minutes) * 60 + seconds


def lower_time_limit(job: str) -> None:
    """Lower the job's limit (whole minutes from its start) to end 35 to 95 s from now.

    slurmctld checks limits every 30 s. A limit already passed at that check ends the job without
    the USR2 warning (the time-out is checked first), so the limit is set from the job's run time,
    not as a fixed minute; with the sweep's default signal delay (120 s) the next check sends USR2."""
    minutes = -(-(job_run_time_s(job) + 35) // 60)
    subprocess.run(["scontrol", "update", f"jobid={job}", f"TimeLimit={minutes}"], check=True, capture_output=True)


def requeued_by_slurm(sweep_dir: Path, cell: str, unit: str) -> bool:
    """True once the unit recorded its requeue; a unit that ended in any other way fails at once.

    The runner records the phase it stopped as interrupted (exit 143, SIGTERM) a moment before the
    job records the requeue, so that state means "not yet"."""
    state = unit_state(sweep_dir, cell, unit)
    if "requeued by SLURM" in (state["reason"] or ""):
        return True
    stopping = state["state"] == "interrupted" and state.get("exit_code") == 143
    assert state["state"] == "running" or stopping, f"{unit} ended without a requeue: {state}"
    return False


def release_requeued(job: str) -> None:
    """SLURM holds a requeued job for two minutes (Reason=BeginTime); release it at once, as an
    administrator can, so that the tests do not wait. Only once the node is idle: until the old
    attempt's step has ended (srun waits up to 32 s for it), its credential is revoked, and a job
    started in that window is killed as "non-startable" (seen on a loaded machine)."""
    wait_until(lambda: subprocess.run(["sinfo", "-h", "-N", "-o", "%T"], capture_output=True, text=True
                                      ).stdout.split() == ["idle"], "the node to be idle after the requeue")
    # slurmd refuses a credential issued in the same second as the old attempt's revocation (it
    # compares whole seconds), and the job is then killed as "non-startable" with exit status 1;
    # the revocation came before the node went idle, so two seconds from here are always later.
    time.sleep(2.0)
    subprocess.run(["scontrol", "update", f"jobid={job}", "StartTime=now"], capture_output=True)


def phase_pid(run: Path, command: str) -> int | None:
    """The process id of the phase ``dvfb COMMAND RUN ...`` (a grandchild of the SLURM job), if any."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
        except OSError:  # it ended meanwhile
            continue
        if argv[1:4] == ["-m", "dvfb", command] and len(argv) > 4 and argv[4] == str(run):
            return int(entry.name)
    return None


def frozen_until_sigterm(pid: int) -> bool:
    """False while the process stays stopped with no SIGTERM pending (/proc's masks, bit 15 - 1).
    True once SIGTERM waits in it, or once something else (SLURM's signal delivery) continued it
    or it ended: either way the runner's stop has reached it."""
    try:
        status = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:  # it ended
        return True
    fields = dict(line.split(":", 1) for line in status if ":" in line)
    if not fields.get("State", "").strip().startswith("T"):
        return True
    masks = [int(fields[k].strip(), 16) for k in ("SigPnd", "ShdPnd") if k in fields]
    return any(mask & (1 << (signal.SIGTERM - 1)) for mask in masks)


def test_a_time_limit_requeues_the_phase_and_it_ends_bit_identical(tmp_path, slurm_cluster):  # noqa: F811
    """A real time limit: once the fine-tuning phase has written a checkpoint, the test lowers its
    job's limit to end 35 to 95 s later, so that SLURM sends USR2 (120 s before the limit by
    default) at its next periodic check; the phase ignores USR2, the runner stops it with SIGTERM
    (it checkpoints), the job requeues itself and the next attempt resumes. The uninterrupted
    reference runs beside it, and the phase ends bit-identical to it.

    The phase must still be running when USR2 comes, up to 30 s after the limit is lowered (the
    limit check's period). Rather than giving it that much work on the fastest machine, the test
    freezes it (SIGSTOP) at its first checkpoint and thaws it (SIGCONT) once the runner's SIGTERM
    waits in it: the signals and the stop are the real ones, only the phase's pace is the test's.

    One phase is enough: every phase runs on the same session core with one set of resume rules
    (docs/architecture.md), and the runner's USR2 handling does not know which phase it stops.
    Fine-tuning is the phase limited here because it also resumes from its pre-trained run;
    test_requeued_job_resumes_and_ends_equal_to_an_uninterrupted_run requeues a pre-training."""
    finetune = ["--phases", "pretrain", "finetune", "--finetune-tasks", "walker_walk",
                "--finetune.frames", "8000", "--finetune.eval-every", "4000", "--finetune.eval-episodes", "1",
                "--finetune.seed-frames", "300", "--finetune.update-every", "4", "--finetune.checkpoint-every", "1000"]
    one_cell = dict(agents=("fb",), seeds=("0",), frames=3000, extra=finetune)
    reference, sweep_dir = tmp_path / "reference", tmp_path / "limited"
    processes = [subprocess.Popen([sys.executable, "-m", "dvfb", *sweep_args(d, executor, **one_cell)],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                 for d, executor in ((reference, "debug"), (sweep_dir, "slurm"))]
    run = sweep_dir / "runs" / "fb_walker_s0"
    unit, run_dir = "finetune-walker_walk", run / "finetune" / "walker_walk"
    frozen = None
    try:
        wait_until(lambda: (run_dir / "checkpoints" / "latest").exists(), f"the first {unit} checkpoint")
        frozen = phase_pid(run, "finetune")
        assert frozen is not None, f"no {unit} process"
        os.kill(frozen, signal.SIGSTOP)
        job = sweep_jobs(sweep_dir)[f"fb_walker_s0/{unit}"]
        lower_time_limit(job)
        wait_until(lambda: frozen_until_sigterm(frozen), f"the runner to stop {unit} after SLURM's USR2", limit_s=150)
        os.kill(frozen, signal.SIGCONT)
        frozen = None
        wait_until(lambda: requeued_by_slurm(sweep_dir, "fb_walker_s0", unit),
                   f"the {unit} job to stop at its time limit", limit_s=300)
        wait_until(lambda: job_state(job) == "PENDING", f"the {unit} job to be requeued")
        subprocess.run(["scontrol", "update", f"jobid={job}", "TimeLimit=30"], check=True, capture_output=True)
        release_requeued(job)
        outputs = [p.communicate(timeout=900)[0] for p in processes]
    finally:
        if frozen is not None:
            try:
                os.kill(frozen, signal.SIGCONT)
            except ProcessLookupError:
                pass
        for p in processes:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert [p.returncode for p in processes] == [0, 0], "\n".join(outputs)
    for name, attempts in (("pretrain", 1), (unit, 2)):
        state = unit_state(sweep_dir, "fb_walker_s0", name)
        assert state["state"] == "done" and state["attempts"] == attempts, (name, state)
    log = (sweep_dir / "logs" / "fb_walker_s0" / f"{unit}.log").read_text()
    assert "SIGTERM received" in log.split("=== attempt 2")[0]
    assert log.split("=== attempt 2")[1].splitlines()[0].endswith("--resume")
    # The job got SLURM's USR2 and requeued itself (submitit reads the limit the job started with,
    # so it calls the lowered limit a preemption; the path is the same).
    job_logs = "".join(p.read_text() for p in (sweep_dir / "slurm").rglob("*_log.out"))
    assert job_logs.count("Caught signal SIGUSR2") >= 1 and job_logs.count("Requeued job") == 1
    expected_run = reference / "runs" / "fb_walker_s0"
    curve = json.loads((run_dir / "curve.json").read_text())["curve"]
    expected = json.loads((expected_run / "finetune" / "walker_walk" / "curve.json").read_text())["curve"]
    assert [p["frames"] for p in curve] == [0, 4000, 8000]
    assert [p["returns"] for p in curve] == [p["returns"] for p in expected]
    from dvfb.runs import RunDir, load_checkpoint

    final = load_checkpoint(RunDir(run_dir))
    expected_final = load_checkpoint(RunDir(expected_run / "finetune" / "walker_walk"))
    assert final["step"] == expected_final["step"] == 8000
    tensors = {k: v for k, v in _flatten(final["finetuner"]) if isinstance(v, torch.Tensor)}
    expected_tensors = dict(_flatten(expected_final["finetuner"]))
    assert tensors and all(torch.equal(v, expected_tensors[k]) for k, v in tensors.items())


def test_rerun_after_killed_submitter_completes_only_the_missing_units(tmp_path, slurm_cluster, capsys):  # noqa: F811
    sweep_dir = tmp_path / "sweep"
    args = sweep_args(sweep_dir, "slurm", agents=("fb",), seeds=("0", "1"))
    submitter = subprocess.Popen([sys.executable, "-m", "dvfb", *args], stdout=subprocess.DEVNULL,
                                 stderr=subprocess.DEVNULL)
    runs = sweep_dir / "runs"
    states = sweep_dir / "state"
    wait_until(lambda: any(json.loads(p.read_text())["state"] == "done" for p in states.glob("*/pretrain.json")),
               "a finished pre-training")
    os.kill(submitter.pid, signal.SIGKILL)
    submitter.wait()
    # The allocation is lost too: every job of the sweep that is still queued or running goes.
    jobs = sweep_jobs(sweep_dir)
    left = [job for job in jobs.values() if job in squeue_ids()]
    if left:
        subprocess.run(["scancel", *left], check=True)
    wait_until(lambda: not squeue_ids() & set(jobs.values()), "the cancelled jobs to end")
    # Done as the sweep itself decides it (the unit's outputs on disk): a job cancelled right after
    # its command finished has a complete unit whose state file was not updated yet.
    config, sweep = spec.load_stored(sweep_dir), units.SweepDir(sweep_dir)

    def done(key: str) -> bool:
        return units.is_done(sweep, config, units.find_unit(config, *key.split("/")))

    done_before = {key for key in jobs if done(key)}
    assert done_before and len(done_before) < len(jobs), "the kill came too late or too early to test anything"
    finished = {p: (p.stat().st_mtime_ns, p.read_bytes()) for key in done_before
                for p in (runs / key.split("/")[0]).rglob("pretrain_summary.json")}
    capsys.readouterr()
    assert main(args) == 0
    out = capsys.readouterr().out
    assert f"{len(jobs) - len(done_before)} job(s) submitted" in out
    # Every unit counted once: those done before this run as already done, the rest as run now.
    assert f"{len(jobs) - len(done_before)} unit(s) run, {len(done_before)} already done, 0 failed" in out
    for key in jobs:
        state = unit_state(sweep_dir, *key.split("/"))
        assert done(key)
        if key in done_before:
            assert state["attempts"] == 1, f"{key} ran again"
        else:
            assert state["state"] == "done"
    assert finished == {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in finished}


def test_failing_cell_is_reported_with_its_log_and_the_rest_finish(tmp_path, slurm_cluster, capsys):  # noqa: F811
    sweep_dir = tmp_path / "sweep"
    # A replay smaller than an episode passes the config's checks and fails when the run starts.
    code = main(sweep_args(sweep_dir, "slurm", agents=("fb",), seeds=("0",),
                           extra=["--replay-capacity", "1000000,500"]))
    out = capsys.readouterr().out
    assert code == 1
    bad, good = "fb_walker_replay_capacity=500_s0", "fb_walker_replay_capacity=1000000_s0"
    log = sweep_dir / "logs" / bad / "pretrain.log"
    assert f"FAILED {bad}/pretrain failed (exit status 2: dvfb pretrain: error: --replay-capacity 500 must be" in out
    assert f"log: {log}" in out and "--replay-capacity 500 must be at least the episode length" in log.read_text()
    assert f"{bad}/zeroshot not run" in out
    assert len(list((sweep_dir / "runs" / good / "zeroshot").glob("*.json"))) == 4
    assert (sweep_dir / "report" / "replay_capacity=1000000" / "report.md").exists()
    assert main(["sweep", "status", str(sweep_dir)]) == 0
    status = capsys.readouterr().out
    assert f"{bad}" in status and "failed" in status and str(log) in status and "1 done, 1 failed" in status


def test_a_second_sweep_on_the_same_directory_is_refused_before_it_touches_anything(tmp_path, capsys):
    import os

    from dvfb.runs import RunLock

    sweep_dir = tmp_path / "sweep"
    sweep_dir.mkdir()
    with RunLock(sweep_dir):  # as a first sweep process holds it
        code = main(sweep_args(sweep_dir, "debug", agents=("fb",), seeds=("0",), frames=400))
    assert code == 2
    assert f"in use by process {os.getpid()}" in capsys.readouterr().err
    assert sorted(p.name for p in sweep_dir.iterdir()) == [".lock"]  # no state, no sweep.json


# ---------------------------------------------------------------------------------------------
# a study's grid: methods per domain, earlier snapshots, results kept in git


def test_exclude_leaves_cells_out_and_a_pattern_that_matches_nothing_is_refused():
    config = spec.build({}, {"agents": ["fb", "rnd", "supervised"], "domains": ["walker", "point_mass_maze"],
                             "seeds": [0, 1], "zeroshot_tasks": ["walker_walk", "point_mass_maze_reach_top_left"],
                             "exclude": ["rnd_point_mass_maze_*", "supervised_*_s1"]}, {}, {})
    names = [cell.name for cell in spec.cells(config)]
    assert names == ["fb_walker_s0", "fb_walker_s1", "fb_point_mass_maze_s0", "fb_point_mass_maze_s1",
                     "rnd_walker_s0", "rnd_walker_s1", "supervised_walker_walk_s0",
                     "supervised_point_mass_maze_reach_top_left_s0"]
    assert [c.name for c in spec.matching(config, ["*_walker_*"])] == [
        "fb_walker_s0", "fb_walker_s1", "rnd_walker_s0", "rnd_walker_s1", "supervised_walker_walk_s0"]
    with pytest.raises(spec.ConfigError, match="exclude: 'cesd_\\*' matches no cell"):
        spec.build({}, {"agents": ["fb"], "exclude": ["cesd_*"]}, {}, {})
    with pytest.raises(spec.ConfigError, match="leaves the sweep without cells"):
        spec.build({}, {"agents": ["fb"], "exclude": ["fb_*"]}, {}, {})
    with pytest.raises(spec.ConfigError, match="--only 'dvfb_\\*' matches no cell"):
        spec.matching(config, ["dvfb_*"])


@pytest.mark.parametrize("data, message", [
    ({"zeroshot_snapshots": [300]}, "keeps no snapshot after 300 frames before its last (600); add it to --snapshot-frames"),
    ({"zeroshot_snapshots": [600], "overrides": {"snapshot_frames": [600]}}, "keeps no snapshot after 600 frames"),
    ({"zeroshot_snapshots": [300], "phases": ["pretrain"]}, "zeroshot_snapshots needs the zeroshot phase"),
])
def test_earlier_snapshots_must_be_kept_by_every_cell(data, message):
    data = {"agents": ["fb"], "seeds": [0], **data}
    data["overrides"] = {"frames": 600, "seed_frames": 300, **data.get("overrides", {})}
    with pytest.raises(spec.ConfigError, match=message.replace("(", "\\(").replace(")", "\\)")):
        spec.build({}, data, {}, {})


def test_a_list_override_reaches_dvfb_pretrain_as_one_argument_per_item():
    config = spec.build({}, {"agents": ["fb"], "seeds": [0], "zeroshot_snapshots": [300],
                             "overrides": {"frames": 600, "seed_frames": 300, "snapshot_frames": [300, 600]}}, {}, {})
    [cell] = spec.cells(config)
    argv = units.command(units.SweepDir("/nowhere"), config, units.units_of(config, cell)[0], 1)
    i = argv.index("--snapshot-frames")
    assert argv[i + 1: i + 3] == ["300", "600"]
    assert [u.name for u in units.units_of(config, cell)] == ["pretrain", "zeroshot@300", "zeroshot"]


@pytest.mark.e2e
def test_a_committed_sweep_directory_runs_nothing_from_a_clone_and_says_when_a_snapshot_is_missing(tmp_path, capsys):
    """Earlier snapshots are evaluated as their own units; the sweep's .gitignore keeps the small
    results only; the sweep run again from a git clone of them runs nothing, and a unit that needs a
    snapshot the clone lacks fails with that reason instead of training again."""
    repo = tmp_path / "repo"
    sweep_dir = repo / "study"
    sweep_dir.mkdir(parents=True)
    (sweep_dir / "sweep.toml").write_text("# the study's file lives beside its results\n")
    extra = ["--snapshot-frames", "300", "--zeroshot-snapshots", "300", "--zeroshot-tasks", "walker_walk",
             "walker_run", "--report", "false"]
    args = sweep_args(sweep_dir, "local", agents=("fb",), seeds=("0", "1"), extra=extra)
    assert main([*args, "--workers", "1", "--only", "fb_walker_s0"]) == 0
    out = capsys.readouterr().out
    assert "no report yet" not in out  # --report false
    run = sweep_dir / "runs" / "fb_walker_s0"
    assert sorted(p.name for p in (run / "zeroshot").iterdir()) == [
        "walker_run.json", "walker_run@300.json", "walker_walk.json", "walker_walk@300.json"]
    early = json.loads((run / "zeroshot" / "walker_walk@300.json").read_text())
    assert early["snapshot_frames"] == 300
    assert not (sweep_dir / "runs" / "fb_walker_s1").exists()  # not among --only's cells this time
    # The order of a local sweep: the cell's zero-shot units ran before the next pre-training.
    log_lines = [line for line in out.splitlines() if line.startswith("[sweep] done ")]
    assert [line.split()[-1] for line in log_lines] == ["fb_walker_s0/pretrain", "fb_walker_s0/zeroshot@300",
                                                        "fb_walker_s0/zeroshot"]

    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q", str(repo)], check=True)
    subprocess.run([*git, "-C", str(repo), "add", "-A"], check=True)
    subprocess.run([*git, "-C", str(repo), "commit", "-q", "-m", "results"], check=True)
    kept = subprocess.run(["git", "-C", str(repo), "ls-files"], capture_output=True, text=True, check=True).stdout
    assert "study/runs/fb_walker_s0/zeroshot/walker_walk@300.json" in kept
    assert "study/runs/fb_walker_s0/pretrain_summary.json" in kept
    assert not any(part in kept for part in ("snapshots/", "checkpoints/", "state/", "logs/", "/tb/"))
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(repo), str(clone)], check=True)
    cloned = clone / "study"
    capsys.readouterr()
    assert main([*sweep_args(cloned, "local", agents=("fb",), seeds=("0", "1"), extra=extra), "--workers", "1",
                 "--only", "fb_walker_s0"]) == 0
    assert "0 unit(s) run, 3 already done" in capsys.readouterr().out
    # A missing result whose snapshot did not travel: the reason, and nothing trained again.
    (cloned / "runs" / "fb_walker_s0" / "zeroshot" / "walker_run@300.json").unlink()
    assert main([*sweep_args(cloned, "local", agents=("fb",), seeds=("0", "1"), extra=extra), "--workers", "1",
                 "--only", "fb_walker_s0"]) == 1
    out = capsys.readouterr().out
    assert "has finished pre-training but not its snapshot after 300 frames" in out
    assert not (cloned / "runs" / "fb_walker_s0" / "snapshots").exists()
    assert unit_state(cloned, "fb_walker_s0", "zeroshot@300")["state"] == "failed"
