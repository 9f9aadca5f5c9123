"""The code a logged model carries (training/bundle.py): the project's own model files, nothing else needed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from torch import nn

from bronchocli import registry
from bronchocli.models import portable
from bronchocli.registry import ArchSpec
from bronchocli.training import bundle


@pytest.mark.parametrize("arch", registry.arch_names())
def test_every_architecture_ships_self_contained_code(arch):
    code = bundle.bundle_for(arch)
    assert code.problems == ()
    names = [f.name for f in code.files]
    assert names[0] == "portable.py" and {"base.py", "backbones.py"} <= set(names) and len(set(names)) == len(names)
    module, _, cls = registry.arch(arch).builder.partition(":")
    assert code.model_class == f".{module.rpartition('.')[2]}:{cls}"
    assert code.loader_module == f"{code.package}.portable" and code.package.startswith(bundle.PREFIX)


def test_a_written_bundle_builds_the_model_with_bronchocli_unimportable(tmp_path):
    """The package ``write`` makes imports and builds the architecture in a Python where bronchocli is blocked."""
    code = bundle.bundle_for("convlstm")
    bundle.write(code, tmp_path)
    script = f"""
import sys
from pathlib import Path
sys.modules["bronchocli"] = None  # any import of bronchocli fails
sys.path.insert(0, {str(tmp_path)!r})
import importlib
loader = importlib.import_module({code.loader_module!r})
model = loader.model_class({code.model_class!r})(image_size=32)
net = loader.Regressor(model, (0.5,) * 3, (0.25,) * 3)
assert net.temporal and type(model).__name__ == "ConvLSTMNet"
assert not [m for m in sys.modules if m.startswith("bronchocli") and sys.modules[m] is not None]
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                          env={"PATH": "/usr/bin:/bin", "PYTHONNOUSERSITE": "1"})
    assert done.returncode == 0, done.stderr[-2000:]


def test_the_package_name_follows_the_code(tmp_path):
    """Two models logged by different code load side by side: the package name is the files' hash."""
    before = bundle.bundle_for("baseline")
    changed = tmp_path / "portable.py"
    changed.write_bytes(Path(portable.__file__).read_bytes() + b"\n# changed\n")
    after = bundle.Bundle((changed, *before.files[1:]), before.model_class, ())
    assert after.package != before.package and bundle.bundle_for("baseline").package == before.package


class Outside(nn.Module):
    temporal = recurrent = False

    def __init__(self, image_size: int = 256, dropout: float = 0.2) -> None:
        super().__init__()


def test_an_architecture_outside_the_models_package_is_named_as_a_problem(monkeypatch):
    monkeypatch.setattr(registry, "_ARCHS", dict(registry._ARCHS))
    registry.register(ArchSpec("outside", Outside, label="x", model_name="x"))
    code = bundle.bundle_for("outside")
    assert code.model_class == f"{__name__}:Outside" and [f.name for f in code.files] == ["portable.py"]
    assert len(code.problems) == 1 and "lies outside bronchocli.models" in code.problems[0]


def test_an_import_of_the_rest_of_bronchocli_is_a_problem(tmp_path, monkeypatch):
    fake = tmp_path / "models"
    fake.mkdir()
    (fake / "portable.py").write_text("import json\nfrom . import base\n")
    (fake / "base.py").write_text("from ..errors import BronchoError\nimport pandas\nimport torch\n")
    (fake / "baseline.py").write_text("from .base import x\n")
    monkeypatch.setattr(bundle, "MODELS_DIR", fake)
    monkeypatch.setattr(portable, "__file__", str(fake / "portable.py"))
    code = bundle.bundle_for("baseline")
    assert [f.name for f in code.files] == ["portable.py", "baseline.py", "base.py"]
    assert sorted(code.problems) == ["base.py: from ..errors import ...", "base.py: import pandas"]
