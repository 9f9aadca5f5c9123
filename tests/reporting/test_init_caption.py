"""Every table's source line states how the backbones of its runs were initialised (issue 23, item 3)."""

from __future__ import annotations

import pytest
from report_fakes import MemRuns, frames_runs

from bronchocli.reporting.captions import dataset_text, init_text, rot_scale_text
from bronchocli.reporting.tables import TABLES, NoData

IMAGENET = "imagenet:efficientnet_b0_rwightman-7f5810bc.pth"


def _runs(init: str) -> MemRuns:
    m = MemRuns(seed=3)
    for seed in (0, 1):
        for arch, loss in (("convlstm", "ce"), ("lstm", "ce"), ("offsetnet", "mse")):
            m.add(arch, loss, seed=seed, init=init)
        for fold in ("p00", "p01"):
            m.add("convlstm", "ce", population="cross-subject", fold=fold, seed=seed, init=init)
    return m


@pytest.mark.parametrize("name", sorted(TABLES))
@pytest.mark.parametrize("init, says", [("random", "Backbone initialisation: random weights (no pretrained backbone)."),
                                        (IMAGENET, "Backbone initialisation: ImageNet weights (the file "
                                                   "efficientnet_b0_rwightman-7f5810bc.pth).")])
def test_every_table_source_states_the_initialisation(name, init, says):
    m = frames_runs() if name == "frames" else _runs(init)
    if name == "frames":
        for i, r in enumerate(m.records):
            m.records[i] = type(r)(r.run_id, r.status, r.start_time, {**r.tags, "init": init}, r.metrics)
    try:
        table = TABLES[name](m.context(), "accumulated")  # tables built once (tracking) ignore it
    except NoData:
        pytest.skip(f"{name}: no data in this fabricated sweep")
    assert says in table.source
    assert any(p.startswith(("Dataset fingerprint ", "Dataset fingerprints differ")) for p in table.source)


def test_mixed_and_unrecorded_initialisations_are_counted():
    m = _runs("random")
    m.add("conv3d", "ce", init=IMAGENET)
    m.add("baseline", "ce", init="")
    text = init_text(m.records)
    assert "random weights (no pretrained backbone) (10 of 12 runs)" in text
    assert "ImageNet weights (the file efficientnet_b0_rwightman-7f5810bc.pth) (1 of 12 runs)" in text
    assert "not recorded" in text


def test_the_source_line_names_the_dataset_fingerprint_and_says_when_runs_differ():
    """Issue 57, item 7: a reader who regenerates the dataset can compare its fingerprint with the table's."""
    m = _runs("random")
    one = [type(r)(r.run_id, r.status, r.start_time, {**r.tags, "dataset_fingerprint": "29a6a538fb3e70dd1e72"},
                   r.metrics) for r in m.records]
    assert dataset_text(one) == "Dataset fingerprint 29a6a538fb3e."
    mixed = one[:-1] + [type(one[-1])(one[-1].run_id, "FINISHED", 0, {**one[-1].tags, "dataset_fingerprint": ""}, {})]
    text = dataset_text(mixed)
    assert text.startswith("Dataset fingerprints differ between runs (not one dataset):")
    assert f"29a6a538fb3e ({len(one) - 1} of {len(one)} runs)" in text and "not recorded (1 of" in text


def test_the_source_line_says_how_de_and_ce_were_weighed():
    """train.rot_scale: the DE/CE runs' rotation term in label-std units or as the paper writes it; runs logged
    before the setting trained unscaled; a table of MSE rows alone says nothing."""
    m = _runs("random")

    def with_scale(records, value):
        return [type(r)(r.run_id, r.status, r.start_time, r.tags, r.metrics, r.artifact_uri,
                        {**r.params, "train.rot_scale": value}) for r in records]

    scaled = with_scale(m.records, "label_std")
    assert rot_scale_text(scaled) == ("Rotation losses DE and CE: divided by their value at one label std of error, "
                                      "as MSE's squared errors are (train.rot_scale label_std).")
    assert "as the paper writes them" in rot_scale_text(m.records)  # no param: logged before it existed
    mixed = rot_scale_text(scaled[:1] + list(m.records[1:]))
    assert "(1 of " in mixed and "label std" in mixed and "unscaled" in mixed
    mse_only = [r for r in scaled if r.identity[1] == "mse"]
    assert mse_only and rot_scale_text(mse_only) == ""
