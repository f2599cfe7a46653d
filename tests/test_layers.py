"""The layers contract (docs/architecture.md, "Layers"): each layer is a folder of dvfb, every module
lives in its layer's folder, imports only its own layer and the layers below it, and every
function-level import says why it is not at the top."""

import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import layers  # noqa: E402


def test_every_module_imports_only_its_own_layer_and_those_below():
    rooms, imports = layers.read_package()
    assert {"core", "agents", "runs", "training", "workflows", "cli"} <= set(rooms)  # the package was read
    assert len(imports) > 100
    assert layers.check(rooms, imports) == []


def test_the_folders_are_the_layers_and_the_top_level_is_the_face():
    rooms, _imports = layers.read_package()
    assert {name for name, room in rooms.items() if room.folder} == set(layers.LAYERS)
    assert {name for name, room in rooms.items() if not room.folder} == set(layers.FACE)


def test_the_check_finds_an_import_that_runs_up_a_layer(tmp_path):
    rooms = {"runs": layers.Room("runs"), "workflows": layers.Room("workflows")}
    upward = layers.Import("dvfb.runs.layout", 12, "dvfb.workflows.session", False, "")
    lazy = layers.Import("dvfb.workflows.pretrain", 30, "dvfb.runs.layout", True, "")
    problems = layers.check(rooms, [upward, lazy])
    assert any("dvfb.runs.layout:12" in p and "runs stands below workflows" in p for p in problems)
    assert any("dvfb.workflows.pretrain:30" in p and "without a comment" in p for p in problems)


def test_a_linters_directive_is_no_reason_for_a_function_level_import():
    lines = ["def f():", "    import wandb  # noqa: F401", "    # optional extra", "    import hub  # noqa: F401"]
    assert layers._reason(lines, 2) == ""
    assert layers._reason(lines, 4) == "optional extra"
    assert layers._reason(["    import x  # noqa: F401  (chooses the backend now)"], 1) == "(chooses the backend now)"


def _copy_of_the_package(tmp_path: Path) -> Path:
    package = tmp_path / "dvfb"
    shutil.copytree(layers.PACKAGE, package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    assert layers.check(package=package) == []
    return package


def test_the_check_finds_a_module_outside_the_layers_folders(tmp_path):
    package = _copy_of_the_package(tmp_path)
    (package / "helpers.py").write_text("from dvfb.core.errors import DvfbError\n")
    problems = layers.check(package=package)
    assert len(problems) == 1 and "dvfb/helpers.py is a top-level module" in problems[0]


def test_the_check_finds_a_folder_that_is_no_layer(tmp_path):
    package = _copy_of_the_package(tmp_path)
    (package / "utils").mkdir()
    (package / "utils" / "__init__.py").write_text("from dvfb.runs import RunDir\n")
    problems = layers.check(package=package)
    assert len(problems) == 1 and "dvfb/utils/ is no layer's folder" in problems[0]


def test_the_check_finds_a_layer_that_imports_the_face(tmp_path):
    package = _copy_of_the_package(tmp_path)
    (package / "runs" / "stamp.py").write_text("from dvfb import __version__\n")
    problems = layers.check(package=package)
    assert len(problems) == 1 and "dvfb.runs.stamp:1 imports dvfb" in problems[0]
    assert "the package's face stands above every layer" in problems[0]


def test_analysis_and_sweep_stand_below_workflows():
    order = layers.LAYERS
    assert order.index("analysis") < order.index("workflows") and order.index("sweep") < order.index("workflows")
    assert order.index("training") < order.index("protocols") < order.index("runs")
    assert order[0] == "core" and order[-1] == "cli"
