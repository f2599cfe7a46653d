"""The package's layers, their imports and the layers contract (docs/architecture.md).

Data flows one way through dvfb's layers, lowest first::

    core -> envs -> data -> nets -> rewards -> agents -> training -> protocols -> runs -> analysis
    -> sweep -> workflows -> cli

Each layer is a folder of ``src/dvfb`` (a room); the folders show the layers and this script reads
them. Beside the folders the package has only its face: ``__init__.py`` (``dvfb.load``, which imports
the API on first use) and ``__main__.py`` (``python -m dvfb``), which stand outside the layers.

A module may import its own layer and the layers below it, never one above. This script reads every
module of ``src/dvfb`` with Python's own parser (nothing is imported or run) and prints each room:
its layer, its lines, the rooms it imports and its function-level imports. It reports as a breach:

* a top-level module other than the face (every module lives in its layer's folder);
* a folder that is no layer of :data:`LAYERS`;
* an import that runs up a layer, the face included (it stands above every layer);
* a function-level import (an import inside a function or method, of dvfb or of any other package)
  without a comment, on its line or on the line above its block of imports, that says why it is not
  at the top of its module: a measured cost at start-up (matplotlib, the API behind ``dvfb.load``),
  an optional extra that may be absent, an import that must follow a setting (MUJOCO_GL).

    python scripts/layers.py           # the table; exit status 1 when the contract is broken
    python scripts/layers.py --json    # the same as JSON

``tests/test_layers.py`` runs :func:`check` in the test suite.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "dvfb"

# The layers, lowest first: each is the folder of src/dvfb of that name.
LAYERS: list[str] = ["core", "envs", "data", "nets", "rewards", "agents", "training", "protocols", "runs",
                     "analysis", "sweep", "workflows", "cli"]
# The package's face: the two top-level modules, outside the layers (they may import any layer; no
# layer may import them).
FACE = ("__init__", "__main__")


def layer_of(room: str) -> int:
    return LAYERS.index(room)  # ValueError: no layer


@dataclass
class Import:
    module: str  # the importing module, dotted
    line: int
    target: str  # the imported module, dotted (a dvfb module or another package's)
    in_function: bool
    comment: str  # why it is where it is: the comment on its line or above its block ("" when none)

    @property
    def internal(self) -> bool:
        return self.target == "dvfb" or self.target.startswith("dvfb.")


@dataclass
class Room:
    name: str
    folder: bool = True  # False: a top-level module (the face, or a stray one)
    lines: int = 0
    imports: set[str] = field(default_factory=set)
    function_imports: int = 0


def module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def room_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


# A linter's directive is no reason: ``# noqa: F401`` alone says nothing of why.
_DIRECTIVE = re.compile(r"^(noqa(:\s*[A-Z]+[0-9]+(,\s*[A-Z]+[0-9]+)*)?|type:\s*ignore(\[[^]]*\])?|isort:\s*\w+)")


def _reason(lines: list[str], lineno: int) -> str:
    """The comment that says why an import is where it is: on its line (less a linter's directive),
    or on the comment line above the block of import lines it belongs to."""
    text = lines[lineno - 1]
    if "#" in text:
        comment = _DIRECTIVE.sub("", text.split("#", 1)[1].strip()).strip()
        if comment:
            return comment
    above = lineno - 2
    while above >= 0 and lines[above].strip().startswith(("from ", "import ")):
        above -= 1
    if above >= 0 and lines[above].strip().startswith("#"):
        return lines[above].strip().lstrip("#").strip()
    return ""


def imports_of(path: Path, package: Path = PACKAGE) -> list[Import]:
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    tree = ast.parse(source, str(path))
    module = module_name(path, package)
    found: list[Import] = []

    def is_room(name: str) -> bool:
        return (package / name).is_dir() or (package / f"{name}.py").is_file()

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = _resolve(child, module, path.name == "__init__.py")
                # ``from dvfb import envs`` imports a room; ``from dvfb.runs import a, b`` one module.
                targets = sorted({f"{base}.{alias.name}" if base == "dvfb" and is_room(alias.name) else base
                                  for alias in child.names})
            for target in targets:
                found.append(Import(module, child.lineno, target, in_function, _reason(lines, child.lineno)))
            visit(child, inner)

    visit(tree, False)
    return found


def read_package(package: Path = PACKAGE) -> tuple[dict[str, Room], list[Import]]:
    """Every room of ``package`` (its folders and top-level modules) and every import of its modules."""
    rooms: dict[str, Room] = {}
    for entry in sorted(package.iterdir()):
        if entry.is_dir() and entry.name != "__pycache__" and not entry.name.startswith("."):
            rooms[entry.name] = Room(entry.name)
        elif entry.suffix == ".py":
            rooms[entry.stem] = Room(entry.stem, folder=False)
    everything: list[Import] = []
    for path in sorted(package.rglob("*.py")):
        room = rooms[room_of(module_name(path, package))]
        room.lines += len(path.read_text(encoding="utf-8").splitlines())
        for item in imports_of(path, package):
            everything.append(item)
            if item.internal and room_of(item.target) != room.name:
                room.imports.add(room_of(item.target))
            room.function_imports += item.in_function
    return rooms, everything


def check(rooms: dict[str, Room] | None = None, imports: list[Import] | None = None,
          package: Path = PACKAGE) -> list[str]:
    """The breaches of the contract, one line each (empty when it holds)."""
    if rooms is None or imports is None:
        rooms, imports = read_package(package)
    problems = []
    for room in rooms.values():
        if not room.folder and room.name not in FACE:
            problems.append(f"dvfb/{room.name}.py is a top-level module: move it into its layer's folder "
                            f"(the top level holds only {' and '.join(f'{n}.py' for n in FACE)})")
        elif room.folder and room.name not in LAYERS:
            problems.append(f"dvfb/{room.name}/ is no layer's folder (the layers: {', '.join(LAYERS)}; "
                            "scripts/layers.py)")
    for item in imports:
        if item.in_function and not item.comment:
            problems.append(f"{item.module}:{item.line} imports {item.target} inside a function without a comment "
                            "that says why")
        if not item.internal:
            continue
        source, target = room_of(item.module), room_of(item.target)
        if target in FACE and source in LAYERS:
            # The face imports the API (the workflows) on first use: a layer that imports it runs up.
            problems.append(f"{item.module}:{item.line} imports {item.target}: the package's face stands above "
                            "every layer; import from the layer that defines it (the version: dvfb.core.version)")
            continue
        if source in FACE or target in FACE or source == target or source not in LAYERS or target not in LAYERS:
            continue  # the face stands outside the layers; a room without a layer is reported above
        if layer_of(target) > layer_of(source):
            problems.append(f"{item.module}:{item.line} imports {item.target}: {source} stands below {target}")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="dvfb's layers, their imports and the layers contract.")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    rooms, imports = read_package()
    problems = check(rooms, imports)

    def layer(room: Room) -> str:
        return "face" if room.name in FACE else room.name if room.name in LAYERS else "?"

    def order(room: Room) -> tuple:
        return (layer_of(room.name) if room.name in LAYERS else -1, room.name)

    table = sorted(rooms.values(), key=order)
    if args.json:
        print(json.dumps({"rooms": [{"room": r.name, "layer": layer(r), "lines": r.lines, "imports": sorted(r.imports),
                                     "function_imports": r.function_imports} for r in table],
                          "lines": sum(r.lines for r in table),
                          "function_imports": sum(r.function_imports for r in table),
                          "problems": problems}, indent=1))
    else:
        print(f"{'layer':<10} {'lines':>6} {'fn-imp':>6}  imports")
        for r in table:
            name = r.name if r.folder else f"{r.name}.py"
            print(f"{name:<10} {r.lines:>6} {r.function_imports:>6}  {', '.join(sorted(r.imports))}")
        print(f"{'total':<10} {sum(r.lines for r in table):>6} {sum(r.function_imports for r in table):>6}")
        for problem in problems:
            print(f"BREACH {problem}")
        print("the layers contract holds" if not problems else f"{len(problems)} breach(es)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
