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


def test_the_command_line_takes_its_defaults_from_the_settings():
    # docs/architecture.md: every default lives in one place and the CLI reads it from there
    import inspect

    from meshmei.cli import build_parser
    from meshmei.mei import MEISettings
    from meshmei.population import run_population
    from meshmei.reconstruct.settings import ReconstructionSettings

    parser = build_parser()
    mei = vars(parser.parse_args(["mei", "--out", "x"]))
    d = MEISettings()
    assert (mei["seeds"], mei["lr"], mei["valid_steps"], mei["reg_ref_vertices"]) == (
        list(d.seeds), d.lr, d.valid_steps, d.reg_ref_vertices)  # --n-vertices None: the settings' for a built-in
    population = vars(parser.parse_args(["population", "--neurons", "0", "--out", "x"]))
    signature = inspect.signature(run_population).parameters
    assert (population["batch_size"], population["pixel_steps"], population["seeds"], population["n_vertices"]) == (
        signature["batch_size"].default, signature["pixel_steps"].default, list(d.seeds), d.n_vertices)
    recon = vars(parser.parse_args(["reconstruct", "--target", "bunny", "--out", "x"]))
    r = ReconstructionSettings()
    edges = {"auto": "auto", "on": True, "off": False}[recon["contact_edges"]]
    assert (recon["method"], recon["steps"], recon["time_budget"], recon["lr"], recon["samples"], recon["eval_every"],
            recon["eval_samples"], recon["seed"], recon["valid_steps"], recon["contact_weight"], recon["facing_weight"],
            edges) == (r.method, r.steps, r.time_budget, r.lr, r.n_samples, r.eval_every, r.eval_samples, r.seed,
                       r.valid_steps, r.w_contact, r.w_facing, r.contact_edges)
