"""The package's three layers import only downward, and no module imports itself back.

    command line   dcsc_torchrl.cli                  parses and dispatches; nothing imports it
    application    dcsc_torchrl.recipes (recipes/)   grid driver, sweep, reproduce, report, play,
                                                     pretraining train(cfg) functions, yamls
    library        every other dcsc_torchrl module   imports neither of the above
                   (dcsc_torchrl.envs is envs/)

Inside the library the task registry (:mod:`dcsc_torchrl.tasks`) sits on top: it wires
the library's factories into :class:`~dcsc_torchrl.task.Task` entries, and no library
module imports it (they take a ``Task``). The graph is read from the source with
:mod:`ast`, imports inside functions included, so a lazy import counts as much as a
top-level one. docs/architecture.md, "Layers".
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_DIRS = {"dcsc_torchrl": ROOT / "dcsc_torchrl", "dcsc_torchrl.envs": ROOT / "envs",
                "dcsc_torchrl.recipes": ROOT / "recipes"}
"""Where each package's files are (pyproject's package-dir)."""


def modules() -> dict[str, Path]:
    """Every module of the installed package, by dotted name."""
    found = {}
    for package, folder in PACKAGE_DIRS.items():
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((package, *parts)).removesuffix(".__init__")
            found[name] = path
    return found


MODULES = modules()


def imports_of(name: str, path: Path) -> set[str]:
    """The project modules ``name`` imports (the longest known prefix of each import)."""
    is_package = path.name == "__init__.py"
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            candidates = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")[: len(name.split(".")) - (node.level - is_package)]
                base = ".".join([*anchor, base] if base else anchor)
            candidates = [base, *(f"{base}.{alias.name}" for alias in node.names)]
        else:
            continue
        for candidate in candidates:
            while candidate and candidate not in MODULES:
                candidate = candidate.rpartition(".")[0]
            if candidate and candidate != name:
                targets.add(candidate)
    return targets


GRAPH = {name: imports_of(name, path) for name, path in MODULES.items()}


def layer(name: str) -> int:
    """2: the command line, 1: the application, 0: the library."""
    if name == "dcsc_torchrl.cli":
        return 2
    return 1 if name == "dcsc_torchrl.recipes" or name.startswith("dcsc_torchrl.recipes.") else 0


def test_layers_import_only_downward():
    upward = sorted(f"{name} -> {target}" for name, targets in GRAPH.items() for target in targets
                    if layer(target) > layer(name) or (layer(target) == 2 and name != target))
    assert not upward, "upward imports: " + "; ".join(upward)


def test_no_library_module_imports_the_task_registry():
    registry = "dcsc_torchrl.tasks"
    users = sorted(name for name, targets in GRAPH.items() if registry in targets and layer(name) == 0)
    assert not users, f"library modules importing the registry: {users}"


def strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components with more than one module (the import cycles)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    return cycles


def test_the_import_graph_has_no_cycles():
    # a package's __init__ re-exporting its submodules is not a cycle of jobs: leave those edges out
    graph = {name: {t for t in targets if not (MODULES[name].name == "__init__.py" and t.startswith(f"{name}."))}
             for name, targets in GRAPH.items()}
    assert strongly_connected(graph) == []


def test_strongly_connected_finds_a_cycle():
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_the_wheel_installs_one_top_level_package(tmp_path):
    """A built wheel holds ``dcsc_torchrl`` only (no generic ``envs`` or ``recipes``), with the yamls.

    Built from a copy of the sources, so no ``build/`` folder of an earlier build leaks into it."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", *PACKAGE_DIRS.values()):
        path = ROOT / name
        copy = shutil.copytree if path.is_dir() else shutil.copy
        copy(path, source / path.relative_to(ROOT), **({"ignore": shutil.ignore_patterns("__pycache__")}
                                                      if path.is_dir() else {}))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(tmp_path), str(source)], check=True)
    (wheel,) = tmp_path.glob("dcsc_torchrl-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {name.split("/")[0] for name in names if not name.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"dcsc_torchrl"}
    assert "dcsc_torchrl/envs/uav.py" in names
    assert "dcsc_torchrl/recipes/shared_control_lunarlander.yaml" in names


def test_gymnasium_finds_both_ids_with_no_import_of_ours():
    """gymnasium 1.x has no plugin entry points: its ``module:id`` form imports ours for it."""
    code = ("import sys, gymnasium as gym\n"
            "assert 'dcsc_torchrl' not in sys.modules\n"
            "for env_id in ('dcsc/TargetLunarLander-v0', 'dcsc/UAVPathPlanning-v0'):\n"
            "    gym.make('dcsc_torchrl.envs:' + env_id).close()\n"
            "    gym.make(env_id).close()\n"
            "import importlib.util\n"
            "assert importlib.util.find_spec('envs') is None and importlib.util.find_spec('recipes') is None\n")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT.parent)
