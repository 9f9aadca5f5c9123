"""Table builders on hand-made run records: layout, pooling over seeds, best-N selection, missing pieces."""

from __future__ import annotations

import pytest
from report_fakes import metrics_from

from bronchocli.reporting.collect import RunRecord, index_runs
from bronchocli.reporting.tables import ReportContext, ablation, cross_subject, personalized, sota


def _rec(run_id: str, arch: str, loss: str, pop: str = "personalized", fold: str = "", seed: int = 0,
         acc=(1.0, 2.0, 0.1, 0.01), n=(10, 100), std_div=2.0, status="FINISHED", **extra) -> RunRecord:
    tags = {"arch": arch, "rot_loss": loss, "population": pop, "fold": fold, "seed": str(seed), "pose_frame": "world"}
    return RunRecord(run_id, status, 0, tags, metrics_from(acc, *n, std_div=std_div) | extra)


def _ctx(*records: RunRecord, **kw) -> ReportContext:
    return ReportContext(index_runs(records, "s", "e"), **kw)


def test_rows_follow_the_paper_order_restricted_to_what_the_sweep_ran():
    t = personalized(_ctx(_rec("a", "offsetnet", "mse"), _rec("b", "convlstm", "ce"), _rec("c", "lstm", "ce",
                                                                                             status="FAILED")),
                     "accumulated")
    assert [(r.group, r.label) for r in t.rows] == [("+LSTM", "MSE+MSE"), ("+LSTM", "MSE+CE"),
                                                    ("+ConvRNN", "MSE+MSE"), ("+ConvRNN", "MSE+CE")]
    assert any("personalized lstm MSE+CE: no FINISHED run (c FAILED)" in w for w in t.warnings)


def test_several_seeds_are_pooled_and_said_so():
    t = personalized(_ctx(_rec("s0", "lstm", "ce", seed=0, acc=(1.0, 2, 0.1, 0.01)),
                          _rec("s1", "lstm", "ce", seed=1, acc=(3.0, 2, 0.1, 0.01))), "accumulated")
    (row,) = t.rows
    assert row.runs == ["s0", "s1"] and row.values[0].mean == pytest.approx(2.0) and row.values[0].n == 20
    assert "seeds 0, 1 (pooled like folds)" in t.caption and "20 test trajectories per cell" in t.caption


def test_a_cell_missing_one_seed_is_left_empty():
    t = personalized(_ctx(_rec("a0", "lstm", "ce", seed=0), _rec("a1", "lstm", "ce", seed=1),
                          _rec("b0", "lstm", "mse", seed=0)), "pair")
    mse = next(r for r in t.rows if r.label == "MSE+MSE")
    assert mse.values == [None] * 4
    assert any("lstm MSE+MSE: no FINISHED run for fold - seed 1" in w for w in t.warnings)


def test_cross_subject_best_n_keeps_the_lowest_mean_rank():
    runs = []
    # (arch, loss) -> acc means; ranks per column: A best everywhere, B second except DE, C last.
    means = {("lstm", "ce"): (1.0, 1.0, 1.0, 1.0), ("conv3d", "ce"): (2.0, 2.0, 9.0, 2.0),
             ("baseline", "mse"): (3.0, 3.0, 3.0, 3.0), ("convlstm", "de"): (9.0, 9.0, 2.0, 9.0)}
    for (arch, loss), acc in means.items():
        runs += [_rec(f"{arch}{loss}{f}", arch, loss, "cross-subject", f, acc=acc) for f in ("p00", "p01")]
    t = cross_subject(_ctx(*runs, best=2), "accumulated")
    assert [(r.group, r.label) for r in t.rows] == [("+LSTM", "MSE+CE"), ("+3D", "MSE+CE")]
    assert "best 2 of 4 complete network/loss combinations" in t.caption
    assert "held-out patients: p00, p01" in t.caption


def test_sota_without_offsetnet_and_without_n_params():
    t = sota(_ctx(_rec("bt", "convlstm", "ce")), "accumulated")
    assert [r.label for r in t.rows] == ["BronchoTrack (ConvLSTM, MSE+CE)", "OffsetNet (MSE+MSE)"]
    assert t.rows[0].values[0] is None and t.rows[1].values == [None] * 5
    assert any("no run logged n_params" in w for w in t.warnings)
    assert any("offsetnet MSE+MSE: no FINISHED run" in w for w in t.warnings)


def test_ablation_takes_cost_from_the_injected_profiler_and_params_from_the_run():
    calls = []

    def profiler(arch):
        calls.append(arch)
        return {"params": 1.0e6, "latency_ms_b1": 2.5, "gmacs_per_pair": 0.25, "device": "cpu (2 threads)",
                "image_size": 64, "window": 10, "precision": "32"}

    ctx = _ctx(_rec("a", "lstm", "ce", n_params=14_164_000), _rec("b", "conv3d", "ce"), profiler=profiler)
    t = ablation(ctx, "accumulated")
    ablation(ctx, "pair")
    assert calls == ["lstm", "conv3d"]  # each architecture profiled once for both tables
    lstm, conv3d = t.rows  # paper order: +LSTM before +3D
    assert lstm.values[:3] == [pytest.approx(14.164), 2.5, 0.25]
    assert conv3d.values[0] == pytest.approx(1.0)  # no n_params logged: the profiler's count
    assert "on cpu (2 threads), 64x64 input" in t.caption


def test_ablation_without_a_profiler_does_not_warn_about_latency():
    t = ablation(_ctx(_rec("a", "lstm", "ce", n_params=5), profiler_note="--no-latency"), "pair")
    assert t.rows[0].values[1:3] == [None, None]
    assert not any("Latency" in w for w in t.warnings)
    assert "Latency and GMAC not measured (--no-latency)" in t.caption
