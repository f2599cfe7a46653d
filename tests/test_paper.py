"""The paper-reproduction kit: the published numbers shipped as package data, ``dvfb report --paper``
and the sweep files of sweeps/paper/ with ``dvfb sweep run --dry-run`` (docs/reproduce.md).

The report tests write synthetic run directories with known returns (the helpers of
tests/test_analysis.py) and check every number of the comparison against a hand computation.
"""

from __future__ import annotations

import csv
import fnmatch
import io
import json
import tomllib
from pathlib import Path

import pytest

from dvfb.analysis import paper
from dvfb.analysis.common import AnalysisError, Score, method_name
from dvfb.analysis.report import make_report
from dvfb.cli import main
from dvfb.analysis.tables import build_table
from dvfb.core.config import merge, save_json, to_dict
from dvfb.envs.registry import tasks_of_domain
from dvfb.core.errors import ConfigError
from dvfb.runs import write_json_atomic
from dvfb.runs.presets import preset_config
from dvfb.protocols import protocols_of
from dvfb.runs.run_config import FinetuneRunConfig
from dvfb.sweep import runner, spec

from tiny import make_finetune_run, make_pretrain_run

ROOT = Path(__file__).resolve().parents[1]
PAPER_SWEEPS = sorted((ROOT / "sweeps" / "paper").glob("*.toml"))
WALKER = tasks_of_domain("walker")
QUADRUPED = tasks_of_domain("quadruped")


def cells_by_key() -> dict[tuple[int, str, str, str], paper.PaperCell]:
    return {(c.table, c.domain, c.task, c.paper_name): c for c in paper.load_paper_tables().cells}


def comparison_rows(path: Path) -> dict[tuple[str, str, str, str, str], dict[str, str]]:
    """The rows of paper_comparison.csv by (table, domain, task, paper_name, method)."""
    rows = list(csv.DictReader(io.StringIO(path.read_text())))
    keyed = {(r["table"], r["domain"], r["task"], r["paper_name"], r["method"]): r for r in rows}
    assert len(keyed) == len(rows)
    return keyed


# ---------------------------------------------------------------------------------------------
# the published numbers


def test_every_cell_of_the_papers_tables_is_package_data():
    tables = paper.load_paper_tables()
    cells = cells_by_key()
    assert len(tables.cells) == len(cells) == 691
    counts = {t: sum(c.table == t for c in tables.cells) for t in (1, 2, 5, 6, 7, 8, 9, 10, 11, 12)}
    assert counts == {1: 150, 2: 150, 5: 213, 6: 38, 7: 25, 8: 20, 9: 25, 10: 25, 11: 25, 12: 20}
    dvfb = cells[(1, "walker", "stand", "DVFB")]
    assert (dvfb.kind, dvfb.mean, dvfb.std, dvfb.seeds, dvfb.report_task) == ("zero_shot", 905, 27, 6, "walker_stand")
    assert cells[(2, "hopper", "hop_backward", "DVFB")].mean == 273 and cells[(2, "hopper", "hop", "RND")].std == 12
    assert cells[(1, "hopper", "hop_backward", "LRA-SR")].std == 5  # larger than its mean, as printed
    faucet = cells[(6, "metaworld", "faucet_open", "DVFB")]
    assert (faucet.mean, faucet.std, faucet.seeds, faucet.metric) == (0.6, None, None, "success_rate")
    assert cells[(6, "point_mass_maze", "reach_top_left", "DVFB")].report_task == "point_mass_maze_reach_top_left"
    assert cells[(5, "all", "average", "LRA-P (Proto)")].mean == 326.5
    assert cells[(5, "all", "average_of_best", "Offline FB")].mean == 647
    assert cells[(7, "walker", "stand", "β=0.5")].std is None and cells[(11, "walker", "stand", "β=0.5")].std == 27
    assert cells[(12, "quadruped", "average", "η=1.0")].report_kind == "finetune"
    assert cells[(9, "quadruped", "walk", "DVFB w/o MAP (adaptive η)")].mean == 820
    # The four averages the paper prints inconsistently keep their printed value and say so.
    fb = cells[(1, "quadruped", "average", "FB")]
    assert fb.mean == 638 and "629" in fb.note
    for table in (2, 9):
        quadruped = cells[(table, "quadruped", "average", "DVFB")]
        assert quadruped.mean == 804 and quadruped.report_kind == "finetune"
    assert "810" in cells[(2, "quadruped", "average", "DVFB")].note
    assert cells[(6, "point_mass_maze", "average", "FB-offline")].mean == 219
    assert "does not match" in cells[(6, "point_mass_maze", "average", "FB-offline")].note


def test_every_paper_column_maps_to_the_dvfb_method_and_flags_that_make_it():
    tables = paper.load_paper_tables()
    domains: dict[tuple[int, str], set[str]] = {}
    for cell in tables.cells:
        if cell.domain != "all":
            domains.setdefault((cell.table, cell.paper_name), set()).add(cell.domain)
    for key, method in tables.methods.items():
        assert method.sweeps and all((ROOT / "sweeps" / "paper" / s).is_file() for s in method.sweeps), key
        if not method.agent:  # Table 5's "Average of best" of a family
            assert key[0] == 5 and key[1] in ("LAP", "LRA-P", "LRA-SR", "Offline FB")
            continue
        kind = "finetune" if key[0] in (2, 9, 12) else "zeroshot"
        for domain in domains[key]:
            # The declared column is the label a run of the flags gets at preset paper, and the flags
            # make a valid config of preset code too.
            assert method.label("paper", domain, kind) == method.method.replace("{domain}", domain), key
            assert method.label("code", domain, kind) is not None, key
    m = tables.methods
    assert (m[(8, "DVFB(CIC)")].agent, m[(8, "DVFB(CIC)")].flags) == ("dvfb", ("--exploration.reward", "cic"))
    assert m[(10, "α=3")].flags == ("--exploration.alpha", "3") and m[(10, "α=3")].method == "dvfb_alpha3"
    assert m[(10, "α=5")].label("code", "walker", "zeroshot") == "dvfb_alpha5"  # preset code's alpha is 50
    assert m[(1, "DVFB")].label("code", "walker", "zeroshot") == "dvfb"
    wo_map = m[(9, "DVFB w/o MAP (η=0.02)")]
    assert wo_map.flags == ("--finetune.reward-mapping", "false", "--finetune.eta", "0.02")
    assert wo_map.label("paper", "quadruped", "finetune") == "dvfb_wo_map_eta0.02"
    assert m[(9, "DVFB w/o MAP (adaptive η)")].method == "dvfb_wo_map_eta_adaptive"
    assert m[(1, "Lap")].flags == ("--sf.features", "lap") and m[(1, "Lap")].method == "SF-Lap"
    assert m[(5, "Offline FB (RND)")].label("paper", "cheetah", "zeroshot") == "fb@rnd_cheetah"
    assert m[(6, "MCFB-offline")].label("code", "point_mass_maze", "zeroshot") == "mcfb@rnd_point_mass_maze"
    assert m[(12, "η=1.0")].label("code", "quadruped", "finetune") == "dvfb"  # preset code's eta is 1


def test_coefficients_away_from_the_preset_name_their_own_column():
    paper_preset, code = preset_config("paper", agent="dvfb"), preset_config("code", agent="dvfb")
    assert method_name(paper_preset) == method_name(code) == "dvfb"
    assert method_name(merge(paper_preset, {"exploration": {"alpha": 3.0}})) == "dvfb_alpha3"
    assert method_name(merge(code, {"exploration": {"alpha": 5.0}})) == "dvfb_alpha5"
    assert method_name(merge(paper_preset, {"exploration": {"beta": 0.7, "alpha_mode": "adaptive"}})) \
        == "dvfb_alpha_adaptive_beta0.7"
    # Fine-tuning coefficients name fine-tuning columns only, against the preset's value.
    eta = merge(paper_preset, {"finetune": {"eta": 0.02}})
    assert method_name(eta) == "dvfb" and method_name(eta, eta.finetune) == "dvfb_eta0.02"
    assert method_name(code, code.finetune) == "dvfb" and method_name(code, paper_preset.finetune) == "dvfb_eta0.5_qf1"
    # A value the registry's own label names adds nothing: eta 0 is w/o SVF.
    assert method_name(paper_preset, merge(paper_preset.finetune, {"eta": 0.0})) == "dvfb_wo_svf"
    # Run configs read back as dicts, and old ones without a preset, label the same way.
    assert method_name(to_dict(merge(paper_preset, {"exploration": {"alpha": 3.0}}))) == "dvfb_alpha3"
    assert method_name({"agent": "dvfb", "exploration": {"alpha": 3.0}}) == "dvfb"


def test_the_tables_ship_as_package_data():
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["dvfb"]
    files = sorted(p.name for p in (ROOT / "src" / "dvfb" / "data" / "paper_tables").glob("*.csv"))
    assert files == ["cells.csv", "methods.csv"]
    for name in files:
        assert any(fnmatch.fnmatch(f"data/paper_tables/{name}", p) for p in patterns), name


CELLS_HEAD = "table,kind,domain,task,paper_name,mean,std,seeds,note\n"
METHODS_HEAD = "table,paper_name,agent,flags,method,sweep,note\n"


@pytest.mark.parametrize("parse, text, words", [
    (paper.parse_cells, "table,kind,domain,task,mean\n1,zero_shot,walker,stand,1\n", "expected the columns"),
    (paper.parse_cells, CELLS_HEAD + "1,later,walker,stand,FB,1,,,\n", "kind must be one of"),
    (paper.parse_cells, CELLS_HEAD + "1,zero_shot,walker,stand,FB,many,,,\n", "mean 'many' is not a number"),
    (paper.parse_cells, CELLS_HEAD + "1,zero_shot,walker,stand,FB,nan,,,\n", "not finite"),
    (paper.parse_cells, CELLS_HEAD + "1,zero_shot,walker,stand,FB,,,,\n", "needs a value"),
    (paper.parse_cells, CELLS_HEAD + "1,zero_shot,walker,stand,FB,3,1,six,\n", "seeds 'six' is not an integer"),
    (paper.parse_methods, METHODS_HEAD + "1,FB,fb,--fb.lr,fb,t.toml,\n", "pairs of --option value"),
    (paper.parse_methods, METHODS_HEAD + "1,FB,nope,,nope,t.toml,\n", "unknown agent 'nope'"),
    (paper.parse_methods, METHODS_HEAD + "1,FB,fb,,,t.toml,\n", "given together"),
])
def test_a_malformed_paper_table_is_one_error_naming_the_line(parse, text: str, words: str):
    with pytest.raises(AnalysisError, match=words) as info:
        parse(text, "bad.csv")
    assert "bad.csv" in str(info.value) and "\n" not in str(info.value)
    if "columns" not in words:
        assert "line 2" in str(info.value)


def test_a_flag_that_is_no_option_of_the_agent_is_an_error():
    method = paper.parse_methods(METHODS_HEAD + "10,α=3,dvfb,--exploration.nope 3,dvfb,t.toml,\n")[0]
    with pytest.raises(AnalysisError, match="--exploration.nope is not an option of dvfb pretrain --agent dvfb"):
        method.overrides("walker")


# ---------------------------------------------------------------------------------------------
# dvfb report --paper


def make_urlb_finetune_run(run: Path, task: str, points: list[tuple[int, float]]) -> Path:
    """A finished fine-tuning run of a URLB-style method (its own fine-tuning config) with a curve."""
    parent = json.loads((run / "config.json").read_text())
    zero_shot, finetuner = protocols_of(parent["agent"])
    config = FinetuneRunConfig(
        pretrain_run=str(run), agent=parent["agent"], domain=parent["domain"], task=task, snapshot=100_000,
        seed=parent["seed"], protocol=finetuner.name, inference=zero_shot.config_cls(),
        finetune=finetuner.config_cls())
    path = run / "finetune" / task
    path.mkdir(parents=True)
    save_json(config, path / "config.json")
    write_json_atomic(path / "curve.json", {
        "task": task, "domain": parent["domain"], "agent": parent["agent"], "seed": parent["seed"],
        "curve": [{"frames": f, "mean_return": r, "std_return": 0.0, "returns": [r]} for f, r in points]})
    write_json_atomic(path / "finetune_summary.json", {"task": task, "frames": points[-1][0]})
    return path


def small_runs(root: Path) -> Path:
    """fb on walker, seeds 0 and 1, every task; cic on quadruped, 2 of 4 tasks; rnd fine-tuned on
    every walker task (seed 0), its curves ending at 20k frames. Small preset, 100k frames."""
    make_pretrain_run(root / "fb_s0", agent="fb", seed=0, zeroshot=dict(zip(WALKER, (100, 200, 300, 400))))
    make_pretrain_run(root / "fb_s1", agent="fb", seed=1, zeroshot=dict(zip(WALKER, (300, 200, 100, 0))))
    make_pretrain_run(root / "cic_s0", agent="cic", domain="quadruped", zeroshot=dict(zip(QUADRUPED[:2], (5, 7))))
    rnd = make_pretrain_run(root / "rnd_s0", agent="rnd")
    for task, last in zip(WALKER, (600, 620, 640, 660)):
        make_urlb_finetune_run(rnd, task, [(10_000, 1.0), (20_000, last)])
    return root


def test_report_paper_sets_the_domain_averages_beside_the_papers(tmp_path: Path):
    runs = small_runs(tmp_path / "runs")
    out = tmp_path / "report"
    report = make_report([runs], out, paper=True)
    rows = comparison_rows(out / "paper_comparison.csv")
    # Every cell of the paper is a row, once per report column it is compared with, or once alone.
    assert {(k[0], k[1], k[2], k[3]) for k in rows} == {(str(c.table), c.domain, c.task, c.paper_name)
                                                        for c in paper.load_paper_tables().cells}
    fb = rows[("1", "walker", "average", "FB", "fb")]
    # per seed: 250 and 150; the domain average is the mean of the task means, 200
    assert float(fb["report_value"]) == pytest.approx(200.0) and float(fb["report_std"]) == pytest.approx(70.7107, 1e-4)
    assert fb["report_seeds"] == "2" and float(fb["paper_value"]) == 114 and fb["paper_seeds"] == "6"
    assert float(fb["difference"]) == pytest.approx(200.0 - 114) and fb["status"] == "compared"
    assert fb["runs_vs_paper"] == "100k of 2M frames; preset small"
    assert float(fb["report_value"]) == pytest.approx(report.zeroshot.cell("walker", "average", "fb").mean)
    stand = rows[("1", "walker", "stand", "FB", "fb")]  # seeds 0 and 1: 100 and 300
    assert (float(stand["report_value"]), float(stand["paper_value"]), float(stand["paper_std"])) == (200.0, 303, 55)
    rnd = rows[("2", "walker", "average", "RND", "rnd")]
    assert float(rnd["report_value"]) == pytest.approx(630.0) and float(rnd["difference"]) == pytest.approx(-18.0)
    assert rnd["runs_vs_paper"] == "100k of 2M frames; preset small; fine-tuned 20k of 100k frames"
    assert rows[("1", "quadruped", "average", "CIC", "cic")]["status"] == "incomplete (2 of 4 tasks)"
    assert rows[("1", "quadruped", "average", "CIC", "cic")]["report_value"] == ""
    assert rows[("1", "quadruped", "walk", "CIC", "cic")]["report_value"] == "7.0"
    for key in [("1", "hopper", "average", "CeSD", ""), ("2", "quadruped", "average", "RND", ""),
                ("8", "walker", "average", "DVFB", ""), ("1", "walker", "average", "CIC", "")]:
        assert rows[key]["status"] == "not run" and rows[key]["difference"] == ""
    compared_averages = {k for k, r in rows.items() if r["status"] == "compared" and k[2] == "average"}
    assert compared_averages == {("1", "walker", "average", "FB", "fb"), ("2", "walker", "average", "RND", "rnd")}
    markdown = (out / "paper_comparison.md").read_text()
    assert "| 1 | walker | fb | FB | 200.0 | 2 | 114 | +86.0 | compared | 100k of 2M frames; preset small |" in markdown
    assert ("| 2 | walker | rnd | RND | 630.0 | 1 | 648 | -18.0 | compared | 100k of 2M frames; preset small; "
            "fine-tuned 20k of 100k frames |") in markdown
    # Per task, beside the report's mean ± std (seeds), with the runs' budget in the row itself.
    assert "### Table 1 (zero-shot), walker" in markdown
    assert ("| walker_stand | fb | FB | 200.0 ± 141.4 (2) | 303 ± 55 (6) | -103.0 | 100k of 2M frames; "
            "preset small |") in markdown
    assert "| walker_stand | rnd | RND | 600.0 (1) | 901 ± 19 | -301.0 | 100k of 2M frames; preset small; " \
           "fine-tuned 20k of 100k frames |" in markdown
    # The scale note: 100k frames of the small preset, curves at 20k, all named against the paper's.
    assert "far below the paper's budget" in markdown
    assert "pre-training of 100,000 frames (the paper: 2,000,000; 5% of it at most)" in markdown
    assert "preset small" in markdown and "fine-tuning curves ending at 20,000 frames" in markdown
    assert "sweeps/paper/table2_finetune.toml" in markdown  # what makes the columns not run here
    assert markdown.strip() in (out / "report.md").read_text()
    assert out / "paper_comparison.md" in report.files and report.paper is not None


def test_report_paper_prints_the_per_task_cells_of_walker_and_the_maze(tmp_path: Path, capsys):
    """The study's shape: DVFB, FB, CIC and RND on walker, DVFB, FB, CIC and CeSD on the maze, small
    preset, 100k frames, 2 seeds: Table 1's walker cells and Table 6's maze cells beside the report's."""
    root = tmp_path / "runs"
    maze = tasks_of_domain("point_mass_maze")
    for seed in (0, 1):
        for agent in ("dvfb", "fb", "cic", "rnd"):
            make_pretrain_run(root / f"{agent}_walker_s{seed}", agent=agent, seed=seed,
                              zeroshot={t: 100.0 * (i + 1) + 10 * seed for i, t in enumerate(WALKER)})
        for agent in ("dvfb", "fb", "cic", "cesd"):
            make_pretrain_run(root / f"{agent}_maze_s{seed}", agent=agent, domain="point_mass_maze", seed=seed,
                              zeroshot={t: 20.0 * (i + 1) + 10 * seed for i, t in enumerate(maze)})
    assert main(["report", str(root), "--out", str(tmp_path / "out"), "--paper"]) == 0
    printed = capsys.readouterr().out
    small = "100k of 2M frames; preset small"
    for agent, name, paper_value, difference in (("dvfb", "DVFB", "905 ± 27 (6)", "-800.0"),
                                                 ("fb", "FB", "303 ± 55 (6)", "-198.0"),
                                                 ("cic", "CIC", "357 ± 26 (6)", "-252.0")):
        assert f"| walker_stand | {agent} | {name} | 105.0 ± 7.1 (2) | {paper_value} | {difference} | {small} |" \
            in printed
    for agent, name, paper_value, difference in (("dvfb", "DVFB", "932 ± 10 (3)", "-907.0"),
                                                 ("fb", "FB", "69 ± 6 (3)", "-44.0"),
                                                 ("cic", "CIC", "18 ± 6 (3)", "+7.0"),
                                                 ("cesd", "CeSD", "12 ± 8 (3)", "+13.0")):
        assert (f"| point_mass_maze_reach_top_left | {agent} | {name} | 25.0 ± 7.1 (2) | {paper_value} | "
                f"{difference} | {small} |") in printed
    assert "| **average** | dvfb | DVFB | 55.0 ± 7.1 (2) | 308.3 (3) | -253.3 | " + small + " |" in printed
    assert "### Table 6 (zero-shot, point-mass maze and Meta-World), point_mass_maze" in printed
    assert "no cell of the paper for the zeroshot column(s) rnd" in printed
    written = (tmp_path / "out" / "paper_comparison.md").read_text()
    assert "| walker_run | cic | CIC | 305.0 ± 7.1 (2) | 78 ± 3 (6) | +227.0 |" in written


def test_report_paper_compares_ablation_columns_and_success_rates(tmp_path: Path):
    """Runs of DVFB at alpha 3 and 5 (preset paper) and at alpha 5 under preset code are three
    columns, each beside Table 10's cell of its alpha; a fine-tuning at eta 0.02 is Table 12's;
    Meta-World's success rates are Table 6's."""
    root = tmp_path / "runs"
    base = preset_config("paper", agent="dvfb", domain="walker", seed=0)
    for name, config in (("a3", merge(base, {"exploration": {"alpha": 3.0}})), ("a5", base),
                         ("code_a5", merge(preset_config("code", agent="dvfb", domain="walker", seed=0),
                                           {"exploration": {"alpha": 5.0}}))):
        run = make_pretrain_run(root / name, agent="dvfb", snapshot_frames=2_000_000,
                                zeroshot=dict(zip(WALKER, (900.0, 800.0, 500.0, 400.0))))
        save_json(config, run / "config.json")
    tuned = make_pretrain_run(root / "eta", agent="dvfb", domain="quadruped")
    save_json(preset_config("paper", agent="dvfb", domain="quadruped", seed=0), tuned / "config.json")
    make_finetune_run(tuned, "quadruped_walk", [(0, 10.0), (100_000, 850.0)], eta=0.02)
    world = make_pretrain_run(root / "world", agent="fb", domain="metaworld")
    for task, rate in (("metaworld_faucet_open", 0.25), ("metaworld_faucet_close", 0.5)):
        result = json.loads((root / "a5" / "zeroshot" / "walker_stand.json").read_text())
        write_json_atomic(world / "zeroshot" / f"{task}.json", {**result, "task": task, "domain": "metaworld",
                                                                  "agent": "fb", "success_rate": rate})
    out = tmp_path / "report"
    report = make_report([root], out, paper=True)
    assert {"dvfb", "dvfb_alpha3", "dvfb_alpha5"} <= set(report.zeroshot.columns)
    rows = comparison_rows(out / "paper_comparison.csv")
    assert rows[("10", "walker", "stand", "α=3", "dvfb_alpha3")]["status"] == "compared"
    assert rows[("10", "walker", "stand", "α=5", "dvfb")]["runs_vs_paper"] == "paper scale"
    assert rows[("10", "walker", "stand", "α=5", "dvfb_alpha5")]["report_value"] == "900.0"
    assert ("10", "walker", "stand", "α=3", "dvfb") not in rows and ("1", "walker", "stand", "DVFB", "dvfb") in rows
    eta = rows[("12", "quadruped", "walk", "η=0.02", "dvfb_eta0.02")]
    # fine-tuned for 100k frames from the 100k snapshot (make_finetune_run's): below the paper's 2M
    assert (float(eta["report_value"]), float(eta["paper_value"]), eta["runs_vs_paper"]) == (850.0, 891,
                                                                                             "100k of 2M frames")
    assert rows[("12", "quadruped", "average", "η=0.02", "dvfb_eta0.02")]["status"] == "incomplete (1 of 4 tasks)"
    faucet = rows[("6", "metaworld", "faucet_open", "FB", "fb")]
    assert (float(faucet["report_value"]), float(faucet["paper_value"])) == (0.25, 0.18)
    assert "| metaworld_faucet_close | fb | FB | 0.50 (1) | 0.1 [" in (out / "paper_comparison.md").read_text()


def test_compare_table_is_the_per_task_comparison_of_any_table():
    """The function the rest of the report calls, on a table it built itself (one snapshot's, say)."""
    scores = [Score("zeroshot", "fb", "walker", task, seed, value, Path(f"/runs/fb_s{seed}/zeroshot/{task}.json"))
              for seed, values in ((0, (10, 20, 30, 40)), (1, (30, 40, 50, 60))) for task, value in zip(WALKER, values)]
    table = build_table(scores, "Table 1 at 500k frames")
    budget = paper.RunBudget(("code",), (500_000,))
    rows = paper.compare_table(table, "zeroshot", budgets={"fb": budget}, presets=("code",))
    mine = {(r.cell.table, r.cell.task): r for r in rows if r.method == "fb"}
    assert set(mine) == {(1, t) for t in ("stand", "walk", "run", "flip", "average")}
    stand = mine[(1, "stand")]
    assert (stand.report.mean, stand.report.n, stand.cell.mean, stand.difference) == (20.0, 2, 303, -283.0)
    assert stand.scale == "500k of 2M frames" and mine[(1, "average")].report.mean == pytest.approx(35.0)
    assert all(r.status in ("not run", "paper only") and not r.method for r in rows if r.cell.paper_name != "FB")
    text = paper.cells_markdown(rows)
    assert text.startswith("### Table 1 (zero-shot), walker")
    assert "| walker_stand | fb | FB | 20.0 ± 14.1 (2) | 303 ± 55 (6) | -283.0 | 500k of 2M frames |" in text
    assert paper.compare_table(None, "finetune")[0].status in ("not run", "paper only")


def test_each_pretraining_budget_of_a_method_is_its_own_comparison_row(tmp_path: Path):
    root = tmp_path / "runs"
    make_pretrain_run(root / "fb_short", agent="fb", seed=0, snapshot_frames=1_200,
                      zeroshot=dict(zip(WALKER, (10, 20, 30, 40))))
    make_pretrain_run(root / "fb_long", agent="fb", seed=0, zeroshot=dict(zip(WALKER, (100, 200, 300, 400))))
    out = tmp_path / "report"
    make_report([root], out, paper=True)
    rows = comparison_rows(out / "paper_comparison.csv")
    assert ("1", "walker", "average", "FB", "fb") not in rows  # no row averages the two budgets
    short = rows[("1", "walker", "average", "FB", "fb (1,200 frames)")]
    long = rows[("1", "walker", "average", "FB", "fb (100,000 frames)")]
    assert float(short["report_value"]) == pytest.approx(25.0) and float(long["report_value"]) == pytest.approx(250.0)
    assert short["status"] == long["status"] == "compared" and short["paper_value"] == long["paper_value"]
    assert rows[("1", "walker", "stand", "FB", "fb (1,200 frames)")]["runs_vs_paper"].startswith("1.2k of 2M")
    markdown = (out / "paper_comparison.md").read_text()
    assert "| walker_stand | fb (1,200 frames) | FB | 10.0 (1) |" in markdown
    assert "no cell of the paper for the zeroshot" not in markdown  # the budgets' columns are fb's
    assert "pre-training of 1,200, 100,000 frames" in markdown  # the scale note names both budgets


def test_report_paper_at_the_papers_scale_says_so(tmp_path: Path):
    run = make_pretrain_run(tmp_path / "runs" / "fb_s0", agent="fb", snapshot_frames=2_000_000,
                            zeroshot=dict(zip(WALKER, (100, 120, 140, 160))))
    save_json(preset_config("code", agent="fb", domain="walker", seed=0), run / "config.json")
    out = tmp_path / "report"
    make_report([tmp_path / "runs"], out, paper=True)
    markdown = (out / "paper_comparison.md").read_text()
    assert "match the paper's budget (2,000,000 pre-training frames, preset code)" in markdown
    assert "far below" not in markdown
    assert "| 1 | walker | fb | FB | 130.0 | 1 | 114 | +16.0 | compared | paper scale |" in markdown


def test_a_full_size_preset_with_fewer_frames_is_still_below_scale(tmp_path: Path):
    run = make_pretrain_run(tmp_path / "runs" / "fb_s0", agent="fb", snapshot_frames=500_000,
                            zeroshot=dict(zip(WALKER, (1, 2, 3, 4))))
    save_json(merge(preset_config("code", agent="fb", domain="walker"), {"frames": 500_000}), run / "config.json")
    make_report([tmp_path / "runs"], tmp_path / "report", paper=True)
    markdown = (tmp_path / "report" / "paper_comparison.md").read_text()
    assert "pre-training of 500,000 frames (the paper: 2,000,000; 25% of it at most)" in markdown
    assert "preset" not in markdown.split("far below the paper's budget")[1].split(". Compare")[0]
    assert "| walker_stand | fb | FB | 1.0 (1) | 303 ± 55 (6) | -302.0 | 500k of 2M frames |" in markdown


def test_cli_report_paper_prints_the_section_and_without_it_writes_none(tmp_path: Path, capsys):
    runs = small_runs(tmp_path / "runs")
    assert main(["report", str(runs), "--out", str(tmp_path / "plain")]) == 0
    assert not (tmp_path / "plain" / "paper_comparison.md").exists()
    assert "Comparison with the paper" not in (tmp_path / "plain" / "report.md").read_text()
    capsys.readouterr()
    assert main(["report", str(runs), "--out", str(tmp_path / "with"), "--paper"]) == 0
    printed = capsys.readouterr().out
    assert "## Comparison with the paper's numbers" in printed and "| 1 | walker | fb | FB | 200.0 |" in printed
    # A second report into the same directory needs --overwrite, also for the comparison alone.
    (tmp_path / "again").mkdir()
    (tmp_path / "again" / "paper_comparison.csv").write_text("kept\n")
    assert main(["report", str(runs), "--out", str(tmp_path / "again"), "--paper"]) == 2
    err = capsys.readouterr().err
    assert "paper_comparison.csv exists" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "again" / "paper_comparison.csv").read_text() == "kept\n"
    assert sorted(p.name for p in (tmp_path / "again").iterdir()) == ["paper_comparison.csv"]


def test_unreadable_paper_tables_are_one_line_and_write_nothing(tmp_path: Path, capsys, monkeypatch):
    runs = small_runs(tmp_path / "runs")
    monkeypatch.setattr(paper, "DATA_DIR", ("data", "no_such_tables"))
    out = tmp_path / "report"
    assert main(["report", str(runs), "--out", str(out), "--paper"]) == 2
    err = capsys.readouterr().err.strip()
    assert "paper's tables cannot be read" in err and len(err.splitlines()) == 1
    assert not out.exists()


# ---------------------------------------------------------------------------------------------
# the sweep files of sweeps/paper and --dry-run


# Which table each sweep file makes (docs/reproduce.md lists the same), and the ablations' preset.
SWEEP_TABLES = {"table1_zeroshot": (1,), "table2_finetune": (2,), "table5_datasets": (5, 6),
                "table5_offline": (5,), "table5_dvfb_cheetah": (5,), "table6_maze_metaworld": (6,),
                "table6_offline": (6,), "table7_table11_beta": (7, 11), "table8_rewards": (8,),
                "table9_wo_map": (9,), "table10_alpha": (10,), "table12_eta": (9, 12)}
ABLATIONS = ("table7_table11_beta", "table8_rewards", "table9_wo_map", "table10_alpha", "table12_eta")


def test_there_is_a_paper_sweep_for_every_table():
    assert sorted(p.stem for p in PAPER_SWEEPS) == sorted(SWEEP_TABLES)
    covered = {t for tables in SWEEP_TABLES.values() for t in tables}
    assert covered == {c.table for c in paper.load_paper_tables().cells} == {1, 2, 5, 6, 7, 8, 9, 10, 11, 12}
    # and every mapping names the files that run it
    for method in paper.load_paper_tables().methods.values():
        assert all(method.table in SWEEP_TABLES[Path(s).stem] or Path(s).stem in ("table1_zeroshot", "table5_datasets")
                   for s in method.sweeps), (method.table, method.paper_name, method.sweeps)


@pytest.mark.parametrize("file", PAPER_SWEEPS, ids=lambda p: p.stem)
def test_each_paper_sweep_passes_dry_run_and_creates_nothing(file: Path, tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in file.parent.iterdir())
    assert main(["sweep", "run", str(file), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []  # no sweeps/<name>/ nor anything else
    assert sorted(p.name for p in file.parent.iterdir()) == before
    config = spec.build({}, spec.read_file(file), {}, {})
    cells = spec.cells(config)
    assert f"[sweep] {len(cells)} cell(s):" in printed
    assert all(f"[sweep]   {c.name} " in printed for c in cells)
    assert f"a run would create {Path('sweeps') / file.stem}" in printed
    # The ablations vary the paper's own coefficients (preset paper); the main tables use the authors' constants.
    assert config.preset == ("paper" if file.stem in ABLATIONS else "code")
    assert config.executor == "slurm" and config.slurm.partition
    assert config.seeds_per_job == len(config.seeds)
    assert config.slurm.pretrain.gpus == 1
    assert printed.count("dvfb pretrain --agent") == len(spec.job_groups(config))
    for cell in cells:
        cfg = spec.cell_config(config, cell)
        if cfg.dataset:  # offline: a frame is an update, about as many as an online run of 2M frames makes
            assert cfg.frames == paper.PAPER_PRETRAIN_FRAMES // 2
        elif file.stem == "table5_datasets":  # the exploration datasets, ExORL's size
            assert cfg.frames == cfg.replay_capacity == 10_000_000 and cfg.replay.record_physics
        else:
            assert cfg.frames == paper.PAPER_PRETRAIN_FRAMES


def _sweep_columns(config) -> set[tuple[str, str, str]]:
    """(kind, domain, report column) of every cell of a sweep, for the phases it runs."""
    columns = set()
    for cell in spec.cells(config):
        cfg = spec.cell_config(config, cell)
        if "zeroshot" in config.phases:
            columns.add(("zeroshot", cell.domain, method_name(cfg)))
        if "finetune" in config.phases:
            columns.add(("finetune", cell.domain, method_name(cfg, cfg.finetune)))
    return columns


def test_the_paper_sweeps_make_every_column_of_the_paper_on_its_domains():
    """For every cell of the paper with a dvfb method, its sweep files make the report column that
    --paper compares it with, on its domain, in the right phase."""
    tables = paper.load_paper_tables()
    configs = {file: spec.build({}, spec.read_file(ROOT / "sweeps" / "paper" / file), {}, {})
               for file in {s for m in tables.methods.values() for s in m.sweeps}}
    made = {file: _sweep_columns(config) for file, config in configs.items()}
    for cell in tables.cells:
        method = tables.method_of(cell)
        if not method.agent or cell.domain == "all":
            continue
        label = method.label(configs[method.sweeps[-1]].preset, cell.domain, cell.report_kind)
        assert any((cell.report_kind, cell.domain, label) in made[file] for file in method.sweeps), \
            (cell.table, cell.paper_name, cell.domain, label)
    table2 = spec.build({}, spec.read_file(ROOT / "sweeps" / "paper" / "table2_finetune.toml"), {}, {})
    assert table2.finetune_tasks == ["all"]
    assert spec.cell_config(table2, spec.cells(table2)[0]).finetune.frames == paper.PAPER_FINETUNE_FRAMES
    table6 = spec.build({}, spec.read_file(ROOT / "sweeps" / "paper" / "table6_maze_metaworld.toml"), {}, {})
    assert table6.domains == ["point_mass_maze", "metaworld"] and "finetune" in table6.phases


def test_dry_run_of_a_bad_sweep_is_one_line_and_creates_nothing(tmp_path: Path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text('agents = ["dvfb", "nope"]\ndomains = ["walker"]\n')
    assert main(["sweep", "run", str(bad), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown agent 'nope'" in err and len(err.splitlines()) == 1
    bad.write_text('agents = ["fb"]\nexecutor = "slurm"\n[slurm]\nextra_sbatch = ["constraint=a100"]\n')
    assert main(["sweep", "run", str(bad), "--dry-run", "--frames", "10000"]) == 2
    assert "slurm.extra_sbatch" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


def test_a_grid_that_only_adds_cells_grows_the_sweep_and_one_that_changes_a_cell_is_refused(tmp_path: Path, capsys):
    files = {"agents": ["fb", "supervised"], "seeds": [0, 1], "phases": ["pretrain", "zeroshot", "finetune"],
             "finetune_tasks": ["walker_walk"], "exclude": ["supervised_*_s1"], "overrides": {"frames": 10000}}
    sweep = tmp_path / "sweep"
    runner.prepare(sweep, spec.build({}, files, {}, {}))
    stored = (sweep / spec.SWEEP_FILE).read_text()
    grown = spec.build({}, {**files, "domains": ["walker", "hopper"], "finetune_tasks": ["walker_walk", "hopper_hop"],
                            "exclude": ["supervised_*_s1", "fb_hopper_s1"]}, {}, {})
    lines = runner.dry_run(sweep, grown)
    assert "the grid grows: 5 new cell(s) beside the 6 of" in capsys.readouterr().out
    assert (sweep / spec.SWEEP_FILE).read_text() == stored  # a dry run writes nothing
    assert any("25 to run (11 pretrain, 11 zeroshot, 3 finetune)" in line for line in lines)  # nothing ran yet
    # Each way of changing what a stored cell is, or of dropping one, is another sweep.
    for change, why in (({"exclude": ["supervised_*_s1", "fb_walker_s1"]}, "cell fb_walker_s1 is not in the new grid"),
                        ({"overrides": {"frames": 20000}}, "would get another config"),
                        ({"finetune_tasks": ["hopper_hop"], "domains": ["walker", "hopper"]},
                         r"would lose its unit\(s\) finetune-walker_walk"),
                        ({"preset": "code"}, "another preset")):
        with pytest.raises(ConfigError, match=why):
            runner.prepare(sweep, spec.build({}, {**files, **change}, {}, {}))
        assert (sweep / spec.SWEEP_FILE).read_text() == stored
    runner.prepare(sweep, grown)
    assert json.loads((sweep / spec.SWEEP_FILE).read_text())["domains"] == ["walker", "hopper"]


def test_dry_run_checks_an_existing_sweep_directory_and_changes_nothing(tmp_path: Path, capsys):
    config = spec.build({}, {"agents": ["fb"], "seeds": [0, 1], "overrides": {"frames": 10000}}, {}, {})
    sweep = tmp_path / "sweep"
    runner.prepare(sweep, config)
    stored = (sweep / spec.SWEEP_FILE).read_text()
    lines = runner.dry_run(sweep, config)
    assert f"a run continues the sweep in {sweep}" in lines[0]
    assert any("4 unit(s), 4 to run (2 pretrain, 2 zeroshot, 0 finetune), 0 already done" in line for line in lines)
    assert (sweep / spec.SWEEP_FILE).read_text() == stored
    assert sorted(p.name for p in sweep.iterdir()) == [".gitignore", spec.SWEEP_FILE]  # what prepare wrote
    other = spec.build({}, {"agents": ["fb"], "seeds": [0, 1, 2]}, {}, {})
    with pytest.raises(ConfigError, match="holds another sweep"):
        runner.dry_run(sweep, other)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    assert main(["sweep", "run", "--dir", str(tmp_path / "full"), "--agents", "fb", "--dry-run"]) == 2
    assert "is not a sweep directory" in capsys.readouterr().err
    assert json.loads(stored)["agents"] == ["fb"]
