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
from dvfb.analysis.common import AnalysisError, method_name
from dvfb.analysis.report import make_report
from dvfb.cli import main
from dvfb.config import merge, save_json
from dvfb.envs.registry import tasks_of_domain
from dvfb.errors import ConfigError
from dvfb.runs import write_json_atomic
from dvfb.runs.presets import preset_config
from dvfb.runs.run_config import finetune_run_config_class
from dvfb.sweep import runner, spec

from test_analysis import make_pretrain_run

ROOT = Path(__file__).resolve().parents[1]
PAPER_SWEEPS = sorted((ROOT / "sweeps" / "paper").glob("*.toml"))
WALKER = tasks_of_domain("walker")
QUADRUPED = tasks_of_domain("quadruped")


def numbers_by_key() -> dict[tuple[int, str, str], paper.PaperNumber]:
    return {(n.table, n.domain, n.method): n for n in paper.load_paper_numbers()}


def comparison_rows(path: Path) -> dict[tuple[str, str, str], dict[str, str]]:
    return {(r["table"], r["domain"], r["method"]): r for r in csv.DictReader(io.StringIO(path.read_text()))}


# ---------------------------------------------------------------------------------------------
# the published numbers


def test_the_published_numbers_are_the_papers():
    numbers = numbers_by_key()
    assert len(numbers) == 27 + 27 + 4
    assert {(t, d) for t, d, _ in numbers} == {(t, d) for t in (1, 2) for d in ("walker", "quadruped", "hopper")} \
        | {(8, "walker")}
    # Table 1 (zero-shot), one row per domain, read from left to right.
    walker1 = [numbers[(1, "walker", m)].value for m in ("SF-CL", "SF-Lap", "SF-LRA-P", "SF-LRA-SR", "fb", "cic",
                                                         "becl", "comsd", "cesd")]
    assert walker1 == [76, 204, 166, 90, 114, 207, 59, 161, 113]
    assert numbers[(1, "quadruped", "fb")].value == 638 and numbers[(1, "hopper", "cic")].value == 11
    # Table 2 (after 100k fine-tuning frames).
    quadruped2 = [numbers[(2, "quadruped", m)].value for m in ("disagreement", "rnd", "smm", "diayn", "aps", "cic",
                                                               "becl", "comsd", "cesd")]
    assert quadruped2 == [405, 605, 182, 517, 353, 583, 720, 686, 787]
    assert numbers[(2, "hopper", "rnd")].value == 152 and numbers[(2, "walker", "comsd")].value == 739
    # Table 8 (DVFB's intrinsic reward swapped; zero-shot walker).
    assert {m: numbers[(8, "walker", m)].value for m in ("dvfb", "dvfb_icm_apt", "dvfb_proto", "dvfb_cic")} == {
        "dvfb": 686, "dvfb_icm_apt": 628, "dvfb_proto": 619, "dvfb_cic": 612}
    assert numbers[(1, "walker", "SF-LRA-P")].paper_name == "LRA-P"
    assert {n.kind for n in numbers.values() if n.table in (1, 8)} == {"zeroshot"}
    assert {n.kind for n in numbers.values() if n.table == 2} == {"finetune"}


def test_every_published_method_is_a_column_name_of_the_report():
    """The CSVs name methods as the report does, so a run of the method lands on its number."""
    labels = {name: method_name({"agent": name}) for name in
              ("fb", "cic", "becl", "comsd", "cesd", "disagreement", "rnd", "smm", "diayn", "aps", "dvfb")}
    labels.update({f"sf:{f}": method_name({"agent": "sf", "sf": {"features": f}}) for f in ("lap", "lra_p", "lra_sr",
                                                                                             "cl")})
    labels.update({f"dvfb:{r}": method_name({"agent": "dvfb", "exploration": {"reward": r}})
                   for r in ("icm_apt", "proto", "cic")})
    assert {n.method for n in paper.load_paper_numbers()} == set(labels.values())


def test_the_tables_ship_as_package_data():
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["dvfb"]
    files = sorted((ROOT / "src" / "dvfb" / "data" / "paper_tables").glob("*.csv"))
    assert len(files) == 3
    for file in files:
        relative = file.relative_to(ROOT / "src" / "dvfb").as_posix()
        assert any(fnmatch.fnmatch(relative, p) for p in patterns), relative


@pytest.mark.parametrize("text, words", [
    ("table,kind,domain,method,value\n1,zeroshot,walker,fb,1\n", "expected the columns"),
    ("table,kind,domain,method,paper_name,value,source\n1,later,walker,fb,FB,1,x\n", "kind must be one of"),
    ("table,kind,domain,method,paper_name,value,source\n1,zeroshot,walker,fb,FB,many,x\n", "value a number"),
    ("table,kind,domain,method,paper_name,value,source\n1,zeroshot,walker,fb,FB,nan,x\n", "not finite"),
    ("table,kind,domain,method,paper_name,value,source\n1,zeroshot,walker,fb,FB,,x\n", "needs a value"),
])
def test_a_malformed_paper_table_is_one_error_naming_the_line(text: str, words: str):
    with pytest.raises(AnalysisError, match=words) as info:
        paper.parse_paper_csv(text, "bad.csv")
    assert "bad.csv" in str(info.value) and "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------
# dvfb report --paper


def make_urlb_finetune_run(run: Path, task: str, points: list[tuple[int, float]]) -> Path:
    """A finished fine-tuning run of a URLB-style method (its own fine-tuning config) with a curve."""
    parent = json.loads((run / "config.json").read_text())
    config = finetune_run_config_class(parent["agent"])(
        pretrain_run=str(run), agent=parent["agent"], domain=parent["domain"], task=task, snapshot=100_000,
        seed=parent["seed"])
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
    assert len(rows) == len(paper.load_paper_numbers())
    fb = rows[("1", "walker", "fb")]
    # per seed: 250 and 150; the domain average is the mean of the task means, 200
    assert float(fb["report_value"]) == pytest.approx(200.0)
    assert fb["report_seeds"] == "2" and float(fb["paper_value"]) == 114
    assert float(fb["difference"]) == pytest.approx(200.0 - 114) and fb["status"] == "compared"
    assert float(fb["report_value"]) == pytest.approx(report.zeroshot.cell("walker", "average", "fb").mean)
    rnd = rows[("2", "walker", "rnd")]
    assert float(rnd["report_value"]) == pytest.approx(630.0) and float(rnd["difference"]) == pytest.approx(-18.0)
    assert rows[("1", "quadruped", "cic")]["status"] == "incomplete (2 of 4 tasks)"
    assert rows[("1", "quadruped", "cic")]["report_value"] == ""
    for key in [("1", "hopper", "cesd"), ("2", "quadruped", "rnd"), ("8", "walker", "dvfb"), ("1", "walker", "cic")]:
        assert rows[key]["status"] == "not run" and rows[key]["difference"] == ""
    compared = {k for k, r in rows.items() if r["status"] == "compared"}
    assert compared == {("1", "walker", "fb"), ("2", "walker", "rnd")}
    markdown = (out / "paper_comparison.md").read_text()
    assert "| 1 | walker | fb | FB | 200.0 | 2 | 114 | +86.0 | compared |" in markdown
    assert "| 2 | walker | rnd | RND | 630.0 | 1 | 648 | -18.0 | compared |" in markdown
    # The scale note: 100k frames of the small preset, curves at 20k, all named against the paper's.
    assert "far below the paper's budget" in markdown
    assert "pre-training of 100,000 frames (the paper: 2,000,000; 5% of it at most)" in markdown
    assert "preset small" in markdown and "fine-tuning curves ending at 20,000 frames" in markdown
    assert markdown.strip() in (out / "report.md").read_text()
    assert out / "paper_comparison.md" in report.files and report.paper is not None


def test_each_pretraining_budget_of_a_method_is_its_own_comparison_row(tmp_path: Path):
    root = tmp_path / "runs"
    make_pretrain_run(root / "fb_short", agent="fb", seed=0, snapshot_frames=1_200,
                      zeroshot=dict(zip(WALKER, (10, 20, 30, 40))))
    make_pretrain_run(root / "fb_long", agent="fb", seed=0, zeroshot=dict(zip(WALKER, (100, 200, 300, 400))))
    out = tmp_path / "report"
    make_report([root], out, paper=True)
    rows = comparison_rows(out / "paper_comparison.csv")
    assert ("1", "walker", "fb") not in rows  # no row averages the two budgets
    short, long = rows[("1", "walker", "fb (1,200 frames)")], rows[("1", "walker", "fb (100,000 frames)")]
    assert float(short["report_value"]) == pytest.approx(25.0) and float(long["report_value"]) == pytest.approx(250.0)
    assert short["status"] == long["status"] == "compared" and short["paper_value"] == long["paper_value"]
    markdown = (out / "paper_comparison.md").read_text()
    assert "| 1 | walker | fb (1,200 frames) | FB | 25.0 | 1 | 114 | -89.0 | compared |" in markdown
    assert "no published zeroshot number" not in markdown  # the budgets' columns are fb's
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
    assert "| 1 | walker | fb | FB | 130.0 | 1 | 114 | +16.0 | compared |" in markdown


def test_a_full_size_preset_with_fewer_frames_is_still_below_scale(tmp_path: Path):
    run = make_pretrain_run(tmp_path / "runs" / "fb_s0", agent="fb", snapshot_frames=500_000,
                            zeroshot=dict(zip(WALKER, (1, 2, 3, 4))))
    save_json(merge(preset_config("code", agent="fb", domain="walker"), {"frames": 500_000}), run / "config.json")
    make_report([tmp_path / "runs"], tmp_path / "report", paper=True)
    markdown = (tmp_path / "report" / "paper_comparison.md").read_text()
    assert "pre-training of 500,000 frames (the paper: 2,000,000; 25% of it at most)" in markdown
    assert "preset" not in markdown.split("far below the paper's budget")[1].split(". Compare")[0]


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


def test_there_are_three_paper_sweeps():
    assert [p.name for p in PAPER_SWEEPS] == ["table1_zeroshot.toml", "table2_finetune.toml",
                                              "table6_maze_metaworld.toml"]


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
    assert config.preset == "code" and config.executor == "slurm" and config.slurm.partition
    assert config.seeds_per_job == len(config.seeds)
    assert config.slurm.pretrain.gpus == 1
    assert printed.count("dvfb pretrain --agent") == len(spec.job_groups(config))
    assert all(spec.cell_config(config, c).frames == paper.PAPER_PRETRAIN_FRAMES for c in cells)


def test_the_paper_sweeps_run_every_published_method_on_its_domains():
    numbers = paper.load_paper_numbers()
    for file, tables, kind in ((PAPER_SWEEPS[0], (1,), "zeroshot"), (PAPER_SWEEPS[1], (2,), "finetune")):
        config = spec.build({}, spec.read_file(file), {}, {})
        run = {(c.domain, method_name(spec.cell_config(config, c))) for c in spec.cells(config)}
        wanted = {(n.domain, n.method) for n in numbers if n.table in tables}
        assert wanted <= run, sorted(wanted - run)
        assert kind in config.phases
        assert set(config.domains) == {"walker", "quadruped", "hopper"}
    table2 = spec.build({}, spec.read_file(PAPER_SWEEPS[1]), {}, {})
    assert table2.finetune_tasks == ["all"]
    assert spec.cell_config(table2, spec.cells(table2)[0]).finetune.frames == paper.PAPER_FINETUNE_FRAMES
    table6 = spec.build({}, spec.read_file(PAPER_SWEEPS[2]), {}, {})
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


def test_dry_run_checks_an_existing_sweep_directory_and_changes_nothing(tmp_path: Path, capsys):
    config = spec.build({}, {"agents": ["fb"], "seeds": [0, 1], "overrides": {"frames": 10000}}, {}, {})
    sweep = tmp_path / "sweep"
    runner.prepare(sweep, config)
    stored = (sweep / spec.SWEEP_FILE).read_text()
    lines = runner.dry_run(sweep, config)
    assert f"a run continues the sweep in {sweep}" in lines[0]
    assert any("4 unit(s), 4 to run (2 pretrain, 2 zeroshot, 0 finetune), 0 already done" in line for line in lines)
    assert (sweep / spec.SWEEP_FILE).read_text() == stored
    assert sorted(p.name for p in sweep.iterdir()) == [spec.SWEEP_FILE]
    other = spec.build({}, {"agents": ["fb"], "seeds": [0, 1, 2]}, {}, {})
    with pytest.raises(ConfigError, match="holds another sweep"):
        runner.dry_run(sweep, other)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    assert main(["sweep", "run", "--dir", str(tmp_path / "full"), "--agents", "fb", "--dry-run"]) == 2
    assert "is not a sweep directory" in capsys.readouterr().err
    assert json.loads(stored)["agents"] == ["fb"]
