"""Issue 53, "one house": every module of the package imports on its own, no function is over 80 lines and no
command module over 250.

Imports. Each module of ``jaxdeform/`` is imported first thing in a process of its own, so that an import cycle
(a module reaching a partly initialised one) or a missing dependency fails here, whatever the test session or
the other modules happened to import before. Importing jax and its kin costs a second or two per interpreter
(tens of seconds for the ~70 modules on two cores), so one helper interpreter imports once the third-party
modules that the package's modules import at their top level, checks that no ``jaxdeform`` module is loaded
yet, then forks one child per module (two at a time): each child starts from that state -- third-party
libraries loaded, no module of the package -- imports its one module and reports. A third-party module missing
from the environment fails to preload (silently) and then fails the children of the modules that import it.
``jaxdeform.__main__`` is imported as ``python -m jaxdeform --help`` would run it (exit status 0). The children
import without the tests' jaxtyping annotation hook (it would quadruple the time; the other tests import the
module their tests use under it).

Function length. A static (ast) check: no function or method in ``jaxdeform/`` spans more than
:data:`MAX_LINES` lines, counted from its ``def`` line to its last line (``end_lineno - lineno + 1``: the
docstring included, the decorators not).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxdeform"
#: the longest function the package may hold, in lines
MAX_LINES = 80
#: children importing at once (each is mostly one CPU's work)
WORKERS = 2


def _sources() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def package_modules() -> list[str]:
    """Every module of the package, by dotted name (a package by its own name, for its ``__init__.py``)."""
    names = []
    for path in _sources():
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        names.append(".".join(parts))
    return names


def third_party_imports() -> list[str]:
    """The modules outside the package that the package's modules import at their top level (sorted)."""
    found = set()
    for path in _sources():
        for node in ast.parse(path.read_text(), str(path)).body:
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module)
    return sorted(n for n in found if n.split(".")[0] not in ("jaxdeform", "__future__"))


# Run by one fresh interpreter: argv[1] is a JSON list of the modules to import, argv[2] of those to preload,
# argv[3] a folder for the children's output. Prints one JSON object {module: error text} of the failures.
_IMPORTER = textwrap.dedent(r"""
    import importlib, json, os, sys, traceback

    modules, preload, logs = json.loads(sys.argv[1]), json.loads(sys.argv[2]), sys.argv[3]
    for name in preload:
        try:
            importlib.import_module(name)
        except Exception:  # missing or broken: the modules that import it fail in their children
            pass
    loaded = sorted(m for m in sys.modules if m == "jaxdeform" or m.startswith("jaxdeform."))
    if loaded:
        raise SystemExit(f"preloading imported modules of the package: {loaded}")

    def child(name, log):
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        status = 1
        try:
            if name == "jaxdeform.__main__":  # runs the command line: as `python -m jaxdeform --help`
                sys.argv = ["jaxdeform", "--help"]
                try:
                    importlib.import_module(name)
                except SystemExit as exc:
                    if exc.code not in (0, None):
                        raise
            else:
                importlib.import_module(name)
            status = 0
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)

    failures, running, queue = {}, {}, list(modules)
    while queue or running:
        while queue and len(running) < WORKERS:
            name = queue.pop(0)
            log = os.path.join(logs, name + ".log")
            pid = os.fork()
            if pid == 0:
                child(name, log)
            running[pid] = (name, log)
        pid, status = os.wait()
        name, log = running.pop(pid)
        code = os.waitstatus_to_exitcode(status)
        if code != 0:
            with open(log) as fh:
                failures[name] = f"exit code {code}:\n" + fh.read()[-4000:]
    print(json.dumps(failures))
""").replace("WORKERS", str(WORKERS))


def test_every_module_imports_on_its_own(tmp_path):
    modules = package_modules()
    assert "jaxdeform" in modules and "jaxdeform.mesh.render" in modules and len(modules) > 40
    proc = subprocess.run(
        [sys.executable, "-c", _IMPORTER, json.dumps(modules), json.dumps(third_party_imports()), str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    failures = json.loads(proc.stdout.strip().splitlines()[-1])
    assert not failures, "modules that fail to import on their own:\n\n" + "\n\n".join(
        f"--- {name}: {text}" for name, text in failures.items()
    )


def long_functions(limit: int = MAX_LINES) -> list[tuple[str, int, str, int]]:
    """(file, line, qualified name, length) of every function of the package longer than ``limit`` lines."""
    found = []
    for path in _sources():
        tree = ast.parse(path.read_text(), str(path))
        stack = [(tree, "")]
        while stack:
            node, prefix = stack.pop()
            for child in ast.iter_child_nodes(node):
                name = prefix
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}."
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    length = child.end_lineno - child.lineno + 1
                    if length > limit:
                        found.append((str(path.relative_to(ROOT)), child.lineno, name[:-1], length))
                stack.append((child, name))
    return sorted(found)


def test_no_function_is_over_80_lines():
    long = long_functions()
    assert not long, f"functions over {MAX_LINES} lines (split them into helpers):\n" + "\n".join(
        f"  {path}:{line} {name}: {length} lines" for path, line, name, length in long
    )


def test_the_length_check_sees_functions_and_methods():
    # the counting itself: a limit of 1 line flags every multi-line function, methods and nested ones included
    names = {name for path, _, name, _ in long_functions(limit=1) if path.endswith("components/train.py")}
    assert {"train", "make_step", "make_step.step", "_Run.stage"} <= names


def test_every_command_module_is_under_250_lines():
    # the CLI is thin: one module per method declaring its subcommands and calling the method's public API
    sizes = {p.name: len(p.read_text().splitlines()) for p in sorted((PACKAGE / "cli").glob("*.py"))}
    assert {"acap.py", "components.py", "cloth.py", "parts.py", "handles.py"} <= set(sizes)
    assert all(n < 250 for n in sizes.values()), sizes
