"""The modules under experiments/ import on their own, import one another without a cycle (also through the imports
inside functions, which an import alone never runs), and take no private name of another module."""

from __future__ import annotations

import ast
from pathlib import Path

from fresh_process import run_script

ROOT = Path(__file__).resolve().parents[1]
PROJECT = ("experiments", "jaxdeform", "benchmarks")  # the packages of this repository


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted((ROOT / "experiments").rglob("*.py"))}


def _is_module(name: str) -> bool:
    base = ROOT.joinpath(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _imports(path: Path) -> list[tuple[str, str | None, int]]:
    """(module, name imported from it or None, line) of every import statement of ``path``, in functions too."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out += [(node.module, a.name, node.lineno) for a in node.names]
    return out


def test_every_experiment_module_imports_alone():
    """One fresh interpreter; before each module every ``experiments`` module is dropped from ``sys.modules``, so
    that each is imported with no other experiment loaded, as ``python -c "import M"`` would (the library and
    third-party packages, which import no experiment, stay loaded: seconds, not an interpreter start per module)."""
    assert "experiments.components.editing" in MODULES and "experiments.charts" in MODULES
    run_script(
        f"""
        import importlib, sys, traceback
        failed = []
        for name in {sorted(MODULES)!r}:
            for loaded in [m for m in sys.modules if m == "experiments" or m.startswith("experiments.")]:
                del sys.modules[loaded]
            try:
                importlib.import_module(name)
            except Exception:
                failed.append(name + ": " + traceback.format_exc())
        assert not failed, "\\n".join(failed)
        print("OK")
    """,
        timeout=600,
    )


def test_no_import_cycle_among_experiments():
    """The graph of ``experiments`` modules importing one another (``from experiments.a import b`` counts as
    importing module ``experiments.a.b`` where that is a module, and ``experiments.a`` otherwise) has no cycle."""
    graph = {}
    for name, path in MODULES.items():
        deps = set()
        for module, imported, _ in _imports(path):
            if module.split(".")[0] != "experiments":
                continue
            sub = f"{module}.{imported}" if imported else None
            deps.add(sub if sub and _is_module(sub) else module)
        graph[name] = deps & set(MODULES)
    cycles = []

    def visit(node, stack):
        for dep in sorted(graph[node]):
            if dep in stack:
                cycles.append(stack[stack.index(dep) :] + [dep])
            elif dep not in done:
                visit(dep, stack + [dep])
        done.add(node)

    done: set[str] = set()
    for name in sorted(graph):
        if name not in done:
            visit(name, [name])
    assert not cycles, cycles
    assert "experiments.components.common" in graph["experiments.components.editing"]  # the graph sees imports


def test_no_private_name_of_another_module():
    """No ``from M import _x`` nor ``m._x`` where ``m`` names a module of this repository bound by an import."""
    found = []
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text(), str(path))
        modules = {}  # name bound by an import -> the repository module it is
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in PROJECT:
                        bound = a.asname or a.name.split(".")[0]  # `import a.b` binds a, `import a.b as x` x
                        modules[bound] = a.name if a.asname else bound
            elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] in PROJECT:
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        found.append(f"{name}:{node.lineno}: from {node.module} import {a.name}")
                    if _is_module(f"{node.module}.{a.name}"):
                        modules[a.asname or a.name] = f"{node.module}.{a.name}"
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in modules
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                found.append(f"{name}:{node.lineno}: {modules[node.value.id]}.{node.attr}")
    assert not found, found
