"""The package's rooms, their imports and the layers contract (docs/architecture.md).

Data flows one way through dvfb's layers, lowest first::

    base (errors, config, files) -> envs -> data -> nets (nets, skills, execution) -> rewards -> agents
    -> training -> protocols -> runs -> analysis -> sweep -> workflows (workflows, api) -> cli

A module may import its own layer and the layers below it, never one above. This script reads
every module of ``src/dvfb`` with Python's own parser (nothing is imported or run) and prints:

* each room (a top-level package or module of ``dvfb``): its layer, its lines and the rooms it
  imports;
* the imports that run up a layer (none, when the contract holds);
* the function-level imports (imports inside a function or method): each must say in a comment, on
  its line or on the line above its block of imports, why it is not at the top of its module (a
  lazy import that keeps ``dvfb``'s start-up fast, for example).

    python scripts/layers.py           # the table; exit status 1 when the contract is broken
    python scripts/layers.py --json    # the same as JSON

``tests/test_layers.py`` runs :func:`check` in the test suite.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "dvfb"

# Lowest first. A room not listed here is an error (every room has a layer).
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("base", ("errors", "config", "files")),
    ("envs", ("envs",)),
    ("data", ("data", "replay", "datasets")),  # replay, datasets: the deprecated aliases of data's modules
    ("nets", ("nets", "skills", "execution")),
    ("rewards", ("rewards",)),
    ("agents", ("agents",)),
    ("training", ("training",)),
    ("protocols", ("protocols",)),
    ("runs", ("runs",)),
    ("analysis", ("analysis",)),
    ("sweep", ("sweep",)),
    ("workflows", ("workflows", "api")),
    ("cli", ("cli", "__main__")),
]
# The package's face: ``dvfb.load`` imports the API on first use (the one arrow that may run up).
FACE = "__init__"


def layer_of(room: str) -> int:
    for index, (_name, rooms) in enumerate(LAYERS):
        if room in rooms:
            return index
    raise KeyError(room)


@dataclass
class Import:
    module: str  # the importing module, dotted
    line: int
    target: str  # the imported dvfb module, dotted
    in_function: bool
    comment: str  # the comment on the import's line ("" when none)


@dataclass
class Room:
    name: str
    lines: int = 0
    imports: set[str] = field(default_factory=set)
    function_imports: int = 0


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def room_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else FACE


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _is_room(name: str) -> bool:
    return (PACKAGE / name).is_dir() or (PACKAGE / f"{name}.py").is_file()


def _reason(lines: list[str], lineno: int) -> str:
    """The comment that says why an import is where it is: on its line, or on the comment line above
    the block of import lines it belongs to."""
    text = lines[lineno - 1]
    if "#" in text:
        return text.split("#", 1)[1].strip()
    above = lineno - 2
    while above >= 0 and lines[above].strip().startswith(("from ", "import ")):
        above -= 1
    if above >= 0 and lines[above].strip().startswith("#"):
        return lines[above].strip().lstrip("#").strip()
    return ""


def imports_of(path: Path) -> list[Import]:
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    tree = ast.parse(source, str(path))
    module = module_name(path)
    found: list[Import] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            targets: list[str] = []
            if isinstance(child, ast.Import):
                targets = [alias.name for alias in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = _resolve(child, module, path.name == "__init__.py")
                # ``from dvfb import envs`` imports a room; ``from dvfb.runs import a, b`` one module.
                targets = sorted({f"{base}.{alias.name}" if base == "dvfb" and _is_room(alias.name) else base
                                  for alias in child.names})
            for target in targets:
                if target == "dvfb" or target.startswith("dvfb."):
                    found.append(Import(module, child.lineno, target, in_function, _reason(lines, child.lineno)))
            visit(child, inner)

    visit(tree, False)
    return found


def read_package() -> tuple[dict[str, Room], list[Import]]:
    rooms: dict[str, Room] = {}
    everything: list[Import] = []
    for path in sorted(PACKAGE.rglob("*.py")):
        room = rooms.setdefault(room_of(module_name(path)), Room(room_of(module_name(path))))
        room.lines += len(path.read_text(encoding="utf-8").splitlines())
        for item in imports_of(path):
            everything.append(item)
            target = room_of(item.target)
            if target != room.name:
                room.imports.add(target)
            room.function_imports += item.in_function
    return rooms, everything


def check(rooms: dict[str, Room] | None = None, imports: list[Import] | None = None) -> list[str]:
    """The breaches of the contract, one line each (empty when it holds)."""
    if rooms is None or imports is None:
        rooms, imports = read_package()
    problems = []
    for name in rooms:
        if name != FACE:
            try:
                layer_of(name)
            except KeyError:
                problems.append(f"dvfb.{name} has no layer in scripts/layers.py")
    for item in imports:
        source, target = room_of(item.module), room_of(item.target)
        if source == FACE or target == FACE or source == target:
            continue
        try:
            upward = layer_of(target) > layer_of(source)
        except KeyError:
            continue  # reported above
        if upward:
            problems.append(f"{item.module}:{item.line} imports {item.target}: {LAYERS[layer_of(source)][0]} "
                            f"stands below {LAYERS[layer_of(target)][0]}")
        if item.in_function and not item.comment:
            problems.append(f"{item.module}:{item.line} imports {item.target} inside a function without a comment "
                            "that says why")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="dvfb's rooms, their imports and the layers contract.")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    rooms, imports = read_package()
    problems = check(rooms, imports)

    def order(room: Room) -> tuple:
        return (layer_of(room.name) if room.name != FACE else -1, room.name)

    table = sorted(rooms.values(), key=order)
    if args.json:
        print(json.dumps({"rooms": [{"room": r.name, "layer": LAYERS[layer_of(r.name)][0] if r.name != FACE else
                                     "face", "lines": r.lines, "imports": sorted(r.imports),
                                     "function_imports": r.function_imports} for r in table],
                          "lines": sum(r.lines for r in table),
                          "function_imports": sum(r.function_imports for r in table),
                          "problems": problems}, indent=1))
    else:
        print(f"{'layer':<10} {'room':<12} {'lines':>6} {'fn-imp':>6}  imports")
        for r in table:
            layer = LAYERS[layer_of(r.name)][0] if r.name != FACE else "face"
            print(f"{layer:<10} {r.name:<12} {r.lines:>6} {r.function_imports:>6}  {', '.join(sorted(r.imports))}")
        print(f"{'':<10} {'total':<12} {sum(r.lines for r in table):>6} {sum(r.function_imports for r in table):>6}")
        for problem in problems:
            print(f"BREACH {problem}")
        print("the layers contract holds" if not problems else f"{len(problems)} breach(es)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
