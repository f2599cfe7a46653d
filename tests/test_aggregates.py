"""Aggregates with confidence intervals, normalised scores and the supervised reference
(docs/reports.md).

The statistics are checked against hand computations on planted score matrices; the coverage of
the intervals on synthetic data with a fixed seed (deterministic); the report on synthetic run
directories; the supervised reference end to end on the maze with a tiny network.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from dvfb.analysis import aggregate as agg, aggregate_report, normalise
from dvfb.analysis.common import AnalysisError, Score
from dvfb.analysis.report import make_report
from dvfb.cli import main
from dvfb.runs import write_json_atomic

from tiny import make_finetune_run, make_pretrain_run, md_row

WALKER = ("walker_stand", "walker_walk", "walker_run", "walker_flip")


# ---------------------------------------------------------------------------------------------
# statistics against hand computations


def test_iqm_median_mean_and_optimality_gap_of_a_planted_matrix():
    # 2 tasks x 4 runs; all 8 scores sorted: 0 10 20 30 | 100 110 120 130.
    matrix = agg.ScoreMatrix("m", ["a", "b"], [np.array([30.0, 0, 20, 10]), np.array([100.0, 130, 110, 120])])
    metrics = agg.aggregate_metrics(matrix)
    assert metrics["iqm"].value == pytest.approx((20 + 30 + 100 + 110) / 4)  # the middle 50%: 4 of 8
    assert metrics["mean"].value == pytest.approx(65.0)
    assert metrics["median"].value == pytest.approx((15 + 115) / 2)  # of the two task means
    # shortfall below 100: 100, 90, 80, 70 and four zeros
    assert metrics["optimality_gap"].value == pytest.approx((100 + 90 + 80 + 70) / 8)
    # 12 scores: IQM drops the lowest 3 and the highest 3.
    twelve = agg.ScoreMatrix("m", ["a"], [np.arange(12.0)])
    assert agg.aggregate_metrics(twelve)["iqm"].value == pytest.approx(np.mean(np.arange(3.0, 9.0)))


def test_the_median_is_the_median_of_the_task_means_not_of_all_scores():
    # Task means 0, 40 and 50: median 40. The median of all nine scores would be 10.
    matrix = agg.ScoreMatrix("m", ["a", "b", "c"], [np.zeros(3), np.array([10.0, 10, 100]), np.full(3, 50.0)])
    metrics = agg.aggregate_metrics(matrix)
    assert metrics["median"].value == pytest.approx(40.0)
    assert metrics["median"].low <= 40.0 <= metrics["median"].high
    # With unequal runs per task the mean is the mean of the task means, as rliable's.
    unequal = agg.ScoreMatrix("m", ["a", "b"], [np.array([0.0, 0, 0, 0]), np.array([100.0])])
    assert agg.aggregate_metrics(unequal)["mean"].value == pytest.approx(50.0)


@pytest.mark.filterwarnings("ignore::FutureWarning")  # arch's note about its own random_state argument
def test_every_aggregate_and_interval_equals_rliables():
    """rliable 1.2.0 (the ``stats`` extra, which ``make install`` installs) on the same score
    matrix: the point estimates equal to rounding, on rliable's scale (scores / 100, gamma 1); the
    intervals, from two different bootstrap implementations, agree to a small fraction of their
    width (both percentile intervals of a stratified bootstrap, 20000 resamples each)."""
    rliable_metrics = pytest.importorskip("rliable.metrics", reason="the rliable comparison needs the stats extra")
    from rliable import library

    rng = np.random.default_rng(5)
    runs, tasks = 5, 6
    scores = rng.gamma(2.0, 30.0, size=(runs, tasks)) + rng.normal(0, 20, size=(1, tasks))
    other = scores + rng.normal(5, 25, size=(runs, tasks))
    matrix = agg.ScoreMatrix("x", [f"t{i}" for i in range(tasks)], [scores[:, i] for i in range(tasks)])
    theirs = {"iqm": rliable_metrics.aggregate_iqm, "mean": rliable_metrics.aggregate_mean,
              "median": rliable_metrics.aggregate_median, "optimality_gap": rliable_metrics.aggregate_optimality_gap}
    ours = agg.aggregate_metrics(matrix, samples=20000, seed=1)
    points, intervals = library.get_interval_estimates(
        {"x": scores / 100.0}, lambda x: np.array([theirs[m](x) for m in agg.METRICS]), reps=20000,
        random_state=np.random.RandomState(1))
    for i, name in enumerate(agg.METRICS):
        estimate = ours[name]
        assert estimate.value == pytest.approx(100.0 * points["x"][i], rel=1e-9, abs=1e-9), name
        width = estimate.high - estimate.low
        assert width > 0, name
        for mine, rliables in ((estimate.low, intervals["x"][0, i]), (estimate.high, intervals["x"][1, i])):
            assert abs(mine - 100.0 * rliables) < 0.1 * width, (name, mine, 100.0 * rliables)
    # P(X > Y): rliable's is the same Mann-Whitney average over tasks.
    y = agg.ScoreMatrix("y", matrix.tasks, [other[:, i] for i in range(tasks)])
    assert agg.probability_of_improvement(matrix, y).value == pytest.approx(
        rliable_metrics.probability_of_improvement(scores, other))


def test_stratified_bootstrap_resamples_each_task_on_its_own():
    # Task a's runs are 0 and 10, task b's are both 20. A resample's pooled mean is
    # (2 m_a + 40) / 4 with m_a in {0, 5, 10} (probabilities 1/4, 1/2, 1/4): 10, 12.5 or 15. The
    # 95% percentile interval is therefore exactly [10, 15]; pooling the tasks (no strata) would
    # also draw means such as 5 (all four draws 0 or 10) or 20.
    low, high = agg.stratified_interval([np.array([0.0, 10.0]), np.array([20.0, 20.0])],
                                        lambda *c, axis=-1: np.mean(np.concatenate(c, axis=axis), axis=axis),
                                        samples=4000, seed=3)
    assert (float(low), float(high)) == (10.0, 15.0)
    # Tasks that are constant within themselves give an interval of width zero, whatever the
    # spread between tasks.
    constant = agg.ScoreMatrix("m", ["a", "b", "c"], [np.full(3, 0.0), np.full(3, 50.0), np.full(3, 100.0)])
    for estimate in agg.aggregate_metrics(constant).values():
        assert estimate.low == estimate.value == estimate.high


def test_bootstrap_is_seeded():
    rng = np.random.default_rng(7)
    matrix = agg.ScoreMatrix("m", ["a", "b"], [rng.normal(size=5), rng.normal(size=5)])
    first = agg.aggregate_metrics(matrix, seed=11)
    assert agg.aggregate_metrics(matrix, seed=11) == first
    assert agg.aggregate_metrics(matrix, seed=12)["iqm"] != first["iqm"]


def test_probability_of_improvement_by_hand():
    # One task: x = 1, 2, 3 against y = 2, 2, 0. Pairs won: 1 beats 0 (1); 2 ties 2 twice and beats
    # 0 (0.5 + 0.5 + 1); 3 beats all (3): (1 + 2 + 3) / 9.
    x = agg.ScoreMatrix("x", ["t"], [np.array([1.0, 2.0, 3.0])])
    y = agg.ScoreMatrix("y", ["t"], [np.array([2.0, 2.0, 0.0])])
    assert agg.probability_of_improvement(x, y).value == pytest.approx(6 / 9)
    assert agg.probability_of_improvement(y, x).value == pytest.approx(3 / 9)
    # Averaged over tasks: a second task that x always wins.
    x2 = agg.ScoreMatrix("x", ["t", "u"], [np.array([1.0, 2.0, 3.0]), np.array([9.0, 9.0, 9.0])])
    y2 = agg.ScoreMatrix("y", ["t", "u"], [np.array([2.0, 2.0, 0.0]), np.array([1.0, 1.0, 1.0])])
    estimate = agg.probability_of_improvement(x2, y2)
    assert estimate.value == pytest.approx((6 / 9 + 1) / 2)
    assert estimate.low <= estimate.value <= estimate.high and estimate.high <= 1.0


def test_performance_profile_by_hand():
    matrix = agg.ScoreMatrix("m", ["a", "b"], [np.array([0.0, 10, 20, 30]), np.array([100.0, 110, 120, 130])])
    profile = agg.performance_profile(matrix, np.array([-1.0, 0.0, 50.0, 115.0, 200.0]))
    assert profile.fraction.tolist() == [1.0, 7 / 8, 0.5, 2 / 8, 0.0]  # strictly above tau
    # tau = 50 separates the tasks: every stratified resample keeps 4 of 8 above it.
    assert profile.low[2] == profile.high[2] == 0.5
    assert np.all(profile.low <= profile.fraction) and np.all(profile.fraction <= profile.high)


def test_too_few_runs_give_no_interval():
    matrix = agg.ScoreMatrix("m", ["a", "b"], [np.array([1.0, 2.0]), np.array([3.0, 4.0, 5.0])])
    assert not matrix.can_bootstrap
    assert all(not e.has_interval for e in agg.aggregate_metrics(matrix).values())
    assert agg.mean_interval(np.array([1.0, 2.0])).low is None


@pytest.mark.slow
def test_intervals_cover_the_truth_at_about_the_nominal_rate():
    # 400 synthetic experiments of 4 tasks x 10 runs, scores N(mu_t, 10^2): the 95% interval of
    # the mean should contain the true mean (the mean of the mu_t) in about 95% of them, and the
    # IQM's interval the true IQM of identical symmetric tasks (their centre). Fixed seeds: the
    # same count every time; percentile intervals of small samples are a little narrow, so the
    # accepted band is 0.90-0.98.
    rng = np.random.default_rng(2021)
    mus = np.array([10.0, 40.0, 60.0, 90.0])
    hits_mean = hits_iqm = 0
    trials = 400
    for trial in range(trials):
        columns = [rng.normal(mu, 10.0, size=10) for mu in mus]
        mean = agg.aggregate_metrics(agg.ScoreMatrix("m", list("abcd"), columns), samples=1000, seed=trial)["mean"]
        hits_mean += mean.low <= mus.mean() <= mean.high
        same = [rng.normal(50.0, 10.0, size=10) for _ in mus]
        iqm = agg.aggregate_metrics(agg.ScoreMatrix("m", list("abcd"), same), samples=1000, seed=trial)["iqm"]
        hits_iqm += iqm.low <= 50.0 <= iqm.high
    assert 0.90 <= hits_mean / trials <= 0.98, hits_mean
    assert 0.90 <= hits_iqm / trials <= 0.98, hits_iqm


# ---------------------------------------------------------------------------------------------
# reports


def _walker_method(root: Path, agent: str, values: dict[int, dict[str, float]]) -> None:
    for seed, per_task in values.items():
        make_pretrain_run(root / f"{agent}_s{seed}", agent=agent, seed=seed, zeroshot=per_task)


def _supervised(root: Path, per_task: dict[str, list[float]]) -> None:
    for task, values in per_task.items():
        for seed, value in enumerate(values):
            path = make_pretrain_run(root / f"supervised_{task}_s{seed}", agent="supervised", seed=seed,
                                     zeroshot={task: value})
            config = json.loads((path / "config.json").read_text())
            config["supervised"]["task"] = task
            (path / "config.json").write_text(json.dumps(config))  # still a valid, strictly loaded run config


def _random_file(path: Path, per_task: dict[str, float]) -> Path:
    write_json_atomic(path, {"agent": "random", "domain": "walker", "seed": 0, "episodes": 2, "tasks": {
        t: {"mean_return": v, "std_return": 0.0, "returns": [v, v]} for t, v in per_task.items()}})
    return path


@pytest.fixture
def compared(tmp_path: Path) -> tuple[Path, Path]:
    """dvfb and fb with 3 seeds on the 4 walker tasks, a supervised reference (3 seeds per task)
    and a random-policy file, with known numbers."""
    root = tmp_path / "runs"
    _walker_method(root, "dvfb", {s: {t: 300.0 + 100 * s + 10 * i for i, t in enumerate(WALKER)} for s in range(3)})
    _walker_method(root, "fb", {s: {t: 100.0 + 50 * s for t in WALKER} for s in range(3)})
    _supervised(root, {t: [500.0, 600.0, 700.0] for t in WALKER})  # mean 600
    return root, _random_file(tmp_path / "random.json", {t: 100.0 for t in WALKER})


def test_report_normalises_by_the_supervised_reference_and_min_max(compared, tmp_path: Path):
    root, random_file = compared
    out = tmp_path / "report"
    report = make_report([root], out, random_files=[random_file])
    table = report.zeroshot
    assert table.columns == ["dvfb", "fb", "supervised", "random"]
    # dvfb on walker_stand: seeds 300, 400, 500; supervised mean 600, random 100.
    assert table.cell("walker", "walker_stand", "dvfb", "supervised").mean == pytest.approx(100 * 400 / 600)
    assert table.cell("walker", "walker_stand", "dvfb", "minmax").mean == pytest.approx(100 * (400 - 100) / 500)
    assert table.cell("walker", "walker_stand", "supervised", "minmax").mean == pytest.approx(100.0)
    assert table.cell("walker", "walker_stand", "random", "minmax").mean == pytest.approx(0.0)
    md = (out / "table1_zeroshot.md").read_text()
    assert "percent of the supervised reference" in md and "min-max score" in md
    assert "dvfb 3 seeds × 1 episodes" in md and "random 1 seed × 2 episodes" in md
    assert (out / "table1_zeroshot_minmax.csv").is_file() and (out / "table1_zeroshot_supervised.csv").is_file()

    # The aggregates use min-max scores (both references exist) over the 12 runs x tasks.
    aggregates = report.aggregates["zeroshot"]
    assert aggregates.normaliser.name == "minmax"
    (scope,) = aggregates.scopes
    dvfb = np.array([(300 + 100 * s + 10 * i - 100) / 5 for s in range(3) for i in range(4)])
    metrics = scope.metrics["dvfb"]
    assert metrics["mean"].value == pytest.approx(dvfb.mean())
    assert metrics["iqm"].value == pytest.approx(np.mean(np.sort(dvfb)[3:9]))
    assert metrics["mean"].low < metrics["mean"].value < metrics["mean"].high
    assert scope.improvement[("dvfb", "fb")].value == pytest.approx(1.0)  # every dvfb run beats every fb run
    assert "supervised" not in scope.metrics and "random" not in scope.metrics
    text = (out / "aggregates_zeroshot.md").read_text()
    assert "stratified bootstrap" in text and "P(row > column)" in text and "min-max" in text
    rows = (out / "aggregates_zeroshot.csv").read_text().splitlines()
    assert rows[0].startswith("scope,method,metric,value,low,high")
    assert any(r.startswith("walker,dvfb > fb,probability_of_improvement,1.0") for r in rows)
    # The performance-profile figure is a real, non-empty PNG.
    png = out / "profiles_zeroshot.png"
    assert png.stat().st_size > 5000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "profiles_zeroshot.png" in (out / "report.md").read_text()


def test_a_missing_reference_is_a_clear_message_and_writes_nothing(tmp_path: Path, capsys):
    root = tmp_path / "runs"
    _walker_method(root, "dvfb", {s: {t: 100.0 for t in WALKER} for s in range(3)})
    out = tmp_path / "report"
    with pytest.raises(AnalysisError, match=r"no supervised reference for walker_flip, walker_run.*dvfb supervised"):
        make_report([root], out, normaliser="supervised")
    assert not out.exists()
    assert main(["report", str(root), "--out", str(out), "--normaliser", "minmax"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "dvfb supervised --task" in err and "--random" in err
    assert not out.exists()
    # auto falls back to the expert normaliser and says why.
    report = make_report([root], out)
    assert report.aggregates["zeroshot"].normaliser.name == "expert"
    assert any("no supervised reference" in note for note in report.notes)


def test_fewer_than_three_runs_say_intervals_are_not_meaningful(tmp_path: Path):
    root = tmp_path / "runs"
    _walker_method(root, "dvfb", {s: {t: 100.0 * (s + 1) for t in WALKER} for s in range(2)})
    report = make_report([root], tmp_path / "report", normaliser="expert")
    (scope,) = report.aggregates["zeroshot"].scopes
    assert not any(e.has_interval for e in scope.metrics["dvfb"].values())
    assert any("not meaningful" in note for note in report.notes)
    text = (tmp_path / "report" / "aggregates_zeroshot.md").read_text()
    assert "dvfb 2 runs/task" in text and "[" not in md_row(text.replace("| dvfb |", "| walker | dvfb |"),
                                                            "walker", "dvfb")[0]


def test_finetuning_curves_have_bootstrap_bands(tmp_path: Path):
    from dvfb.analysis.curves import aggregate

    curves = [(np.array([0.0, 10.0]), np.array([v, 2 * v])) for v in (1.0, 2.0, 3.0, 4.0)]
    band = aggregate(curves, spread="ci")
    assert band.mean.tolist() == [2.5, 5.0]
    assert band.low[0] < 2.5 < band.high[0] and band.low[1] < 5.0 < band.high[1]
    assert np.all(np.isnan(aggregate(curves[:2], spread="ci").low))  # two seeds: no band


def test_finetuning_aggregates_name_their_normaliser_without_asking_for_a_supervised_run(compared, tmp_path: Path):
    """The supervised reference normalises zero-shot results: with it in the report, the fine-tuning
    aggregates use the URLB expert returns, and the note says so instead of asking for the runs it has."""
    root, random_file = compared
    for seed in range(3):
        make_finetune_run(root / f"dvfb_s{seed}", "walker_walk", [(0, 10.0), (20_000, 300.0 + seed)])
        make_finetune_run(root / f"fb_s{seed}", "walker_walk", [(0, 10.0), (20_000, 100.0 + seed)])
    report = make_report([root], tmp_path / "report", random_files=[random_file])
    assert report.aggregates["zeroshot"].normaliser.name == "minmax"
    finetune = report.aggregates["finetune"]
    assert finetune.normaliser.name == "expert"
    assert finetune.notes == ["fine-tuning aggregates use the expert normaliser (the supervised reference "
                              "normalises zero-shot results only)"]
    assert not any("dvfb supervised" in note for note in report.notes)


# ---------------------------------------------------------------------------------------------
# the supervised reference


@pytest.mark.slow
def test_supervised_reference_trains_on_its_task_and_is_evaluated_on_it_only(tmp_path: Path, capsys):
    import torch

    from dvfb.agents import make_agent
    from dvfb.core.config import merge
    from dvfb.workflows.pretrain import pretrain
    from dvfb.workflows.zeroshot import zeroshot
    from dvfb.core.errors import ConfigError
    from tiny import filled_replay, tiny_run_config

    task = "point_mass_maze_reach_bottom_right"
    config = merge(tiny_run_config("supervised", frames=1500), {"supervised": {"task": task}})
    # Its learner's reward is the batch's own n-step task reward.
    agent = make_agent("supervised", 4, 2, config, "cpu")
    replay = filled_replay(agent)
    batch = agent.replay_needs().sample(replay)
    assert torch.equal(agent.intrinsic.score(batch), batch.reward)

    run = pretrain(config, tmp_path / "sup", progress=False)
    # The replay stored the task's rewards: the episode returns logged are those of the task.
    episodes = [json.loads(line) for line in (run.path / "metrics" / "episode.jsonl").read_text().splitlines()]
    assert episodes and all("episode_task_reward" in e for e in episodes)
    with pytest.raises(ConfigError, match=f"learned '{task}'; it is evaluated on that task only"):
        zeroshot(run.path, "point_mass_maze_reach_top_left", inference={"eval_episodes": 1})
    result = zeroshot(run.path, task, inference={"eval_episodes": 1})
    assert result["agent"] == "supervised" and result["protocol"] == "single_policy"
    # `--task all` is its own task; the CLI refuses another one with one line.
    assert main(["zeroshot", str(run.path), "--task", "all", "--overwrite"]) == 0
    capsys.readouterr()
    assert main(["zeroshot", str(run.path), "--task", "point_mass_maze_reach_top_left"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_dvfb_supervised_command_trains_and_evaluates(tmp_path: Path, capsys):
    run = tmp_path / "sup"
    assert main(["supervised", "--task", "point_mass_maze_reach_top_right", "--run-dir", str(run), "--frames", "600",
                 "--seed-frames", "300", "--update-every", "4", "--ddpg.hidden-dim", "32", "--ddpg.batch-size", "32",
                 "--inference.eval-episodes", "1", "--no-progress", "--torch-threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "point_mass_maze_reach_top_right return" in out
    config = json.loads((run / "config.json").read_text())
    assert config["agent"] == "supervised" and config["domain"] == "point_mass_maze"
    assert config["supervised"]["task"] == "point_mass_maze_reach_top_right"
    assert json.loads((run / "zeroshot" / "point_mass_maze_reach_top_right.json").read_text())["eval_episodes"] == 1
    # A bad task is one line and creates nothing.
    assert main(["supervised", "--task", "walker_moonwalk", "--run-dir", str(tmp_path / "bad")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()


def test_sweeps_give_the_supervised_reference_a_cell_per_task():
    from dvfb.sweep import spec

    config = spec.build({}, {"agents": ["fb", "supervised"], "domains": ["walker"], "seeds": [0, 1],
                             "zeroshot_tasks": ["walker_walk", "walker_run"], "overrides": {"frames": 6000}}, {}, {})
    cells = {c.name: c for c in spec.cells(config)}
    assert set(cells) == {"fb_walker_s0", "fb_walker_s1", *(f"supervised_{t}_s{s}" for t, s in
                                                             itertools.product(("walker_walk", "walker_run"), (0, 1)))}
    cell = cells["supervised_walker_run_s1"]
    assert spec.pretrain_flags(cell) == ["--frames", "6000", "--supervised.task", "walker_run"]
    assert spec.zeroshot_tasks(config, cell) == ["walker_run"]
    assert spec.cell_config(config, cell).supervised.task == "walker_run"
    assert spec.zeroshot_tasks(config, cells["fb_walker_s0"]) == ["walker_walk", "walker_run"]
    from dvfb.core.errors import ConfigError

    with pytest.raises(ConfigError, match="set by the sweep itself"):
        spec.build({}, {"agents": ["supervised"], "overrides": {"supervised.task": "walker_run"}}, {}, {})


def test_a_reference_that_never_reached_the_goal_normalises_nothing():
    """A supervised agent that never reaches a maze goal still returns float dust (1e-125, a Gaussian
    tolerance far from the goal): min-max must not divide a baseline's 1e-60 by it."""
    def score(method: str, task: str, value: float) -> Score:
        return Score("zeroshot", method, "point_mass_maze", task, 0, value, Path("x.json"))

    scores = [score("supervised", "reached", 900.0), score("random", "reached", 0.0),
              score("supervised", "never", 1e-125), score("random", "never", 0.0),
              score("cic", "never", 1e-60)]
    available = normalise.normalisers(scores)
    minmax = available["minmax"]
    assert minmax.covers("reached") and minmax("reached", 450.0) == pytest.approx(50.0)
    assert not minmax.covers("never") and minmax.uncovered(["reached", "never"]) == ["never"]
    assert normalise.choose("auto", ["reached", "never"], available) is None  # raw returns instead
    with pytest.raises(AnalysisError, match=r"^the minmax reference is less than 0.01 above its floor on never"):
        normalise.choose("minmax", ["reached", "never"], available)


def test_each_domain_takes_the_normaliser_that_covers_its_own_tasks():
    """Walker has a supervised reference above random on every task; the maze's reference never
    reached two goals. Walker stays min-max, the maze falls to raw returns (without an optimality
    gap, which is a shortfall below a normaliser's 100), and no all-domain aggregate mixes them."""
    def score(method: str, domain: str, task: str, seed: int, value: float) -> Score:
        return Score("zeroshot", method, domain, task, seed, value, Path(f"{method}{seed}.json"))

    scores = []
    for task in ("walker_walk", "walker_run"):
        scores += [score("supervised", "walker", task, 0, 500.0), score("random", "walker", task, 0, 100.0)]
        scores += [score("dvfb", "walker", task, s, 100.0 + 100.0 * s) for s in range(3)]
    for task, reference in (("maze_a", 900.0), ("maze_b", 1e-125)):
        scores += [score("supervised", "maze", task, 0, reference), score("random", "maze", task, 0, 0.0)]
        scores += [score("dvfb", "maze", task, s, 10.0 * s) for s in range(3)]
    result = aggregate_report.compute(scores, "zeroshot", "Table 1", bootstrap=aggregate_report.BootstrapConfig(200))
    scopes = {scope.name: scope for scope in result.scopes}
    assert sorted(scopes) == ["maze", "walker"] and result.normaliser is None and not result.uniform
    assert scopes["walker"].normaliser.name == "minmax" and scopes["maze"].normaliser is None
    # walker min-max: (100, 200, 300) -> 0, 25, 50 on both tasks; the maze's raw returns 0, 10, 20
    assert scopes["walker"].metrics["dvfb"]["mean"].value == pytest.approx(25.0)
    assert scopes["maze"].metrics["dvfb"]["mean"].value == pytest.approx(10.0)
    assert "no aggregate over all domains: their scores are on different scales (walker: minmax, maze: raw " \
           "episode returns)" in result.notes
    md = aggregate_report.markdown(result, aggregate_report.BootstrapConfig(200), None)
    maze = md.split("### maze")[1].split("### walker")[0]
    assert "On raw episode returns" in maze and "| method | IQM | mean | median |\n" in maze
    assert "On the minmax normaliser" in md.split("### walker")[1] and "optimality gap" in md.split("### walker")[1]
    assert {row.split(",")[2] for row in aggregate_report.to_csv(result).splitlines()[1:]
            if row.startswith("maze,dvfb,")} == {"iqm", "mean", "median"}
