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

from rebel_jax.cli import collector_paused

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
    assert {"rebel_jax.train", "rebel_jax.cli", "rebel_jax.reward_model", "rebel_jax.methods.surf"} <= set(graph)
    assert "rebel_jax.reward_model" in graph["rebel_jax.methods.surf"]  # The graph sees the package's own imports.
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_train_does_not_import_the_command_line():
    graph = import_graph(SRC, "rebel_jax")
    assert "rebel_jax.cli" not in graph["rebel_jax.train"]
    assert "rebel_jax.train" in graph["rebel_jax.cli"]


def test_the_methods_terms_import_the_reward_model_and_not_the_reverse():
    graph = import_graph(SRC, "rebel_jax")
    for method in ("rebel_jax.methods.surf", "rebel_jax.methods.rebel"):
        assert "rebel_jax.reward_model" in graph[method]
        assert method not in graph["rebel_jax.reward_model"]


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
