"""Reports and analyses (dvfb.analysis): tables, curves, value and exploration analyses, videos.

The report tests write synthetic run directories (real PretrainConfig/FinetuneRunConfig files,
zero-shot results, curves) with known numbers and check the table cells. The end-to-end tests run
the analyses with tiny budgets on conftest's tiny DVFB maze run (on a copy where they write); the
video tests render in subprocesses with OSMesa (software OpenGL) and with no OpenGL backend at all.
"""

from __future__ import annotations

import csv
import ctypes.util
import importlib.util
import io
import json
import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dvfb.analysis.common import AnalysisError, method_name
from dvfb.analysis.statistics import coverage
from dvfb.analysis.report import make_report
from dvfb.analysis.statistics import binned_spearman, quantile_bins, spearman
from dvfb.protocols.dual_value import FinetuneConfig
from dvfb.cli import main
from dvfb.runs import write_json_atomic
from dvfb.runs.presets import preset_config

from tiny import FAST_INFERENCE, copy_run, make_finetune_run, make_pretrain_run, md_row, run_cli

MAZE_TASK = "point_mass_maze_reach_top_left"


# ---------------------------------------------------------------------------------------------
# synthetic run directories (tiny.make_pretrain_run and make_finetune_run)


@pytest.fixture
def walker_runs(tmp_path: Path) -> Path:
    """Known numbers: dvfb seeds 0, 1 (all walker tasks) and 2 (walk only), fb seed 0 (stand only),
    dvfb w/o CE on the maze."""
    root = tmp_path / "runs"
    make_pretrain_run(root / "dvfb_s0", seed=0, zeroshot={
        "walker_stand": 900, "walker_walk": 100, "walker_run": 50, "walker_flip": 200})
    make_pretrain_run(root / "dvfb_s1", seed=1, zeroshot={
        "walker_stand": 700, "walker_walk": 300, "walker_run": 150, "walker_flip": 400})
    make_pretrain_run(root / "nested" / "dvfb_s2", seed=2, zeroshot={"walker_walk": 200})
    make_pretrain_run(root / "fb_s0", agent="fb", seed=0, zeroshot={"walker_stand": 500})
    make_pretrain_run(root / "maze" / "dvfb_noce_s0", domain="point_mass_maze", use_ce=False,
                      zeroshot={MAZE_TASK: 10})
    return root


def read_csv(path: Path) -> dict[str, dict[str, str]]:
    rows = csv.DictReader(io.StringIO(path.read_text()))
    return {f"{r['domain']}/{r['task']}": r for r in rows}


def md_columns(markdown: str) -> list[str]:
    header = next(line for line in markdown.splitlines() if line.startswith("| domain |"))
    return [c.strip() for c in header.strip().strip("|").split("|")][2:]


# ---------------------------------------------------------------------------------------------
# method names and report arithmetic


def test_method_name_is_derived_from_configs():
    config = preset_config("small")
    assert method_name(config) == "dvfb"
    assert method_name({"agent": "dvfb", "exploration": {"use_ce": False}}) == "dvfb_wo_ce"
    assert method_name({"agent": "dvfb", "exploration": {"reward": "proto"}}) == "dvfb_proto"
    assert method_name({"agent": "fb", "exploration": {"use_ce": False}}) == "fb"  # CE is a DVFB option only
    assert method_name(config, FinetuneConfig()) == "dvfb"
    assert method_name(config, FinetuneConfig(eta=0.0)) == "dvfb_wo_svf"
    assert method_name({"agent": "fb"}, FinetuneConfig(reward_mapping=False)) == "fb_wo_map"
    assert method_name({"agent": "dvfb", "exploration": {"use_ce": False}},
                       {"eta": 0, "reward_mapping": False}) == "dvfb_wo_ce_wo_svf_wo_map"
    assert method_name(preset_config("small", agent="rnd")) == "rnd"
    assert method_name({"agent": "rnd"}, {"init_critic": "trunk"}) == "rnd"  # no FB ablation suffixes


def test_zeroshot_table_cells(walker_runs: Path, tmp_path: Path):
    random_file = tmp_path / "random_walker.json"
    write_json_atomic(random_file, {"agent": "random", "domain": "walker", "seed": 0, "episodes": 2, "tasks": {
        t: {"mean_return": v, "std_return": 1.0, "returns": [v, v]}
        for t, v in {"walker_stand": 40, "walker_walk": 30, "walker_run": 20, "walker_flip": 10}.items()}})
    out = tmp_path / "report"
    # The same run reached through two paths (parent and itself) counts once.
    report = make_report([walker_runs, walker_runs / "dvfb_s0"], out, random_files=[random_file])
    assert report.finetune is None
    # No result carries a success rate (DMC tasks have none), so there is no Table 6.
    assert report.success_zeroshot is None and not (out / "table6_success.md").exists()
    md = (out / "table1_zeroshot.md").read_text()
    table = md.split("### ")[0]
    assert md_columns(table) == ["dvfb", "dvfb_wo_ce", "fb", "random"]
    # mean ± sample std over seeds (ddof = 1): stand [900, 700], walk [100, 300, 200]
    assert md_row(table, "walker", "walker_stand") == ["800.0 ± 141.4", "–", "500.0", "40.0"]
    assert md_row(table, "walker", "walker_walk") == ["200.0 ± 100.0", "–", "–", "30.0"]
    # average: mean of task means (800, 200, 100, 300); spread over the complete seeds 0 and 1
    # (per-seed averages 312.5 and 387.5); fb lacks tasks -> a gap, never a zero.
    assert md_row(table, "walker", "average") == ["350.0 ± 53.0", "–", "–", "25.0"]
    assert md_row(table, "point_mass_maze", MAZE_TASK) == ["–", "10.0", "–", "–"]
    assert md_row(table, "point_mass_maze", "point_mass_maze_reach_top_right") == ["–"] * 4
    # expert-normalised (percent of URLB expert): 800/984, and no expert return for the maze
    normalised = md.split("### ")[1]
    assert md_row(normalised, "walker", "walker_stand") == ["81.3 ± 14.4", "–", "50.8", "4.1"]
    assert md_row(normalised, "point_mass_maze", MAZE_TASK) == ["–"] * 4
    expected_avg = np.mean([800 / 984, 200 / 971, 100 / 796, 300 / 799]) * 100
    assert md_row(normalised, "walker", "average")[0].startswith(f"{expected_avg:.1f} ± ")

    rows = read_csv(out / "table1_zeroshot.csv")
    walk = rows["walker/walker_walk"]
    assert float(walk["dvfb_mean"]) == pytest.approx(200.0)
    assert float(walk["dvfb_std"]) == pytest.approx(np.std([100, 300, 200], ddof=1))
    assert walk["dvfb_n"] == "3"
    assert walk["fb_mean"] == walk["fb_std"] == walk["fb_n"] == ""  # a gap, not 0
    assert rows["walker/walker_stand"]["fb_std"] == ""  # one seed: no spread
    assert float(rows["walker/average"]["dvfb_mean"]) == pytest.approx(350.0)
    assert float(rows["walker/average"]["dvfb_std"]) == pytest.approx(np.std([312.5, 387.5], ddof=1))
    normalised_rows = read_csv(out / "table1_zeroshot_normalised.csv")
    assert float(normalised_rows["walker/walker_stand"]["dvfb_mean"]) == pytest.approx(100 * 800 / 984)
    assert normalised_rows["point_mass_maze/" + MAZE_TASK]["dvfb_wo_ce_mean"] == ""
    assert "Table 1" in (out / "report.md").read_text()


def test_standard_error_option(walker_runs: Path, tmp_path: Path, capsys):
    out = tmp_path / "report_se"
    assert main(["report", str(walker_runs), "--out", str(out), "--stderr"]) == 0
    table = (out / "table1_zeroshot.md").read_text().split("### ")[0]
    se = 100.0 / math.sqrt(3)
    assert md_row(table, "walker", "walker_walk")[0] == f"200.0 ± {se:.1f}"
    rows = read_csv(out / "table1_zeroshot.csv")
    assert float(rows["walker/walker_walk"]["dvfb_se"]) == pytest.approx(se)
    assert "standard error" in table
    assert "walker_walk" in capsys.readouterr().out
    # An existing report is not overwritten without --overwrite.
    assert main(["report", str(walker_runs), "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["report", str(walker_runs), "--out", str(out), "--overwrite"]) == 0


def test_duplicate_results_are_an_error_naming_both_files(walker_runs: Path, tmp_path: Path, capsys):
    make_pretrain_run(walker_runs / "copy_of_s0", seed=0, zeroshot={"walker_walk": 123})
    with pytest.raises(AnalysisError) as exc:
        make_report([walker_runs], tmp_path / "out")
    message = str(exc.value)
    assert "dvfb_s0" in message and "copy_of_s0" in message and "walker_walk" in message
    assert main(["report", str(walker_runs), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "duplicate" in err and "copy_of_s0" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_report_bad_inputs(tmp_path: Path, capsys):
    assert main(["report", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    make_pretrain_run(tmp_path / "bare")  # a run without any results
    assert main(["report", str(tmp_path / "bare"), "--out", str(tmp_path / "o")]) == 2
    assert "no zero-shot or fine-tuning results" in capsys.readouterr().err


def assert_png_has_content(path: Path) -> None:
    from matplotlib.image import imread

    assert path.is_file() and path.stat().st_size > 0, path
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] > 50 and image.shape[1] > 50
    assert float(image[..., :3].std()) > 0.01, f"{path} is a uniform image"


def test_finetune_table_and_curves(tmp_path: Path):
    root = tmp_path / "runs"
    s0 = make_pretrain_run(root / "dvfb_s0", seed=0)
    s1 = make_pretrain_run(root / "dvfb_s1", seed=1)
    fb = make_pretrain_run(root / "fb_s0", agent="fb", seed=0)
    make_finetune_run(s0, "walker_walk", [(0, 100), (5000, 300), (10000, 500)])
    make_finetune_run(s1, "walker_walk", [(0, 200), (5000, 400), (10000, 700)])
    make_finetune_run(s0, "walker_walk", [(0, 100), (10000, 250)], name="walk_wo_svf", eta=0.0)
    make_finetune_run(s0, "walker_walk", [(0, 100), (10000, 150)], name="walk_wo_map", reward_mapping=False)
    make_finetune_run(fb, "walker_run", [(0, 10), (5000, 20)], finished=False)
    out = tmp_path / "report"
    report = make_report([root], out)
    assert report.zeroshot is None and report.finetune is not None
    md = (out / "table2_finetune.md").read_text()
    table = md.split("### ")[0]
    assert md_columns(table) == ["dvfb", "dvfb_wo_map", "dvfb_wo_svf", "fb"]
    # last point of each curve: dvfb [500, 700] -> 600 ± 141.4
    assert md_row(table, "walker", "walker_walk") == ["600.0 ± 141.4", "150.0", "250.0", "–"]
    assert md_row(table, "walker", "walker_run") == ["–", "–", "–", "20.0"]
    assert md_row(md.split("### ")[1], "walker", "walker_walk")[0] == f"{60000 / 971:.1f} ± {14142.1356 / 971:.1f}"
    # the mixed budgets and the unfinished run are reported
    text = (out / "report.md").read_text()
    assert "different frame counts" in text and "unfinished" in text and "fb_s0" in text
    for name in ("finetune_walker_walk.png", "finetune_walker_run.png", "finetune_all.png"):
        assert_png_has_content(out / "curves" / name)
        assert f"curves/{name}" in text


def test_numbers_from_different_pretraining_budgets_are_different_cells(tmp_path: Path):
    root = tmp_path / "runs"
    make_pretrain_run(root / "dvfb_s0", seed=0, zeroshot={"walker_walk": 300.0}, snapshot_frames=1_200)
    make_pretrain_run(root / "dvfb_s1", seed=1, zeroshot={"walker_walk": 500.0})
    make_pretrain_run(root / "dvfb_s0_long", seed=0, zeroshot={"walker_walk": 700.0})  # seed 0 at both budgets
    make_pretrain_run(root / "fb_s0", agent="fb", seed=0, zeroshot={"walker_walk": 100.0})
    make_pretrain_run(root / "fb_s1", agent="fb", seed=1, zeroshot={"walker_walk": 200.0})
    for run in ("dvfb_s0", "dvfb_s1", "dvfb_s0_long"):
        make_finetune_run(root / run, "walker_walk", [(0, 10), (10_000, 40 if run == "dvfb_s0" else 60)])
    (root / "dvfb_s0" / "finetune" / "walker_walk" / "config.json").write_text(
        (root / "dvfb_s0" / "finetune" / "walker_walk" / "config.json").read_text().replace('"snapshot": 100000',
                                                                                            '"snapshot": 1200'))
    out = tmp_path / "out"
    report = make_report([root], out)
    short, long = "dvfb (1,200 frames)", "dvfb (100,000 frames)"
    table = report.zeroshot
    assert table.columns == [short, long, "fb"]  # one method's budgets side by side, the smaller first
    assert table.cell("walker", "walker_walk", short).mean == 300.0 and table.cell("walker", "walker_walk", short).n == 1
    assert table.cell("walker", "walker_walk", long).mean == 600.0 and table.cell("walker", "walker_walk", long).n == 2
    assert table.cell("walker", "walker_walk", "fb").mean == 150.0  # one budget: its plain name
    assert md_columns((out / "table1_zeroshot.md").read_text().split("### ")[0]) == [short, long, "fb"]
    assert report.finetune.columns == [short, long]
    assert report.finetune.cell("walker", "walker_walk", short).mean == 40.0
    assert report.finetune.cell("walker", "walker_walk", long).mean == 60.0
    assert {m for kind in report.aggregates.values() for scope in kind.scopes for m in scope.matrices} >= {short, long}
    notes = [n for n in report.notes if "pre-training budgets" in n]
    assert notes == [f"Table 1: dvfb on walker has runs of different pre-training budgets, each budget its own column "
                     f"({short}: 1 number(s), {long}: 2 number(s)); evaluate one snapshot (--snapshot) to compare "
                     "like with like",
                     f"Table 2: dvfb on walker has runs of different pre-training budgets, each budget its own column "
                     f"({short}: 1 number(s), {long}: 2 number(s)); evaluate one snapshot (--snapshot) to compare "
                     "like with like"]
    assert all(note in (out / "report.md").read_text() for note in notes)


def test_finetune_run_given_alone_takes_the_method_from_its_pretraining_run(tmp_path: Path):
    run = make_pretrain_run(tmp_path / "noce", use_ce=False)
    ft = make_finetune_run(run, "walker_flip", [(0, 50), (10000, 400)], eta=0.0)
    report = make_report([ft], tmp_path / "out")
    assert report.finetune.columns == ["dvfb_wo_ce_wo_svf"]
    assert report.finetune.cell("walker", "walker_flip", "dvfb_wo_ce_wo_svf").mean == 400.0


def test_curve_aggregation_uses_the_seeds_that_have_each_point():
    from dvfb.analysis.curves import aggregate

    band = aggregate([(np.array([0.0, 10.0, 20.0]), np.array([1.0, 3.0, 5.0])),
                      (np.array([0.0, 10.0]), np.array([3.0, 7.0]))])
    assert band.frames.tolist() == [0.0, 10.0, 20.0]
    assert band.mean.tolist() == [2.0, 5.0, 5.0]
    assert band.n.tolist() == [2, 2, 1]
    assert band.spread[0] == pytest.approx(np.std([1, 3], ddof=1)) and math.isnan(band.spread[2])
    se = aggregate([(np.array([0.0]), np.array([1.0])), (np.array([0.0]), np.array([3.0]))], spread="se")
    assert se.spread[0] == pytest.approx(np.std([1, 3], ddof=1) / math.sqrt(2))


# ---------------------------------------------------------------------------------------------
# Spearman and coverage on constructed data


def test_spearman_on_constructed_data():
    x = np.arange(12.0)
    assert spearman(x, x ** 3) == pytest.approx(1.0)
    assert spearman(x, -np.exp(x)) == pytest.approx(-1.0)
    assert math.isnan(spearman([1, 2], [1, 2])) and math.isnan(spearman([1, 1, 1], [1, 2, 3]))
    # Returns 0..11 in three bins of four; values rise across bins but fall inside each bin.
    returns = np.arange(12.0)
    values = np.array([100 * (i // 4) + (3 - i % 4) for i in range(12)], dtype=float)
    assert 0 < spearman(values, returns) < 1
    bins = binned_spearman(values, returns, 3)
    assert [b["n"] for b in bins] == [4, 4, 4]
    assert [(b["return_min"], b["return_max"]) for b in bins] == [(0, 3), (4, 7), (8, 11)]
    assert [b["spearman"] for b in bins] == pytest.approx([-1.0, -1.0, -1.0])
    # Bins are by rank of the return, whatever the input order; sizes differ by at most one.
    shuffled = np.random.default_rng(0).permutation(10).astype(float)
    parts = quantile_bins(shuffled, 3)
    assert sorted(len(p) for p in parts) == [3, 3, 4]
    assert [sorted(shuffled[p].tolist()) for p in parts] == [[0, 1, 2, 3], [4, 5, 6], [7, 8, 9]]


def test_coverage_counts_occupied_cells():
    points = np.array([[0.05, 0.05], [0.06, 0.07], [0.15, 0.05], [-0.01, 0.0], [0.15, 0.09]])
    assert coverage(points, 0.1) == 3  # cells (0, 0), (1, 0), (-1, 0)
    assert coverage(points, 1.0) == 2  # (0, 0) and (-1, 0)
    line = np.stack([np.linspace(0.005, 0.995, 100), np.zeros(100)], axis=1)
    assert coverage(line, 0.1) == 10
    assert coverage(np.zeros((0, 2)), 0.1) == 0
    trajectories = np.zeros((2, 3, 4, 1))  # (skills, repeats, steps, coordinates)
    trajectories[1] = 2.5
    assert coverage(trajectories, 1.0) == 2
    with pytest.raises(AnalysisError):
        coverage(points, 0.0)


# ---------------------------------------------------------------------------------------------
# end to end on a tiny pre-trained agent


@pytest.mark.slow
def test_analyze_value_end_to_end(dvfb_maze_run: Path, tmp_path: Path, capsys):
    run = copy_run(dvfb_maze_run, tmp_path)  # the analyses write into the run: on a copy
    args = ["analyze-value", str(run), "--task", MAZE_TASK, "--skills", "6", "--episodes-per-skill", "1",
            "--bins", "2", "--max-steps", "150", *FAST_INFERENCE]
    assert main(args) == 0
    assert "Spearman" in capsys.readouterr().out
    out = run / "analysis"
    summary = json.loads((out / f"value_{MAZE_TASK}.json").read_text())
    assert summary["trajectories"] == 6 and summary["skills"] == 6 and len(summary["bins"]) == 2
    assert summary["spearman"] is None or -1.0 <= summary["spearman"] <= 1.0
    rows = list(csv.DictReader(io.StringIO((out / f"value_{MAZE_TASK}.csv").read_text())))
    assert len(rows) == 6 and rows[0]["kind"] == "z_r" and rows[-1]["kind"] == "prior"
    assert all(math.isfinite(float(r["value"])) and int(r["steps"]) == 150 for r in rows)
    assert_png_has_content(out / f"value_{MAZE_TASK}.png")
    assert main(args) == 2  # not overwritten without --overwrite
    assert "--overwrite" in capsys.readouterr().err


def test_analyze_exploration_end_to_end(dvfb_maze_run: Path, tmp_path: Path, capsys, monkeypatch):
    run = copy_run(dvfb_maze_run, tmp_path)  # the analyses write into the run: on a copy
    monkeypatch.setenv("DVFB_PROGRESS_SECONDS", "0")  # off a terminal: a progress line at every step
    assert main(["analyze-exploration", str(run), "--skills", "3", "--repeats", "2", "--steps", "100"]) == 0
    captured = capsys.readouterr()
    assert "coverage" in captured.out
    progress = [line for line in captured.err.splitlines() if line.startswith("[analyze-exploration] ")]
    assert len(progress) == 600 and progress[-1].startswith("[analyze-exploration] 600/600 steps (100%)")
    out = run / "analysis"
    summary = json.loads((out / "exploration.json").read_text())
    assert summary["actions"] == "rollout" and summary["cell_size"] == 0.02
    assert summary["coordinates"] == ["x", "y"]
    positions = np.load(out / "exploration_positions.npz")["positions"]
    assert positions.shape == (3, 2, 101, 2) and np.isfinite(positions).all()
    assert summary["coverage_cells"] == coverage(positions, 0.02) >= 1
    assert len(summary["coverage_cells_per_skill"]) == 3
    # the maze start room is the top left: x < 0 < y at reset
    assert (positions[:, :, 0, 0] < 0).all() and (positions[:, :, 0, 1] > 0).all()
    assert_png_has_content(out / "exploration.png")


# ---------------------------------------------------------------------------------------------
# videos: OSMesa software rendering and the no-backend error, in subprocesses


def run_dvfb(args: list[str], **env: str) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    environment.update(env)
    return run_cli(*args, env=environment, timeout=300)


@pytest.mark.slow
def test_video_renders_with_osmesa(dvfb_maze_run: Path, tmp_path: Path):
    if ctypes.util.find_library("OSMesa") is None:
        pytest.fail("libOSMesa (software OpenGL) is not installed, so rendering cannot be tested: install it "
                    "with `apt-get install -y libosmesa6` (Debian/Ubuntu), or run `make test` as root, which does")
    gif = tmp_path / "maze.gif"
    result = run_dvfb(["video", str(dvfb_maze_run), "--task", MAZE_TASK, "--out", str(gif), "--max-steps", "30",
                       "--frame-skip", "3", "--height", "96", "--width", "128", *FAST_INFERENCE],
                      MUJOCO_GL="osmesa", PYOPENGL_PLATFORM="osmesa")
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    import imageio.v3 as iio

    frames = iio.imread(gif, index=None)
    # The reset frame + 30 / 3 frames were rendered (Pillow may merge identical consecutive frames).
    assert "1 episode(s), 11 frames" in result.stdout
    assert 1 <= frames.shape[0] <= 11 and frames.shape[1:] == (96, 128, 3)
    assert frames.std() > 1.0, "the video frames are one uniform colour"


@pytest.mark.parametrize("backend", ["disable", "no-such-backend"])
@pytest.mark.slow
def test_video_without_gl_backend_says_how_to_enable_one(dvfb_maze_run: Path, tmp_path: Path, backend: str):
    result = run_dvfb(["video", str(dvfb_maze_run), "--task", MAZE_TASK, "--out", str(tmp_path / "v.gif")],
                      MUJOCO_GL=backend)
    assert result.returncode == 2, result.stderr
    err = result.stderr
    assert "MUJOCO_GL=egl" in err and "MUJOCO_GL=osmesa" in err and "libosmesa6" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "v.gif").exists()


def test_video_format_checks(dvfb_maze_run: Path, tmp_path: Path, capsys):
    assert main(["video", str(dvfb_maze_run), "--task", MAZE_TASK, "--out", str(tmp_path / "v.avi")]) == 2
    assert ".gif" in capsys.readouterr().err
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        # MP4 needs imageio-ffmpeg: a clear message before any work, not a traceback.
        assert main(["video", str(dvfb_maze_run), "--task", MAZE_TASK, "--out", str(tmp_path / "v.mp4")]) == 2
        err = capsys.readouterr().err
        assert "imageio-ffmpeg" in err and ".gif" in err
    else:
        mp4 = tmp_path / "v.mp4"
        result = run_dvfb(["video", str(dvfb_maze_run), "--task", MAZE_TASK, "--out", str(mp4), "--max-steps", "20",
                           *FAST_INFERENCE], MUJOCO_GL="osmesa", PYOPENGL_PLATFORM="osmesa")
        assert result.returncode == 0, result.stderr
        assert mp4.stat().st_size > 0


def test_crosscheck_table_reads_dvfb_runs_harness_outputs_and_metrics(tmp_path, capsys):
    """scripts/crosscheck_table.py (docs/results/crosscheck_walker.md): per-seed task means, their
    average and the ddof=1 spread, from either kind of directory; metrics under dvfb's names."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("crosscheck_table",
                                                  Path(__file__).parents[1] / "scripts" / "crosscheck_table.py")
    table = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(table)
    for seed, (a, b) in enumerate([(10.0, 30.0), (20.0, 60.0)]):
        run = tmp_path / f"dvfb_s{seed}"
        (run / "zeroshot").mkdir(parents=True)
        (run / "zeroshot" / "t_a.json").write_text(json.dumps({"mean_return": a}))
        (run / "zeroshot" / "t_b.json").write_text(json.dumps({"mean_return": b}))
        (run / "metrics").mkdir()
        (run / "metrics" / "train.jsonl").write_text(
            "\n".join(json.dumps({"step": f, "ortho_loss": -seed - f / 1000}) for f in (1000, 2000)) + "\n")
        harness = tmp_path / f"authors_s{seed}"
        harness.mkdir()
        (harness / "zeroshot_t_a.json").write_text(json.dumps({"mean": a + 1}))
        (harness / "zeroshot_t_b.json").write_text(json.dumps({"mean": b + 1}))
        (harness / "log.txt").write_text("start\n  frames 1000 fps 3 orth_loss -5 intr_reward1 0.5\n"
                                         "  frames 2000 fps 3 orth_loss -7 intr_reward1 0.25\n")
    assert table.main(["--tasks", "t_a,t_b", f"dvfb={tmp_path}/dvfb_s?", f"authors={tmp_path}/authors_s?"]) == 0
    out = capsys.readouterr().out
    # Seed averages 20 and 40: mean 30, std (ddof=1) 14.1; the harness rows are 1 higher.
    assert "| dvfb | 2 | 15.0 ± 7.1 | 45.0 ± 21.2 | 30.0 ± 14.1 | 20.0, 40.0 |" in out
    assert "| authors | 2 | 16.0 ± 7.1 | 46.0 ± 21.2 | 31.0 ± 14.1 | 21.0, 41.0 |" in out
    assert table.main(["--metrics", "ortho_loss,rnd_reward", "--window", "1000:2000",
                       f"authors={tmp_path}/authors_s0", f"dvfb={tmp_path}/dvfb_s1"]) == 0
    out = capsys.readouterr().out
    assert "| authors | ortho_loss | -6 |" in out and "| authors | rnd_reward | 0.375 |" in out
    assert "| dvfb | ortho_loss | -2.5 |" in out and "| dvfb | rnd_reward | - |" in out
    with pytest.raises(SystemExit, match="no zero-shot result for t_c"):
        table.main(["--tasks", "t_a,t_c", f"dvfb={tmp_path}/dvfb_s0"])


# ---------------------------------------------------------------------------------------------
# zero-shot over the pre-training budget


def _budget_runs(root: Path) -> None:
    """dvfb and fb (3 seeds) at 50k and 100k frames on walk and run, the supervised reference
    (one seed per task) at both snapshots; min-max: random 0 and the final supervised 100, so
    the normalised scores are the returns."""
    at = {"dvfb": {50_000: ([10, 20, 30], [40, 50, 60]), 100_000: ([60, 70, 80], [90, 100, 110])},
          "fb": {50_000: ([5, 15, 25], [5, 15, 25]), 100_000: ([50, 60, 70], [50, 60, 70])}}
    for agent, snapshots in at.items():
        for seed in range(3):
            run = make_pretrain_run(root / f"{agent}_s{seed}", agent=agent, seed=seed, zeroshot={
                "walker_walk": snapshots[100_000][0][seed], "walker_run": snapshots[100_000][1][seed]})
            for task, values in zip(("walker_walk", "walker_run"), snapshots[50_000]):
                _earlier_result(run, task, 50_000, values[seed])
    for task, (early, final) in {"walker_walk": (50, 100), "walker_run": (60, 100)}.items():
        run = make_pretrain_run(root / f"supervised_{task}", agent="supervised", zeroshot={task: final})
        _earlier_result(run, task, 50_000, early)


def _earlier_result(run: Path, task: str, frames: int, value: float) -> None:
    config = json.loads((run / "config.json").read_text())
    write_json_atomic(run / "zeroshot" / f"{task}@{frames}.json", {
        "task": task, "domain": config["domain"], "agent": config["agent"], "preset": "small",
        "pretrain_seed": config["seed"], "seed": config["seed"], "snapshot_frames": frames, "mean_return": value,
        "std_return": 0.0, "returns": [value], "eval_episodes": 1, "z": [0.0] * 4})


def test_zeroshot_over_the_budget_iqm_ranking_and_probability_of_improvement(tmp_path: Path, capsys):
    root = tmp_path / "runs"
    _budget_runs(root)
    random_file = tmp_path / "random.json"
    write_json_atomic(random_file, {"domain": "walker", "seed": 0, "tasks": {
        t: {"mean_return": 0.0, "returns": [0.0]} for t in ("walker_walk", "walker_run")}})
    out = tmp_path / "report"
    assert main(["report", str(root), "--out", str(out), "--random", str(random_file),
                 "--bootstrap-samples", "200"]) == 0
    printed = capsys.readouterr().out
    rows = list(csv.DictReader(io.StringIO((out / "budget_zeroshot.csv").read_text())))
    iqm = {(r["method"], int(r["frames"])): float(r["value"]) for r in rows if r["metric"] == "iqm"}
    # IQM of 6 runs x tasks: the mean of the middle four.
    assert iqm == pytest.approx({("dvfb", 50_000): 35.0, ("dvfb", 100_000): 85.0, ("fb", 50_000): 15.0,
                                 ("fb", 100_000): 60.0, ("supervised (same frames)", 50_000): 55.0,
                                 ("supervised (same frames)", 100_000): 100.0})
    assert {r["normaliser"] for r in rows} == {"minmax"}
    bands = {(r["method"], int(r["frames"])): (r["low"], r["high"]) for r in rows if r["metric"] == "iqm"}
    assert all(bands[("dvfb", f)][0] and bands[("fb", f)][0] for f in (50_000, 100_000))
    assert bands[("supervised (same frames)", 50_000)] == ("", "")  # one run per task: no interval
    improvement = {(r["method"], int(r["frames"])): float(r["value"]) for r in rows
                   if r["metric"] == "probability_of_improvement"}
    # walk: 6 of 9 pairs, run: 9 of 9 at 50k; walk 7 of 9 (ties count a half), run 9 of 9 at 100k
    assert improvement[("dvfb > fb", 50_000)] == pytest.approx((6 / 9 + 1) / 2)
    assert improvement[("dvfb > fb", 100_000)] == pytest.approx((7 / 9 + 1) / 2)
    md = (out / "budget_zeroshot.md").read_text()
    assert "- 50,000 frames: supervised (same frames) > dvfb > fb" in md
    assert "- 100,000 frames: supervised (same frames) > dvfb > fb" in md
    assert "Table 1 at 50,000 pre-training frames: walker" in md
    assert md_row(md.split("Table 1 at 50,000")[1], "walker", "walker_walk")[:2] == ["20.0 ± 10.0", "15.0 ± 10.0"]
    assert "![Zero-shot over the pre-training budget](budget_zeroshot.png)" in (out / "report.md").read_text()
    assert_png_has_content(out / "budget_zeroshot.png")
    assert "## Zero-shot over the pre-training budget" in printed
    # The final table is unchanged by the earlier snapshots.
    assert md_row((out / "table1_zeroshot.md").read_text(), "walker", "walker_walk")[:2] == ["70.0 ± 10.0",
                                                                                              "60.0 ± 10.0"]


def test_a_maze_whose_reference_never_reached_its_goal_is_on_raw_returns_beside_a_min_max_walker(tmp_path: Path):
    """The report end to end: the maze's supervised reference returns 1e-125 (a goal it never
    reached), so the maze's aggregates and budget curves are raw returns while walker's stay
    min-max, and no aggregate adds the two."""
    root = tmp_path / "runs"
    _budget_runs(root)
    maze, task = "point_mass_maze", "point_mass_maze_reach_top_left"
    for agent, (early, final) in {"dvfb": ((0, 10, 20), (30, 40, 50)), "fb": ((0, 0, 0), (5, 5, 5))}.items():
        for seed in range(3):
            run = make_pretrain_run(root / f"{agent}_maze_s{seed}", agent=agent, domain=maze, seed=seed,
                                    zeroshot={task: float(final[seed])})
            _earlier_result(run, task, 50_000, float(early[seed]))
    reference = make_pretrain_run(root / "supervised_maze", agent="supervised", domain=maze, zeroshot={task: 1e-125})
    _earlier_result(reference, task, 50_000, 0.0)
    random_files = []
    for domain, tasks in (("walker", ("walker_walk", "walker_run")), (maze, (task,))):
        random_files.append(tmp_path / f"random_{domain}.json")
        write_json_atomic(random_files[-1], {"domain": domain, "seed": 0, "tasks": {
            t: {"mean_return": 0.0, "returns": [0.0]} for t in tasks}})
    out = tmp_path / "report"
    assert main(["report", str(root), "--out", str(out), "--random", *map(str, random_files),
                 "--bootstrap-samples", "200"]) == 0
    budget = list(csv.DictReader(io.StringIO((out / "budget_zeroshot.csv").read_text())))
    assert {(r["domain"], r["normaliser"]) for r in budget} == {("walker", "minmax"), (maze, "none")}
    iqm = {(r["domain"], r["method"], int(r["frames"])): float(r["value"]) for r in budget if r["metric"] == "iqm"}
    assert iqm[("walker", "dvfb", 100_000)] == pytest.approx(85.0)  # as on walker alone
    assert iqm[(maze, "dvfb", 50_000)] == pytest.approx(10.0) and iqm[(maze, "dvfb", 100_000)] == pytest.approx(40.0)
    aggregates = list(csv.DictReader(io.StringIO((out / "aggregates_zeroshot.csv").read_text())))
    assert {r["scope"] for r in aggregates} == {"walker", maze}  # no "all domains"
    assert {r["metric"] for r in aggregates if r["scope"] == maze} == {"iqm", "mean", "median",
                                                                       "probability_of_improvement"}
    assert "optimality_gap" in {r["metric"] for r in aggregates if r["scope"] == "walker"}
    md = (out / "budget_zeroshot.md").read_text()
    assert "On raw episode returns" in md.split(f"### {maze}")[1].split("### walker")[0]


def test_no_budget_section_without_earlier_snapshots(walker_runs: Path, tmp_path: Path):
    report = make_report([walker_runs], tmp_path / "out")
    assert report.budget is None and not (tmp_path / "out" / "budget_zeroshot.md").exists()
