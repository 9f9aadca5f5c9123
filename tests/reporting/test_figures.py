"""Report figures from fabricated predictions.csv artifacts of real MLflow runs."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from report_fakes import predictions_frame

from bronchocli.reporting.figures import choose_trajectories, frame_errors, local_artifact, make_figures, mlflow_loader
from bronchocli.reporting.report import collect_index


def test_frame_errors_match_the_planted_drift():
    pos, rot = frame_errors(predictions_frame(0, drift=0.1, n_frames=20))
    assert pos.shape == rot.shape == (4, 20)
    np.testing.assert_allclose(pos, np.tile(0.1 * np.arange(20), (4, 1)), atol=1e-12)
    np.testing.assert_allclose(rot, 0.0, atol=1e-5)  # rotations are predicted exactly


def test_frame_errors_pad_shorter_trajectories_with_nan():
    a = predictions_frame(0, 0.2, lobes=("ur",), n_frames=5)
    b = predictions_frame(0, 0.2, lobes=("bl",), n_frames=8)
    import pandas as pd

    pos, _ = frame_errors(pd.concat([a, b], ignore_index=True))
    assert pos.shape == (2, 8) and np.isnan(pos).sum() == 3


def test_trajectories_are_chosen_one_per_lobe_and_common_to_every_model():
    everything = predictions_frame(0, 0.1)
    no_ul = everything[everything["lobe"] != "ul"]
    assert choose_trajectories([everything], 4) == [("p00", "ur", "0"), ("p00", "br", "1"), ("p00", "ul", "2"),
                                                    ("p00", "bl", "3")]
    assert choose_trajectories([everything, no_ul], 2) == [("p00", "ur", "0"), ("p00", "br", "1")]


def test_make_figures_writes_png_and_pdf_from_mlflow_artifacts(golden_store, tmp_path):
    client = golden_store.client
    index = collect_index(client, golden_store.cfg)
    warnings: list[str] = []
    files = make_figures(index, mlflow_loader(client, warnings), tmp_path, 3, warnings)
    names = sorted(p.name for p in files)
    assert names == sorted(f"{stem}.{ext}" for stem in ("fig5-trajectories", "fig-error-position",
                                                          "fig-error-rotation") for ext in ("png", "pdf"))
    # conv3d's MSE+CE run FAILED: no curve for it (the caption and one warning say so), and nothing else is missing.
    assert warnings == ["figures: the error-vs-frame curves leave out +3D MSE+CE (Table 7: no FINISHED personalized "
                        "run)"]
    assert local_artifact(next(iter(index.runs.values())), "x.csv") is not None  # read in place, no download
    for p in files:
        assert p.stat().st_size > 2000
        if p.suffix == ".png":
            with Image.open(p) as im:
                assert im.size[0] > 300 and im.size[1] > 200
        else:
            assert p.read_bytes().startswith(b"%PDF")


def test_a_model_without_predictions_is_left_out_with_a_warning(golden_store, tmp_path):
    client, ids = golden_store.client, golden_store.ids
    index = collect_index(client, golden_store.cfg)
    warnings: list[str] = []
    real = mlflow_loader(client, warnings)
    offsetnet = {ids["personalized/offsetnet/mse/s0"], ids["personalized/offsetnet/mse/s1"]}
    files = make_figures(index, lambda run: None if run.run_id in offsetnet else real(run), tmp_path, 2, warnings)
    assert (tmp_path / "fig5-trajectories.png") in files
    assert any("no OffsetNet curve" in w for w in warnings)


def test_a_run_without_the_artifact_is_a_warning_not_a_crash(golden_store, tmp_path):
    client, ids = golden_store.client, golden_store.ids
    index = collect_index(client, golden_store.cfg)
    warnings: list[str] = []
    run = next(r for r in index.runs.values() if r.run_id == ids["personalized/lstm/mse/s0"])
    assert mlflow_loader(client, warnings)(run) is None
    assert len(warnings) == 1 and "no predictions.csv artifact" in warnings[0]


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import matplotlib.pyplot as plt

    plt.close("all")
