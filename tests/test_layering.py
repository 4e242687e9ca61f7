"""The architecture's rules (docs/DESIGN.md, "What each folder may import"), read from the
code's own imports, module-level and inside functions alike:

- ``diffplan/`` (the method) imports nothing from ``envs/`` or ``experiments/``;
- ``envs/`` (the worlds) imports nothing from ``experiments/``;
- no package has an import circle (a module that, through its imports, imports itself);
- inside ``experiments/``, a subpackage imports only those on floors below its own: the shared
  ``harness`` first, then one per world (``gridworld``, ``kuka``, ``babyai``), then those over
  the worlds (``sweeping``, ``bench``, ``shipping``); the entry points at the top may import any;
- no module under ``experiments/`` is longer than 250 lines.
"""
from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("diffplan", "envs", "experiments")
MAX_EXPERIMENT_LINES = 250
EXPERIMENT_FLOORS = {"harness": 0, "gridworld": 1, "kuka": 1, "babyai": 1, "sweeping": 2,
                     "bench": 2, "shipping": 2}
"""The subpackages of experiments/ by floor: each imports only subpackages of lower floors."""


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def all_modules() -> dict[str, pathlib.Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def imports_of(path: pathlib.Path, name: str, known: set[str]) -> set[str]:
    """The project modules ``path`` (module ``name``) imports, anywhere in its code. ``from
    a.b import c`` counts as an import of ``a.b.c`` when that is a module, else of ``a.b``."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                       for alias in node.names]
        else:
            continue
        for target in targets:
            # the longest project module that the imported name starts with
            parts = target.split(".")
            for end in range(len(parts), 0, -1):
                candidate = ".".join(parts[:end])
                if candidate in known:
                    out.add(candidate)
                    break
    out.discard(name)
    return out


def import_graph() -> dict[str, set[str]]:
    modules = all_modules()
    known = set(modules)
    return {name: imports_of(path, name, known) for name, path in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_circle_finder_finds_circles_and_nothing_else():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set(), "c": {"b"}}) == []


def test_the_import_reader_resolves_from_imports_to_modules():
    graph = import_graph()
    assert "diffplan.sampler" in graph["diffplan"]       # from diffplan.sampler import sample
    assert "envs.gridworld.episode" in graph["envs.gridworld.task"]


@pytest.mark.parametrize("package, forbidden", [("diffplan", ("envs", "experiments")),
                                                ("envs", ("experiments",))])
def test_lower_layers_never_import_upper_ones(package, forbidden):
    graph = import_graph()
    bad = sorted(f"{m} imports {t}" for m, targets in graph.items()
                 if m == package or m.startswith(package + ".")
                 for t in targets if t.split(".")[0] in forbidden)
    assert not bad, bad


def experiment_subpackage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "experiments" and len(parts) > 2 else None


def test_experiment_subpackages_import_only_lower_floors():
    graph = import_graph()
    found = {experiment_subpackage(m) for m in graph} - {None}
    assert found == set(EXPERIMENT_FLOORS), found   # a new subpackage gets its floor here
    bad = sorted(f"{m} imports {t}" for m, targets in graph.items()
                 if (own := experiment_subpackage(m)) for t in targets
                 if t.startswith("experiments.") and (other := experiment_subpackage(t))
                 and other != own and EXPERIMENT_FLOORS[other] >= EXPERIMENT_FLOORS[own])
    assert not bad, bad


def test_no_import_circles():
    assert circles(import_graph()) == []


def test_experiment_modules_are_short():
    long = {str(p.relative_to(ROOT)): n for p in (ROOT / "experiments").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_EXPERIMENT_LINES}
    assert not long, long
