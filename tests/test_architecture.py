"""The package's shape (docs/architecture.md): layers in order, no import circle, lazy imports justified.

A string that names a bronchocli module (``python -m bronchocli.sweep.task``, ``from bronchocli.cli import
main`` in a ``-c`` code string, an MLflow ``loader_module``) starts that module as surely as an import does:
it counts as an import of the module that holds the string ("launched"), so a lower layer cannot start a
higher one through a subprocess either.
"""

from __future__ import annotations

import ast
import re
import sys
from collections import defaultdict
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "bronchocli"

# Lowest first. A module may import modules of its own layer or of a lower one, never of a higher one.
LAYERS: list[set[str]] = [
    {"errors"},
    {"urls", "pathcheck", "io", "extras", "retry", "registry", "runkeys", "speed", "interrupts", "hostfree"},
    {"cells"},
    {"config"},
    {"geometry", "metrics", "odometry", "runs", "plots"},  # runs: MLflow run tracking
    {"anatomy", "data"},
    {"render"},
    {"generation"},
    {"models"},
    {"training"},
    {"diagnostics"},  # op counting and `bronchopose selftest`: trains, so above training
    {"inference"},
    {"sweep"},
    {"reporting"},
    {"api"},  # the public API: inference, and the work of train/report/sweep/tune/status as calls
    {"commands"},
    {"cli"},
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}


def _resolve(current: str, is_package: bool, node: ast.ImportFrom | ast.Import) -> list[str]:
    """The bronchocli modules an import statement loads."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.startswith("bronchocli")]
    if node.level:
        base = current.split(".") if is_package else current.split(".")[:-1]
        base = base[: len(base) - node.level + 1]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    if not target.startswith("bronchocli"):
        return []
    out = []
    for alias in node.names:  # ``from . import x`` may name a submodule
        sub = f"{target}.{alias.name}"
        out.append(sub if sub in MODULES else target)
    return out


def _is_type_checking(node: ast.If) -> bool:
    return isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


LAUNCHED = re.compile(r"\bbronchocli(?:\.\w+)+")  # a module path inside a string

# Launch edges that run against the layers on purpose, each with its reason (like a ``# lazy:`` comment).
ALLOWED_LAUNCHES = {
    ("bronchocli.registry", "bronchocli.models"):
        "each architecture's builder path is data: models.build_model (layer 8) resolves it, the registry never "
        "imports it; tests/models/test_architectures.py checks every path is a PoseNet inside bronchocli.models",
}


def _allowed(name: str, target: str) -> bool:
    """A launch edge listed above (the target a module, or a module inside a listed package)."""
    return any(name == src and (target == dst or target.startswith(dst + ".")) for src, dst in ALLOWED_LAUNCHES)


def _launched_module(text: str) -> str:
    """The longest bronchocli module (or package) that a dotted path in a string names."""
    parts = text.split(".")
    while len(parts) > 1 and ".".join(parts) not in MODULES:
        parts.pop()
    return ".".join(parts)


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def source_imports(name: str, source: str, is_package: bool = False) -> list[tuple[str, int, bool, bool]]:
    """(imported module, line, nested in a function, launched by a string) for every bronchocli module that the
    source of module ``name`` imports, or names in a string (docstrings aside: they describe, they do not run)."""
    tree = ast.parse(source)
    docs = _docstrings(tree)
    out: list[tuple[str, int, bool, bool]] = []

    def visit(node: ast.AST, nested: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                continue  # never executed
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for target in _resolve(name, is_package, child):
                    out.append((target, child.lineno, nested, False))
            elif isinstance(child, ast.Constant) and isinstance(child.value, str) and id(child) not in docs:
                for text in LAUNCHED.findall(child.value):
                    if not _allowed(name, target := _launched_module(text)):
                        out.append((target, child.lineno, nested, True))
            visit(child, nested or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, False)
    return out


def imports(name: str) -> list[tuple[str, int, bool, bool]]:
    path = MODULES[name]
    return source_imports(name, path.read_text(), path.name == "__init__.py")


def top_package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "cli"


def test_every_package_is_in_a_layer():
    missing = sorted({top_package(m) for m in MODULES if m != "bronchocli"} - set(RANK))
    assert not missing, f"add these to LAYERS and docs/architecture.md: {missing}"


def upward(sources: dict[str, list[tuple[str, int, bool, bool]]]) -> list[str]:
    """``module:line: src imports|launches dst`` for every edge from a lower layer to a higher one."""
    out = []
    for name, edges in sources.items():
        if name == "bronchocli":
            continue
        for target, line, _, launched in edges:
            if target == "bronchocli":
                continue
            src, dst = top_package(name), top_package(target)
            if RANK[dst] > RANK[src]:
                out.append(f"{name}:{line}: {src} {'launches' if launched else 'imports'} {dst}")
    return out


def test_no_import_from_a_lower_layer_to_a_higher_one():
    found = upward({name: imports(name) for name in MODULES})
    assert not found, "imports from a lower layer to a higher one:\n" + "\n".join(found)


@pytest.mark.parametrize("planted", [
    'MAIN = "import sys; from bronchocli.cli import main; main()"',  # the old array task's code string
    'def command():\n    return ["python", "-m", "bronchocli.commands.sweep", "--help"]',
    "LOADER = 'bronchocli.reporting.tables'",
])
def test_a_string_that_launches_a_higher_layer_is_caught(planted):
    name = "bronchocli.sweep.planted"
    source = f'"""A module whose docstring may name bronchocli.cli freely."""\n\nfrom . import plan\n\n{planted}\n'
    edges = source_imports(name, source)
    assert [e for e in edges if not e[3]] == [("bronchocli.sweep.plan", 3, False, False)]
    found = upward({name: edges})
    assert len(found) == 1 and " launches " in found[0], found
    assert upward({name: source_imports(name, '"""Runs bronchocli.cli (said, not done)."""\nX = "bronchocli"\n')}) == []


def test_the_array_task_is_launched_through_its_own_module_not_the_command_line():
    launched = {t for name in MODULES for t, _, _, how in imports(name) if how}
    assert "bronchocli.sweep.task" in launched and "bronchocli.cli" not in launched


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


def implied_packages(name: str, target: str) -> list[str]:
    """The packages Python initialises before ``target`` when module ``name`` imports it: each package above
    ``target`` that is not also above ``name`` (those are already being initialised when ``name`` runs)."""
    parts = target.split(".")
    above = {".".join(parts[:i]) for i in range(1, len(parts))}
    mine = {".".join(name.split(".")[:i]) for i in range(1, len(name.split(".")) + 1)}
    return sorted(p for p in above - mine if p in MODULES)


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules its imports run: the imported one and the packages initialised on the way."""
    graph: dict[str, set[str]] = defaultdict(set)
    for name in MODULES:
        for target, _, _, _ in imports(name):
            graph[name] |= {t for t in (target, *implied_packages(name, target)) if t != name}
    return graph


def test_no_import_circle_between_modules():
    """No circle, counting a package's ``__init__`` on the way to its modules: ``from .launchers.base import X``
    runs ``launchers/__init__.py`` first (issue 58: a circle through it held only by the import order elsewhere)."""
    assert _cycles(import_graph()) == []


def test_a_package_init_on_the_way_counts():
    assert implied_packages("bronchocli.sweep.stagework", "bronchocli.sweep.launchers.base") == [
        "bronchocli.sweep.launchers"]
    assert implied_packages("bronchocli.sweep.launchers.local", "bronchocli.sweep.stagework") == []


def test_the_circle_check_finds_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("name", sorted(MODULES))
def test_an_import_inside_a_function_says_why_it_is_lazy(name):
    """Imports inside functions hide the dependency graph: each group of them carries a ``# lazy:`` reason."""
    path = MODULES[name]
    lines = path.read_text().splitlines()
    tree = ast.parse("\n".join(lines))
    bad = []
    for func in ast.walk(tree):
        if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        previous = None
        for node in ast.walk(func):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                first_of_group = previous is None or node.lineno > previous + 1
                if first_of_group and "# lazy:" not in lines[node.lineno - 1]:
                    bad.append(f"{path.name}:{node.lineno}: {lines[node.lineno - 1].strip()}")
                previous = node.end_lineno
    assert not bad, "imports inside functions without a '# lazy: <reason>' comment:\n" + "\n".join(bad)


MAX_LINES = 500  # a module past this holds more than one job: split it (docs/architecture.md)


def test_no_module_is_over_the_size_limit():
    big = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob("*.py")
           if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not big, f"modules over {MAX_LINES} lines (split them by job): {big}"


def test_the_command_line_starts_without_the_heavy_libraries():
    """`bronchopose --help` and flag errors stay fast: MLflow, torch, Optuna and VTK load only in the command
    that needs them (each such import is a ``# lazy:`` one inside the command)."""
    import subprocess
    import sys

    code = ("import sys, bronchocli.cli; "
            "print(','.join(m for m in ('mlflow', 'torch', 'optuna', 'vtk', 'sqlalchemy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"imported at start-up: {out}"


def test_every_command_module_is_a_thin_layer():
    """Issue 47: a command parses its flags, calls the library (bronchocli.api or an entry) and prints: its module
    stays short (at most 80 lines)."""
    long = {p.name: n for p in sorted((PACKAGE / "commands").glob("*.py"))
            if (n := len(p.read_text().splitlines())) > 80}
    assert not long, f"command modules over 80 lines (move the work below the command): {long}"


COMMAND_LIBRARIES = {"typer", "rich"}  # what a command module may import besides the standard library and the API


def command_imports(name: str, source: str) -> list[str]:
    """``line: module`` for every import of a command module's source (at any depth, under ``TYPE_CHECKING`` too)
    that is not Typer, Rich, the standard library, ``bronchocli.api`` or another command module."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            targets = _resolve(name, False, node) if node.level else [node.module or ""]
        else:
            continue
        for target in targets:
            top = target.split(".")[0]
            if target.startswith("bronchocli"):
                allowed = target.split(".")[1:2] in (["api"], ["commands"])
            else:
                allowed = top in COMMAND_LIBRARIES or top in sys.stdlib_module_names or top == "__future__"
            if not allowed:
                out.append(f"{node.lineno}: {target}")
    return out


def test_every_command_module_imports_only_the_api():
    """Issue 58: every command is a thin layer over ``bronchocli.api`` (dvc's commands over one ``Repo``): a module
    of ``commands/`` imports Typer, Rich, the standard library, ``bronchocli.api`` and the other command modules,
    nothing else of bronchocli."""
    found = {p.name: hits for p in sorted((PACKAGE / "commands").glob("*.py"))
             if (hits := command_imports(f"bronchocli.commands.{p.stem}", p.read_text()))}
    assert not found, f"command modules importing below bronchocli.api (call the API instead): {found}"


@pytest.mark.parametrize("planted", [
    "from ..sweep import entry",
    "def f():\n    from ..inference import reader  # lazy: planted\n",
    "from ..config import DEFAULT_CONFIG",
    "import bronchocli.runs.client",
    "import numpy",
])
def test_the_command_import_check_finds_a_planted_import(planted):
    assert command_imports("bronchocli.commands.planted", planted + "\n")
    assert not command_imports("bronchocli.commands.planted", "from ..api import tools\nfrom .common import console\n"
                               "import typer\nfrom rich.table import Table\nfrom pathlib import Path\n")


# -- issue 47, item 2: launchers own their names, settings and signals ------------------------------------------

LAUNCHERS_PACKAGE = PACKAGE / "sweep" / "launchers"  # the launchers and their registry
BUILT_IN_LAUNCHERS = {"local", "slurm"}


def _launcher_names_compared(tree: ast.AST) -> list[int]:
    """Lines comparing a value with a built-in launcher's name (``x == "slurm"``, ``name in ("local", ...)``)."""
    lines = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Compare):
            continue
        values = []
        for side in (node.left, *node.comparators):
            elts = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
            values += [e.value for e in elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
        if BUILT_IN_LAUNCHERS & set(values):
            lines.append(node.lineno)
    return lines


def _identifiers(tree: ast.AST) -> list[tuple[int, str]]:
    """Every name the code uses or defines (variables, attributes, classes, functions, arguments), with its line."""
    out = []
    for node in ast.walk(tree):
        name = (node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else
                node.name if isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) else
                node.arg if isinstance(node, ast.arg) else None)
        if name is not None:
            out.append((node.lineno, name))
    return out


def test_no_launcher_is_named_outside_the_launchers_and_their_registry():
    """Issue 47: the launchers own their names, settings and signals. Outside ``sweep/launchers/`` no code compares
    a value with ``"local"``/``"slurm"``; ``config/`` and ``training/`` hold no Slurm type or setting
    (``SlurmCfg``, ``cfg.slurm``, ``slurm_logs``) and training hard-codes no launcher's signal (SIGUSR1)."""
    compared, slurm_in_core = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        if LAUNCHERS_PACKAGE in path.parents:
            continue
        tree = ast.parse(path.read_text())
        where = str(path.relative_to(PACKAGE.parent))
        compared += [f"{where}:{n}" for n in _launcher_names_compared(tree)]
        if path.parent.name in ("config", "training"):
            slurm_in_core += [f"{where}:{n}: {name}" for n, name in _identifiers(tree)
                              if "slurm" in name.lower() or name == "SIGUSR1"]
    assert not compared, f"launcher names compared outside sweep/launchers/ (ask the launcher instead): {compared}"
    assert not slurm_in_core, f"Slurm names in config/ or training/ (they belong to its launcher): {slurm_in_core}"


@pytest.mark.parametrize("code, found", [
    ("if kind.name == 'local':\n    pass\n", True), ("ok = 'slurm' != launcher\n", True),
    ("ok = name in ('local', 'slurm')\n", True), ("ok = name == 'other'\n", False),
])
def test_the_launcher_name_check_finds_a_comparison(code, found):
    assert bool(_launcher_names_compared(ast.parse(code))) is found
