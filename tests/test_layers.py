"""The layers contract (docs/architecture.md, "Layers"): every module of dvfb imports only its own
layer and the layers below it, and every function-level import says why it is not at the top."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import layers  # noqa: E402


def test_every_module_imports_only_its_own_layer_and_those_below():
    rooms, imports = layers.read_package()
    assert {"agents", "runs", "training", "workflows", "cli"} <= set(rooms)  # the package was read
    assert len(imports) > 100
    assert layers.check(rooms, imports) == []


def test_the_check_finds_an_import_that_runs_up_a_layer(tmp_path):
    rooms = {"runs": layers.Room("runs"), "workflows": layers.Room("workflows")}
    upward = layers.Import("dvfb.runs.layout", 12, "dvfb.workflows.session", False, "")
    lazy = layers.Import("dvfb.workflows.pretrain", 30, "dvfb.runs.layout", True, "")
    problems = layers.check(rooms, [upward, lazy])
    assert any("dvfb.runs.layout:12" in p and "runs stands below workflows" in p for p in problems)
    assert any("dvfb.workflows.pretrain:30" in p and "without a comment" in p for p in problems)


def test_analysis_and_sweep_stand_below_workflows():
    order = [name for name, _rooms in layers.LAYERS]
    assert order.index("analysis") < order.index("workflows") and order.index("sweep") < order.index("workflows")
    assert order.index("training") < order.index("protocols") < order.index("runs")
