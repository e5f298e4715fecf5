"""The layout's rules, read from the source: no import cycles, no private names across modules, explicit
re-exports in every package."""

from __future__ import annotations

import ast
from pathlib import Path

import meshmei

ROOT = Path(meshmei.__file__).resolve().parent


def _modules() -> dict:
    out = {}
    for p in ROOT.rglob("*.py"):
        parts = ("meshmei",) + p.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _target(mods, name, node) -> str:
    base = name.split(".") if mods[name].name == "__init__.py" else name.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _graph(mods) -> dict:
    graph = {}
    for name, path in mods.items():
        deps = set()
        for node in ast.parse(path.read_text()).body:  # module level: what runs at import
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                tgt = _target(mods, name, node)
                for a in node.names:
                    deps.add(f"{tgt}.{a.name}" if f"{tgt}.{a.name}" in mods else tgt)
        graph[name] = {d for d in deps if d in mods and d != name}
    return graph


def test_no_import_cycles():
    graph, state, cycles = _graph(_modules()), {}, []

    def visit(u, stack):
        state[u] = "open"
        for v in sorted(graph[u]):
            if state.get(v) == "open":
                cycles.append(stack[stack.index(v):] + [v])
            elif v not in state:
                visit(v, stack + [v])
        state[u] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []


def test_no_private_name_is_imported_across_modules():
    found = []
    for name, path in _modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                found += [f"{name}: {a.name}" for a in node.names if a.name.startswith("_")]
    assert found == []


def test_every_package_reexports_explicitly():
    for name, path in _modules().items():
        if path.name != "__init__.py" or name == "meshmei.benchmarks":
            continue
        tree = ast.parse(path.read_text())
        assert not any(isinstance(n, ast.ImportFrom) and any(a.name == "*" for a in n.names) for n in tree.body), name
        names = [t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)]
        assert "__all__" in names, name
