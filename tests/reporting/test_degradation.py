"""Reports say what degraded: NaN rows left out of intervals (with the count), and the true reason a run has no
trajectory_errors.csv (its artifact folder deleted, not "made before it was logged")."""

from __future__ import annotations

import dataclasses

import numpy as np
from report_fakes import MemRuns

from bronchocli.reporting.tables import personalized


def test_nan_rows_of_trajectory_errors_are_counted_in_a_warning():
    m = MemRuns(seed=3)
    bad = m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01))
    m.add("convlstm", "ce", (3.0, 10.0, 0.1, 0.01))
    errors = m.errors[bad.run_id]
    cols = {k: v.copy() for k, v in errors.columns.items()}
    for name in [c for c in cols if c.startswith("model.")][:2]:
        cols[name][[0, 2]] = np.nan  # two trajectories (rows 0 and 2) with a NaN error
    m.errors[bad.run_id] = dataclasses.replace(errors, columns=cols)
    t = personalized(m.context(), "accumulated")
    warned = [w for w in t.warnings if "NaN" in w]
    assert len(warned) == 1 and "2 trajectory row(s)" in warned[0] and bad.run_id in warned[0], t.warnings


def test_clean_errors_give_no_nan_warning():
    m = MemRuns(seed=4)
    m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01))
    assert not [w for w in personalized(m.context(), "accumulated").warnings if "NaN" in w]


def test_a_run_whose_artifacts_were_deleted_is_reported_as_such(tmp_path):
    m = MemRuns(seed=5)
    gone = tmp_path / "artifacts" / "0" / "abc" / "artifacts"
    old = m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01), with_errors=False)
    m.records[-1] = dataclasses.replace(old, artifact_uri=gone.as_uri())
    m.add("convlstm", "ce", (3.0, 10.0, 0.1, 0.01))
    t = personalized(m.context(), "accumulated")
    warned = [w for w in t.warnings if "no trajectory_errors.csv" in w]
    assert len(warned) == 1 and "deleted or moved" in warned[0] and str(gone) in warned[0], warned
    assert "made before" not in warned[0]


def test_a_run_whose_folder_exists_without_the_table_keeps_the_old_reason(tmp_path):
    m = MemRuns(seed=6)
    here = tmp_path / "a"
    here.mkdir()
    old = m.add("lstm", "ce", (2.0, 10.0, 0.1, 0.01), with_errors=False)
    m.records[-1] = dataclasses.replace(old, artifact_uri=here.as_uri())
    m.add("convlstm", "ce", (3.0, 10.0, 0.1, 0.01))
    warned = [w for w in personalized(m.context(), "accumulated").warnings if "no trajectory_errors.csv" in w]
    assert len(warned) == 1 and "made before it was logged" in warned[0]
