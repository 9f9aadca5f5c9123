"""Adding an architecture touches one place: a toy one, registered by one ``registry.register`` call, is then
built by name, profiled by `bronchopose profile`, in the grid and ``--only``, and a row of the report tables."""

from __future__ import annotations

import json

import pytest
import torch
from reporting.report_fakes import MemRuns
from torch import nn

from bronchocli import registry
from bronchocli.cells import parse_only, select
from bronchocli.config import Config, expand_grid
from bronchocli.errors import BronchoError, ConfigError
from bronchocli.models import build_model
from bronchocli.models import profile as profiling
from bronchocli.registry import ArchSpec
from bronchocli.reporting.tables import ablation, personalized


class ToyNet(nn.Module):
    """A real pose network, tiny: per pair, the two frames' mean colours through one Linear(6, 6)."""

    temporal = False
    recurrent = False
    backbone_kind = "efficientnet_b0"

    def __init__(self, image_size: int = 256, dropout: float = 0.2) -> None:
        super().__init__()
        self.head = nn.Linear(6, 6)

    def forward(self, frames: torch.Tensor, state=None):
        colour = frames.mean((-1, -2))  # [B, T, 3]
        return self.head(torch.cat([colour[:, 1:], colour[:, :-1]], -1)), None


@pytest.fixture
def toy(monkeypatch):
    monkeypatch.setattr(registry, "_ARCHS", dict(registry._ARCHS))  # the registration ends with the test
    return registry.register(ArchSpec("toy", ToyNet, label="+Toy", model_name="Toy"))  # the one place


def test_the_toy_is_built_and_profiled_by_name(toy, cli, one_thread):
    model = build_model("toy", image_size=16)
    assert isinstance(model, ToyNet) and model.name == "toy"
    assert profiling.arch_names(["all"])[-1] == "toy"
    code, out, err = cli("profile", "--arch", "toy", "--image-size", "16", "--batch", "1", "--repeats", "1",
                         "--warmup", "0", "--window", "2", "--no-channels-last", "--format", "json")
    assert code == 0, err
    (row,) = json.loads(out)
    assert row["arch"] == "toy" and row["params"] == 6 * 6 + 6
    assert row["gmacs_per_pair"] * 1e9 == pytest.approx(6 * 6)  # one Linear(6, 6) per pair


def test_the_toy_is_in_the_grid_and_only_selects_it(toy):
    cfg = Config.model_validate({"name": "t", "grid": {"rot_loss": ["ce"], "population": ["personalized"],
                                                       "seed": [0]}})
    cells = expand_grid(cfg, ["p00"])
    assert [c.arch for c in cells] == [*registry.arch_names()] and cells[-1].arch == "toy"  # the default grid
    assert [c.label for c in select(cells, parse_only(["arch=toy"]))] == ["toy/ce/personalized/s0/world"]
    explicit = Config.model_validate({"name": "t", "grid": {"arch": ["toy"], "rot_loss": ["ce"]}})
    assert {c.arch for c in expand_grid(explicit, ["p00", "p01"])} == {"toy"}


def test_without_the_registration_the_toy_is_refused_everywhere():
    with pytest.raises(ConfigError, match="arch 'toy' must be one of baseline, lstm, convlstm, conv3d, offsetnet$"):
        parse_only(["arch=toy"])
    with pytest.raises(ConfigError, match="arch 'toy': must be one of"):
        Config.model_validate({"name": "t"}).cell(arch="toy", rot_loss="ce", population="personalized")
    with pytest.raises(Exception, match="unknown architecture 'toy'"):
        build_model("toy")


def test_the_toy_is_a_row_of_the_report_tables(toy):
    m = MemRuns()
    m.add("lstm", "ce")
    m.add("toy", "ce", n_params=42)
    ctx = m.context()
    t = personalized(ctx, "accumulated")
    assert [(r.group, r.label) for r in t.rows if r.kind == "model"] == [("+LSTM", "MSE+CE"), ("+Toy", "MSE+CE")]
    a = ablation(ctx, "accumulated")
    rows = [r for r in a.rows if r.kind == "model"]
    # Table 7 names each model once, as every table does (registry.model_name: the row label and its loss)
    assert [r.label for r in rows] == ["+LSTM MSE+CE", "+Toy MSE+CE"] and rows[1].values[0] == pytest.approx(42e-6)


@pytest.mark.parametrize("name, message", [("lstm", "registered already"), ("all", "must be lower case"),
                                           ("Toy-1", "must be lower case"), ("", "must be lower case")])
def test_a_taken_or_unusable_name_is_refused(monkeypatch, name, message):
    monkeypatch.setattr(registry, "_ARCHS", dict(registry._ARCHS))
    with pytest.raises(BronchoError, match=message):
        registry.register(ArchSpec(name, ToyNet, label="x", model_name="x"))
    assert registry.arch_names() == ("baseline", "lstm", "convlstm", "conv3d", "offsetnet")
