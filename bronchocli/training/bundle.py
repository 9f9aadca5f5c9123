"""The code a logged MLflow Model carries, so that it loads where bronchocli is not installed.

A bundle is a Python package ``bronchopose_model_<hash>`` holding copies, byte
for byte, of ``models/portable.py`` (the pyfunc loader and predictor) and of
the model modules it needs: the architecture's own file and what it imports
relatively (``base.py``, ``backbones.py``), found by reading their imports.
These files are the project's own source (one copy of each model); only the
package's ``__init__.py`` is written here. The hash of the files names the
package, so two models logged by different versions of the code load side by
side in one Python (MLflow puts each model's ``code/`` folder on ``sys.path``
and Python imports a package name once).

A shipped file may import the standard library, numpy, torch, Pillow and the
files beside it; anything else (the rest of bronchocli) is a ``problem``:
tests/training/test_bundle.py checks that every registered architecture has
none, and logging a model with one warns that it needs that code to load.
"""

from __future__ import annotations

import ast
import hashlib
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from .. import registry
from ..models import portable

PREFIX = "bronchopose_model_"  # the bundle's package name: PREFIX + hash of its files
LOADER = "portable"  # the module of the bundle MLflow imports (``<package>.portable``)
ALLOWED = frozenset({"torch", "numpy", "PIL"})  # third-party imports a shipped file may make
MODELS_DIR = Path(portable.__file__).parent
MODELS_PACKAGE = portable.__name__.rpartition(".")[0]  # "bronchocli.models"


@dataclass(frozen=True)
class Bundle:
    files: tuple[Path, ...]  # the project's source files it copies, portable.py first
    model_class: str  # ".baseline:BaselineNet" (a shipped module) or "package.module:Class" (not shipped)
    problems: tuple[str, ...]  # imports that leave the bundle; empty when it is self-contained

    @property
    def package(self) -> str:
        digest = hashlib.sha256()
        for path in self.files:
            digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
        return PREFIX + digest.hexdigest()[:12]

    @property
    def loader_module(self) -> str:
        return f"{self.package}.{LOADER}"


def _class_path(arch: str) -> tuple[str, str]:
    builder = registry.arch(arch).builder
    if isinstance(builder, str):
        module, _, attr = builder.partition(":")
    else:  # a class registered directly (a test's toy architecture)
        module, attr = builder.__module__, builder.__qualname__
    return module, attr


def _imports(path: Path) -> tuple[set[str], list[str]]:
    """The sibling modules ``path`` imports relatively, and what else it imports that a bundle cannot hold."""
    siblings, outside = set(), []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            siblings |= {node.module.split(".")[0]} if node.module else {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level > 1:
            outside.append(f"{path.name}: from {'.' * node.level}{node.module or ''} import ...")
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            outside += [f"{path.name}: import {n}" for n in names if not _allowed(n)]
    return siblings, outside


def _allowed(module: str) -> bool:
    top = module.split(".")[0]
    return top in ALLOWED or top in sys.stdlib_module_names or top == "__future__"


def bundle_for(arch: str) -> Bundle:
    """What a model of architecture ``arch`` must carry (see the module doc)."""
    module, attr = _class_path(arch)
    files, problems = [Path(portable.__file__)], []
    package, _, name = module.rpartition(".")
    if package == MODELS_PACKAGE and (MODELS_DIR / f"{name}.py").is_file():
        files.append(MODELS_DIR / f"{name}.py")
        model_class = f".{name}:{attr}"
    else:
        model_class = f"{module}:{attr}"
        problems.append(f"{model_class} lies outside {MODELS_PACKAGE}: loading the model needs it installed")
    todo = list(files)
    while todo:
        siblings, outside = _imports(todo.pop())
        problems += outside
        for sibling in sorted(siblings):
            path = MODELS_DIR / f"{sibling}.py"
            if not path.is_file():
                problems.append(f"{MODELS_PACKAGE}.{sibling} is not a module file that can be shipped")
            elif path not in files:
                files.append(path)
                todo.append(path)
    return Bundle(tuple(files), model_class, tuple(problems))


def write(bundle: Bundle, parent: Path) -> Path:
    """The bundle as a package folder ``parent/<package>/`` (what ``code_paths`` ships); returns it."""
    folder = parent / bundle.package
    folder.mkdir(parents=True)
    for path in bundle.files:
        shutil.copyfile(path, folder / path.name)
    (folder / "__init__.py").write_text(
        f'"""bronchopose model code, copied from {MODELS_PACKAGE} ({", ".join(p.name for p in bundle.files)}): '
        f'MLflow imports {bundle.loader_module}."""\n', encoding="utf-8")
    return folder
