"""Imports flow one way: no module of the package imports, even lazily or transitively, a module that imports it.

A static check with ``ast``: every ``import`` and ``from ... import`` anywhere in a module (at the top,
inside a function, under ``if __name__ == "__main__"``) is an edge to the package's module it names.
``from pkg import name`` is an edge to the submodule ``pkg.name`` when there is one, else to ``pkg``
(its ``__init__``); a parent package's ``__init__`` that Python runs on the way is not counted, so a
package may import its own submodules.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

from rebel_jax.run.cli import collector_paused

SRC = pathlib.Path(__file__).resolve().parents[1] / "src"


def module_files(root: pathlib.Path, package: str) -> dict[str, pathlib.Path]:
    """Dotted module name -> file, for every ``.py`` file of ``package`` under ``root``."""
    modules = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _resolve(module: str, is_package: bool, level: int, target: str | None) -> str:
    """The absolute name of ``from <level dots><target> import ...`` written in ``module``."""
    if level == 0:
        return target or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def _parse(path: pathlib.Path) -> ast.Module:
    """``ast.parse`` with the collector paused: a finalizer that parses source during the parse breaks it on
    CPython 3.11 (``cli.collector_paused``; gh-106905), and the test workers hold such garbage."""
    with collector_paused():
        return ast.parse(path.read_text(), str(path))


def import_graph(root: pathlib.Path, package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (anywhere in its source)."""
    modules = module_files(root, package)
    graph = {}
    for name, path in modules.items():
        is_package = path.name == "__init__.py"
        edges = set()
        for node in ast.walk(_parse(path)):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                source = _resolve(name, is_package, node.level, node.module)
                targets = [
                    f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source for alias in node.names
                ]
            else:
                continue
            for target in targets:
                while target and target not in modules:  # ``import pkg.mod.attr`` style: the longest module prefix.
                    target = target.rpartition(".")[0]
                if target and target != name:
                    edges.add(target)
        graph[name] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle ``[a, b, ..., a]`` of ``graph``, or None (depth-first search, three colours)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done.
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for succ in sorted(graph.get(node, ())):
            if state.get(succ) == 1:
                return path[path.index(succ) :] + [succ]
            if succ not in state and (cycle := visit(succ)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def _write_package(root: pathlib.Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_package_has_no_import_cycle():
    graph = import_graph(SRC, "rebel_jax")
    assert {
        "rebel_jax.train",
        "rebel_jax.run.cli",
        "rebel_jax.preference.reward_model",
        "rebel_jax.methods.surf",
    } <= set(graph)
    assert "rebel_jax.preference.reward_model" in graph["rebel_jax.methods.surf"]  # it sees the package's imports
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


LAYERS = ("core", "envs", "agents", "preference", "methods", "config", "train", "api", "run")
"""The package's layers, bottom first (each package's docstring says what it may import): a module may import its
own layer and those below it, never one above."""


def layer(module: str) -> int:
    """The index in :data:`LAYERS` of ``module``'s layer (``rebel_jax.X...``; the package's root sits below all)."""
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 else -1


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """``a -> b`` for each import of ``graph`` from a lower layer to a higher one."""
    return sorted(f"{a} -> {b}" for a, targets in graph.items() for b in targets if layer(b) > layer(a))


def test_every_top_level_entry_is_a_layer():
    entries = {p.stem for p in (SRC / "rebel_jax").iterdir() if p.name != "__pycache__"} - {"__init__"}
    assert entries == set(LAYERS)


def test_imports_flow_down_the_layers():
    graph = import_graph(SRC, "rebel_jax")
    assert "rebel_jax.config" in graph["rebel_jax.train.trainer"]  # the graph sees imports across layers
    assert upward_imports(graph) == []


def test_an_upward_import_is_caught():
    graph = {"rebel_jax.agents.sac": {"rebel_jax.config"}, "rebel_jax.run.cli": {"rebel_jax.train"}}
    assert upward_imports(graph) == ["rebel_jax.agents.sac -> rebel_jax.config"]


def test_train_does_not_import_the_command_line():
    graph = import_graph(SRC, "rebel_jax")
    assert not any(b.startswith("rebel_jax.run") for b in graph["rebel_jax.train.trainer"])
    assert "rebel_jax.train" in graph["rebel_jax.run.cli"]


def test_the_methods_terms_import_the_reward_model_and_not_the_reverse():
    graph = import_graph(SRC, "rebel_jax")
    for method in ("rebel_jax.methods.surf", "rebel_jax.methods.rebel"):
        assert "rebel_jax.preference.reward_model" in graph[method]
        assert method not in graph["rebel_jax.preference.reward_model"]


@pytest.mark.parametrize(
    "files,expected",
    [
        # A lazy import inside a function closes the circle a -> b -> a.
        ({"a.py": "from pkg import b\n", "b.py": "def f():\n    import pkg.a\n"}, ["pkg.a", "pkg.b", "pkg.a"]),
        # Under the entry-point guard, and through a relative import and a third module.
        (
            {
                "a.py": "from . import b\n",
                "b.py": "from .sub.c import thing\n",
                "sub/__init__.py": "",
                "sub/c.py": "if __name__ == '__main__':\n    from ..a import x\n",
            },
            ["pkg.a", "pkg.b", "pkg.sub.c", "pkg.a"],
        ),
        # One way only: no cycle; a package importing its own submodule is no cycle either.
        ({"__init__.py": "from pkg.a import x\n", "a.py": "import os\nfrom pkg import b\n", "b.py": ""}, None),
    ],
)
def test_the_check_finds_cycles_in_a_written_package(tmp_path, files, expected):
    _write_package(tmp_path / "pkg", files)
    assert find_cycle(import_graph(tmp_path, "pkg")) == expected
