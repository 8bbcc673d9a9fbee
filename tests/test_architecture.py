"""The package's structure, read from its sources: the layout stays one a newcomer can walk.

The import graph of ``tertiary`` and ``safety`` has no cycle; no module is over 800 lines; at most
eight modules sit directly under ``tertiary/``; imports inside functions only defer an optional
dependency; no module imports another's private names; ``safety`` builds on the core and the
contract only; importing ``tertiary`` leaves the process's environment as it was.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tertiary", "safety")
MAX_LINES = 800
MAX_TOP_MODULES = 8
#: optional dependencies a function may import when it needs them (the ``dask`` and ``bench`` extras)
OPTIONAL = ("dask", "distributed", "stonesoup")
#: heavy dependencies a function may defer so that commands which do not need them start fast
DEFERRED_FOR_START_UP = ("asterix",)        # libasterix: ~2.4 s to import; only ASTERIX commands use it
#: sub-package dependencies both ways that remain (module level they form no cycle), with why
KNOWN_PACKAGE_LOOPS = {
    ("tertiary.io", "tertiary.simulate"): "a dataset's scenario.toml is a simulate.config.ScenarioConfig, and "
                                          "ADS-B trajectories are simulate.trajectory.Trajectories",
}
#: what ``safety`` may import from ``tertiary``
SAFETY_MAY_USE = ("tertiary.core", "tertiary.contract")


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def sources() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


@dataclass
class Imports:
    top: set[str] = field(default_factory=set)          # imported at module level
    deferred: list[tuple[int, str]] = field(default_factory=list)   # (line, module) inside a function
    private: list[tuple[int, str]] = field(default_factory=list)    # (line, "module._name")


def _targets(node: ast.AST, mods: dict[str, Path], here: str) -> list[tuple[str, str | None]]:
    """(module, imported name) pairs an import statement names; a name that is a module counts as one."""
    out: list[tuple[str, str | None]] = []
    if isinstance(node, ast.Import):
        out += [(a.name, None) for a in node.names]
    elif isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:
            pkg = here.split(".")
            pkg = pkg[: len(pkg) - node.level + (1 if mods.get(here, Path()).name == "__init__.py" else 0)]
            base = ".".join([*pkg, base] if base else pkg)
        for a in node.names:
            full = f"{base}.{a.name}"
            out.append((full, None) if full in mods else (base, a.name))
    return out


def read_imports(name: str, path: Path, mods: dict[str, Path]) -> Imports:
    tree = ast.parse(path.read_text(), str(path))
    res = Imports()
    bound: set[str] = set()      # local names bound to a package module

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for mod, attr in _targets(child, mods, name):
                    if in_function:
                        res.deferred.append((child.lineno, mod))
                    if mod.split(".")[0] in PACKAGES:
                        res.top.add(mod)
                        if attr and attr.startswith("_") and not attr.startswith("__"):
                            res.private.append((child.lineno, f"{mod}.{attr}"))
                for a in child.names:
                    if isinstance(child, ast.ImportFrom) and f"{_targets(child, mods, name)[0][0]}" in mods:
                        bound.add(a.asname or a.name)
                    elif isinstance(child, ast.Import) and a.name.split(".")[0] in PACKAGES and a.asname:
                        bound.add(a.asname)
            visit(child, nested)

    visit(tree, False)
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in bound
                and node.attr.startswith("_") and not node.attr.startswith("__")):
            res.private.append((node.lineno, f"{node.value.id}.{node.attr}"))
    return res


@pytest.fixture(scope="module")
def graph() -> dict[str, Imports]:
    mods = sources()
    return {n: read_imports(n, p, mods) for n, p in mods.items()}


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph (a list of nodes, the first repeated last), or None."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(edges, WHITE)
    stack: list[str] = []

    def dfs(u: str) -> list[str] | None:
        colour[u] = GREY
        stack.append(u)
        for v in sorted(edges.get(u, ())):
            if colour.get(v, BLACK) == GREY:
                return stack[stack.index(v):] + [v]
            if colour.get(v) == WHITE and (c := dfs(v)):
                return c
        stack.pop()
        colour[u] = BLACK
        return None

    for node in sorted(edges):
        if colour[node] == WHITE and (c := dfs(node)):
            return c
    return None


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_no_import_cycle(graph):
    edges = {n: {m for m in imp.top if m in graph and m != n} for n, imp in graph.items()}
    assert find_cycle(edges) is None


def test_no_package_cycle(graph):
    """Between the sub-packages (``tertiary.stages``, ``safety`` …) too: the layout reads one way."""
    def pkg(m: str) -> str:
        return ".".join(m.split(".")[:2]) if m.startswith("tertiary.") else m.split(".")[0]
    edges: dict[str, set[str]] = {}
    for n, imp in graph.items():
        edges.setdefault(pkg(n), set()).update(pkg(m) for m in imp.top if m in graph and pkg(m) != pkg(n))
    edges.pop("tertiary", None)          # the package's own __init__ gathers the public names
    for e in edges.values():
        e.discard("tertiary")
    for a, b in KNOWN_PACKAGE_LOOPS:
        edges.get(a, set()).discard(b)
    assert find_cycle(edges) is None


def test_no_module_over_the_line_limit():
    long = {n: c for n, p in sources().items() if (c := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_few_modules_directly_under_the_package():
    top = sorted(p.name for p in (ROOT / "tertiary").glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, top


def test_functions_import_only_optional_dependencies(graph):
    bad = [f"{n}:{line} {m}" for n, imp in graph.items() for line, m in imp.deferred
           if m.split(".")[0] not in (*OPTIONAL, *DEFERRED_FOR_START_UP)]
    assert not bad, bad


def test_no_private_name_imported_across_modules(graph):
    bad = [f"{n}:{line} {what}" for n, imp in graph.items() for line, what in imp.private]
    assert not bad, bad


def test_safety_builds_on_the_core_and_the_contract_only(graph):
    bad = [f"{n} -> {m}" for n, imp in graph.items() if n.split(".")[0] == "safety"
           for m in imp.top if m.startswith("tertiary") and not m.startswith(SAFETY_MAY_USE)]
    assert not bad, bad


def test_importing_the_package_changes_nothing_in_the_process():
    code = ("import os, json; before = dict(os.environ); import tertiary; "
            "print(json.dumps(sorted(set(os.environ.items()) ^ set(before.items()))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={k: v for k, v in os.environ.items() if "MALLOC_CONF" not in k})
    assert out.stdout.strip() == "[]"


def test_public_names_are_few():
    import tertiary
    assert 15 <= len(tertiary.__all__) <= 40
    assert all(hasattr(tertiary, n) for n in tertiary.__all__)


def test_every_sub_package_is_installed():
    """A sub-package missing from pyproject's package list would be absent from the wheel."""
    import tomllib
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for pkg in PACKAGES for p in (ROOT / pkg).rglob("__init__.py")}
    assert not found - listed, sorted(found - listed)
