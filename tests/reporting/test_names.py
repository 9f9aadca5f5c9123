"""One model, one name (issue 48): the figure legends, the UI's run names and the table rows of a fabricated sweep
all come from the registry's display names (registry.display_name / short_name)."""

from __future__ import annotations

import pytest

from bronchocli import registry
from bronchocli.cells import Cell
from bronchocli.reporting import curves, figures, report, tables
from bronchocli.reporting.collect import RunRecord
from bronchocli.reporting.figures import errors_loader, make_figures, mlflow_loader
from bronchocli.runs.records import run_name


def test_the_registry_names_each_model_once():
    assert registry.display_name("convlstm", "ce") == "BronchoTrack (ConvLSTM, MSE+CE)"
    assert registry.short_name("convlstm", "ce") == "BronchoTrack"
    assert registry.display_name("convlstm", "de") == "ConvLSTM (MSE+DE)"
    assert registry.display_name("convlstm", "de", role="BronchoTrack") == "BronchoTrack (ConvLSTM, MSE+DE)"
    assert registry.display_name("offsetnet", "mse") == "OffsetNet (MSE+MSE)"
    assert registry.short_name("lstm", "ce") == "LSTM MSE+CE"
    assert registry.display_name("gone", "old") == "gone (old)"  # an old run's unregistered tags, as they are


def _legends(monkeypatch, module) -> dict[str, list[str]]:
    """Figure stem -> its legend texts, captured as ``module`` saves each figure."""
    seen: dict[str, list[str]] = {}
    real = module.save_figure

    def capture(fig, path, formats):
        seen[path.name] = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
        return real(fig, path, formats)

    monkeypatch.setattr(module, "save_figure", capture)
    return seen


def test_figure_legends_run_names_and_table_rows_use_the_registry_names(golden_store, tmp_path, monkeypatch):
    g = golden_store
    index = report.collect_index(g.client, g.cfg)
    arch, loss, _ = tables.bronchotrack(index)
    ours, offsetnet = registry.display_name(arch, loss, role="BronchoTrack"), registry.display_name("offsetnet", "mse")
    # tables: Table 6's rows are the registry's names of the two models
    ctx = tables.ReportContext(index, errors=errors_loader(g.client))
    sota = tables.sota(ctx, "pair")
    assert [r.label for r in sota.rows if r.kind == "model"] == [ours, offsetnet]
    # figures: the trajectory figure and the error curves name the same models the same way
    legends = _legends(monkeypatch, figures)
    make_figures(index, mlflow_loader(g.client, []), tmp_path, 2, [])
    assert legends["fig5-trajectories"] == ["ground truth", ours, offsetnet]
    assert legends["fig-error-position"] == [registry.display_name(a, "ce") for a in ("baseline", "lstm", "convlstm")]
    # the training curves name each run by its UI run name
    legends = _legends(monkeypatch, curves)
    run = next(r for r in index.runs.values() if r.identity[:2] == ("lstm", "ce"))
    history = {"train.pairs_seen": [(1, 10.0), (2, 20.0)], "val.ratio.pos_l2": [(1, 1.0), (2, 0.9)]}
    curves.training_curves([run], lambda _id, key: history.get(key, []), tmp_path, [])
    cell = Cell.from_tags(run.tags)
    assert run_name(cell).startswith(registry.short_name("lstm", "ce") + " · pers · s")
    assert legends["fig-training-curves"][0] == run_name(cell) == run.title


TAGS = {"arch": "baseline", "rot_loss": "ce", "population": "personalized", "fold": "", "seed": "0",
        "pose_frame": "world", "train_trajectories": ""}


@pytest.mark.parametrize("best, at", [(250.0, 5000.0), (300.0, 5000.0), (500.0, 10000.0), (None, 10000.0)])
def test_the_test_result_is_drawn_at_the_step_of_the_weights_tested(best, at):
    metrics = {} if best is None else {"train.best_step": best}
    run = RunRecord("a", "FINISHED", 0, TAGS, metrics)
    pairs = {"train.pairs_seen": [(250, 5000.0), (500, 10000.0)]}
    assert curves.tested_at(run, lambda _id, key: pairs.get(key, [])) == at
