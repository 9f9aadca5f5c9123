"""One model, one name (issues 48, 57): every table row, figure legend, UI run name, run and logged-model description
of a fabricated sweep comes from ``registry.model_name``, the paper's names: "BronchoTrack", "OffsetNet", else the
paper's row label and loss ("+ConvRNN MSE+DE"); a backbone other than the paper's adds itself and the
initialisation. The same check on a tiny real sweep is ``test_one_name.py``."""

from __future__ import annotations

import re

import pytest
from mlflow.entities import Param, RunTag

from bronchocli import registry
from bronchocli.cells import Cell
from bronchocli.reporting import curves, figures, report, tables
from bronchocli.reporting.collect import RunRecord
from bronchocli.reporting.figures import errors_loader, make_figures, mlflow_loader
from bronchocli.runs.records import run_name


def test_the_registry_names_each_model_once():
    assert registry.model_name("convlstm", "ce") == "BronchoTrack"  # the paper's name (Table 6)
    assert registry.model_name("offsetnet", "mse") == "OffsetNet"
    assert registry.model_name("convlstm", "de") == "+ConvRNN MSE+DE"  # the paper's Tables 2-3 row labels
    assert registry.model_name("baseline", "mse") == "Baseline MSE+MSE"
    assert registry.model_name("offsetnet", "ce") == "OffsetNet MSE+CE"
    assert registry.model_name("gone", "old") == "gone old"  # an old run's unregistered tags, as they are
    # grouped tables: the paper's labels, and the paper's name where it gives one
    assert registry.grouped_label("convlstm", "de") == "MSE+DE"
    assert registry.grouped_label("convlstm", "ce") == "MSE+CE (BronchoTrack)"


@pytest.mark.parametrize("backbone, init, suffix", [
    (None, "imagenet:efficientnet_b0.pth", ""), ("efficientnet_b0", "random", ""),  # the paper's: no suffix
    ("efficientnet_lite0", "imagenet:efficientnet_lite0.pth", " · Lite0 ImageNet"),
    ("efficientnet_lite0", "random", " · Lite0 random"),
    ("efficientnet_lite0", "file:mine.pt#0a1b", " · Lite0 mine.pt")])
def test_a_backbone_other_than_the_papers_is_named(backbone, init, suffix):
    assert registry.model_name("convlstm", "ce", backbone, init) == "BronchoTrack" + suffix
    assert registry.grouped_label("lstm", "de", backbone, init) == "MSE+DE" + suffix
    assert registry.grouped_label("convlstm", "ce", backbone, init) == f"MSE+CE (BronchoTrack{suffix})"


TAGS = {"arch": "baseline", "rot_loss": "ce", "population": "personalized", "fold": "", "seed": "0",
        "pose_frame": "world", "train_trajectories": ""}


def test_runs_that_carry_the_backbone_param_are_named_with_it(tmp_path):
    """A run logged with the param ``model.backbone`` and the tag ``init`` (as training logs them): its name in the
    report (RunRecord.model, .title) says the backbone; one without the param is the paper's."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{tmp_path / 'm.db'}")
    exp = client.create_experiment("names", artifact_location=str(tmp_path / "art"))
    names = {}
    for backbone in ("efficientnet_lite0", None):
        run = client.create_run(exp).info.run_id
        client.log_batch(run, params=[Param(registry.BACKBONE_PARAM, backbone)] if backbone else [],
                         tags=[RunTag(k, v) for k, v in {**TAGS, "init": "random"}.items()])
        names[backbone] = RunRecord.from_run(client.get_run(run))
    assert names["efficientnet_lite0"].model == "Baseline MSE+CE · Lite0 random"
    assert names["efficientnet_lite0"].title == "Baseline MSE+CE · Lite0 random · s0 · pers · world"
    assert names[None].model == "Baseline MSE+CE" and names[None].title == "Baseline MSE+CE · s0 · pers · world"


def _legends(monkeypatch, module) -> dict[str, list[str]]:
    """Figure stem -> its legend texts, captured as ``module`` saves each figure."""
    seen: dict[str, list[str]] = {}
    real = module.save_figure

    def capture(fig, path, formats):
        seen[path.name] = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
        seen[path.name + ":text"] = [t.get_text() for t in fig.texts]
        return real(fig, path, formats)

    monkeypatch.setattr(module, "save_figure", capture)
    return seen


def shown_name(table, row) -> str:
    """A model row's name as the table shows it: the label of a one-column table; under a group, the paper's name
    where the label gives one ("MSE+CE (BronchoTrack)"), else the group and the label."""
    named = re.fullmatch(r".+ \((.+)\)", row.label) if table.grouped else None
    return named.group(1) if named else f"{row.group} {row.label}".strip()


def test_figure_legends_run_names_and_table_rows_use_the_one_name(golden_store, tmp_path, monkeypatch):
    g = golden_store
    index = report.collect_index(g.client, g.cfg)
    arch, loss, _ = tables.bronchotrack(index)
    ours, offsetnet = registry.model_name(arch, loss), registry.model_name("offsetnet", "mse")
    ctx = tables.ReportContext(index, errors=errors_loader(g.client))
    sota = tables.sota(ctx, "pair")
    assert [r.label for r in sota.rows if r.kind == "model"] == [ours, offsetnet] == ["+ConvRNN MSE+DE", "OffsetNet"]
    # every table: each (arch, loss) row shows the registry's one name
    seen: dict[tuple[str, str], set[str]] = {}
    for name in tables.table_names("all"):
        for ev in tables.evaluations("both"):
            try:
                t = tables.TABLES[name](ctx, ev)
            except tables.NoData:
                continue
            for r in t.rows:
                if r.kind == "model" and r.runs:
                    run = next(x for x in index.runs.values() if x.run_id == r.runs[0])
                    seen.setdefault(run.identity[:2], set()).add(shown_name(t, r))
    assert seen and all(names == {registry.model_name(*k)} for k, names in seen.items()), seen
    # figures: the trajectory figure and the error curves name the same models the same way
    legends = _legends(monkeypatch, figures)
    make_figures(index, mlflow_loader(g.client, []), tmp_path, 2, [])
    assert legends["fig5-trajectories"] == ["ground truth", ours, offsetnet]
    # the training curves name each run by its UI run name, which starts with the model's name and seed
    legends = _legends(monkeypatch, curves)
    run = next(r for r in index.runs.values() if r.identity[:2] == ("lstm", "ce"))
    history = {"train.pairs_seen": [(1, 10.0), (2, 20.0)], "val.ratio.pos_l2": [(1, 1.0), (2, 0.9)]}
    curves.training_curves([run], lambda _id, key: history.get(key, []), tmp_path, [])
    cell = Cell.from_tags(run.tags)
    assert run_name(cell).startswith(registry.model_name("lstm", "ce") + f" · s{cell.seed} · pers")
    assert legends["fig-training-curves"][0] == run_name(cell) == run.title


def test_the_error_curves_show_every_model_of_tables_6_and_7_and_the_references(golden_store, tmp_path,
                                                                                 monkeypatch):
    """Issue 57.3: the error-vs-frame figures draw every model of Table 6 (OffsetNet with its MSE loss too) and of
    Table 7 (each architecture with MSE+CE), the zero-motion reference, and say in their caption what they leave
    out (here the 3D conv MSE+CE cell, which failed, and the training mean, whose poses these runs lack)."""
    g = golden_store
    index = report.collect_index(g.client, g.cfg)
    ctx = tables.ReportContext(index, errors=errors_loader(g.client))
    wanted = [r.model for t in (tables.sota(ctx, "pair"), tables.ablation(ctx, "pair"))
              for r in t.rows if r.kind == "model"]
    legends = _legends(monkeypatch, figures)
    warnings: list[str] = []
    make_figures(index, mlflow_loader(g.client, []), tmp_path, 2, warnings)
    for kind in ("position", "rotation"):
        shown, caption = legends[f"fig-error-{kind}"], " ".join(legends[f"fig-error-{kind}:text"])
        for name in dict.fromkeys(wanted):
            assert name in shown or f"{name} (" in caption.replace("\n", " "), (name, shown, caption)
        assert "OffsetNet" in shown and "Zero motion" in shown
        assert "Left out: +3D MSE+CE (Table 7: no FINISHED personalized run)" in caption.replace("\n", " ")
        assert "Training mean not drawn" in caption.replace("\n", " ")
    assert any("leave out +3D MSE+CE" in w for w in warnings)
