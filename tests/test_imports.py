"""Dependencies run one way: no import cycle between the modules of ``core`` and ``app``, nor
between their packages; ``core`` imports nothing of ``app`` or ``bench``, and the tests nothing of
``bench`` (but its own tests)."""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def import_graph(*packages: str) -> dict[str, set[str]]:
    """Module -> the modules of ``packages`` it imports, anywhere in its body (lazy imports too)."""
    paths = {_name(p): p for pkg in packages for p in sorted((ROOT / pkg).rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in paths.items():
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found.add(node.module)
                found.update(f"{node.module}.{alias.name}" for alias in node.names)
        graph[name] = {m for m in found if m in paths and m != name}
    return graph


def _unit(module: str) -> str:
    """A subpackage (``app.jobs``, ``core.formats``) for its modules; any other module itself."""
    parts = module.split(".")
    return ".".join(parts[:2]) if len(parts) > 2 or (ROOT / module.replace(".", "/")).is_dir() else module


def test_no_import_cycle_between_modules() -> None:
    graphlib.TopologicalSorter(import_graph("core", "app")).prepare()  # raises CycleError


def test_no_import_cycle_between_packages() -> None:
    units: dict[str, set[str]] = {}
    for module, deps in import_graph("core", "app").items():
        here = _unit(module)
        units.setdefault(here, set()).update(u for u in map(_unit, deps) if u != here)
    graphlib.TopologicalSorter(units).prepare()


def test_core_does_not_import_the_service() -> None:
    for module, deps in import_graph("core", "app", "bench").items():
        if module.startswith("core"):
            assert not {d for d in deps if not d.startswith("core")}, module


def test_tests_do_not_import_the_benchmarks() -> None:
    """Only the benchmarks' own tests (``tests/bench``) may; the benchmarks reuse test helpers,
    never the other way round."""
    for module, deps in import_graph("tests", "bench").items():
        if module.startswith("tests") and not module.startswith("tests.bench"):
            assert not {d for d in deps if d.startswith("bench")}, module


def test_a_cycle_is_found() -> None:
    with pytest.raises(graphlib.CycleError):
        graphlib.TopologicalSorter({"a": {"b"}, "b": {"c"}, "c": {"a"}}).prepare()
