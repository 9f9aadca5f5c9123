"""Table builders on in-memory runs: layout, staged plans (which cells each table takes), sota, ablation."""

from __future__ import annotations

import pytest
from report_fakes import THRESHOLDS, MemRuns

from bronchocli.config import Config, load_config
from bronchocli.reporting.collect import RunRecord
from bronchocli.reporting.scope import PlanView, profile_plans
from bronchocli.reporting.tables import NoData, _thresholds_text, ablation, cross_subject, personalized, sota


def _ident(arch, loss, pop="personalized", fold="", seed="0"):
    return (arch, loss, pop, fold, seed, "world", "")


def test_rows_follow_the_paper_order_restricted_to_what_the_sweep_ran():
    m = MemRuns()
    m.add("offsetnet", "mse")
    m.add("convlstm", "ce")
    m.add("lstm", "ce", status="FAILED")
    t = personalized(m.context(), "accumulated")
    assert [(r.group, r.label) for r in t.rows] == [
        ("+LSTM", "MSE+MSE"), ("+LSTM", "MSE+CE"), ("+ConvRNN", "MSE+MSE"), ("+ConvRNN", "MSE+CE (BronchoTrack)"),
        ("OffsetNet", "MSE+MSE (OffsetNet)"),  # a run of it: its row after the paper's groups, only the loss it ran
        ("Image-blind", "Zero motion"), ("Image-blind", "Training mean")]
    lacks = [w for w in t.warnings if "lacks" in w]
    assert len(lacks) == 1 and "lstm/ce/personalized/s0/world (FAILED r002)" in lacks[0]


def _plan(cells_by_stage: dict) -> PlanView:
    keys = {i: f"k{n}" for n, i in enumerate(i for cells in cells_by_stage.values() for i in cells or [])}
    return PlanView(cells_by_stage, keys, staged=True, selections={})


def test_a_table_planned_in_part_names_the_paper_cells_it_lacks_and_the_profile_that_plans_them():
    """The main job's plan (one stage, sota: BronchoTrack and OffsetNet) read as Table 3: both rows shown, and the
    11 paper cells it does not plan named with the profiles that do."""
    m = MemRuns()
    m.add("convlstm", "ce", key="k0")
    m.add("offsetnet", "mse", key="k1")
    plan = PlanView({"sota": [_ident("convlstm", "ce"), _ident("offsetnet", "mse")]},
                    {_ident("convlstm", "ce"): "k0", _ident("offsetnet", "mse"): "k1"}, staged=True)
    ctx = m.context(plan=plan)
    paper = {(a, lo, "personalized") for a in ("baseline", "lstm", "conv3d", "convlstm") for lo in ("mse", "de", "ce")}
    ctx.profile_plans = lambda: {"paper": paper, "bronchotrack-cpu": {("convlstm", "ce", "personalized")},
                                 "learning-curve": {("baseline", "ce", "personalized"),
                                                    ("convlstm", "ce", "personalized")}}
    t = personalized(ctx, "pair")
    assert [r.name for r in t.rows if r.kind == "model"] == ["BronchoTrack", "OffsetNet"]
    note = ("This config plans 1 of the paper's 12 personalized network/loss cells; not planned: Baseline: MSE+MSE, "
            "MSE+DE, MSE+CE; +LSTM: MSE+MSE, MSE+DE, MSE+CE; +3D: MSE+MSE, MSE+DE, MSE+CE; +ConvRNN: MSE+MSE, "
            "MSE+DE; the profile paper plans them (bronchopose report --profile paper).")
    assert note in t.notes and f"personalized: {note}" in t.warnings
    ctx.profile_plans, ctx._plans = (lambda: {"learning-curve": {("baseline", "ce", "personalized")}}), None
    t = personalized(ctx, "pair")
    assert any("partly planned by the profile learning-curve (1)." in n for n in t.notes)
    full = PlanView({"personalized": sorted((a, lo, "personalized", "", "0", "world", "") for a, lo, _ in paper)},
                    {}, staged=True)
    t = personalized(m.context(plan=full), "pair")
    assert not any("This config plans" in n for n in t.notes)


def test_staged_plan_each_table_takes_its_own_stage():
    m = MemRuns()
    runs = {("lstm", "ce"): m.add("lstm", "ce", key="k0"), ("lstm", "mse"): m.add("lstm", "mse", key="k1"),
            ("convlstm", "ce"): m.add("convlstm", "ce", key="k2")}
    plan = _plan({"personalized": [_ident("lstm", "ce"), _ident("lstm", "mse")],
                  "sota": [_ident("convlstm", "ce"), _ident("offsetnet", "mse")]})
    plan.keys[_ident("convlstm", "ce")] = "k2"
    ctx = m.context(plan=plan)
    t = personalized(ctx, "pair")
    assert [r.label for r in t.rows if r.kind == "model"] == ["MSE+MSE", "MSE+CE"]  # convlstm is sota-only
    s = sota(ctx, "pair")
    assert s.rows[0].runs == [runs[("convlstm", "ce")].run_id]
    assert any("lacks 1 cell(s)" in w and "offsetnet/mse/personalized/s0/world" in w for w in s.warnings)


def test_sota_follows_the_recorded_selection():
    m = MemRuns()
    chosen = m.add("lstm", "de", key="k0")
    m.add("offsetnet", "mse", key="k1")
    plan = _plan({"sota": [_ident("lstm", "de"), _ident("offsetnet", "mse")]})
    plan.selections = {"sota": {"selected": [{"arch": "lstm", "rot_loss": "de"}], "by": "val_best.ce"}}
    t = sota(m.context(plan=plan), "accumulated")
    assert t.rows[0].label == "+LSTM MSE+DE" and t.rows[0].runs == [chosen.run_id]  # its one name, its role said
    assert ("+LSTM MSE+DE, selected on validation CE in the role of the paper's BronchoTrack, against OffsetNet"
            in t.caption)


def test_a_pending_selection_is_said_once():
    m = MemRuns()
    m.add("lstm", "ce", key="k0")
    plan = _plan({"personalized": [_ident("lstm", "ce")], "cross-subject": None})
    ctx = m.context(plan=plan)
    assert ctx.index.notes == ["plan: stage 'cross-subject' has no recorded selection yet (its cells are not "
                               "known; run `bronchopose sweep` to finish the earlier stage)"]
    with pytest.raises(NoData, match="table5-cross-subject skipped: none of the runs' cells belongs to it"):
        cross_subject(ctx, "pair")  # a table of reference rows only says nothing: the report skips it


def test_a_table_none_of_whose_cells_ran_is_skipped_not_broken():
    m = MemRuns()
    m.add("offsetnet", "mse", key="k0")  # OffsetNet only: no architecture of Tables 2-5 or the ablation's loss
    plan = _plan({"sota": [_ident("offsetnet", "mse")]})
    ctx = m.context(plan=plan)
    for build in (personalized, ablation):
        with pytest.raises(NoData, match="skipped: none of the runs' cells belongs to it"):
            build(ctx, "pair")
    assert [r.label for r in sota(ctx, "pair").rows if r.kind == "model" and r.runs] == ["OffsetNet"]


def test_cross_subject_best_n_keeps_the_lowest_mean_rank():
    m = MemRuns()
    means = {("lstm", "ce"): (1.0, 1.0, 0.1, 0.01), ("conv3d", "ce"): (2.0, 2.0, 0.9, 0.02),
             ("baseline", "mse"): (3.0, 3.0, 0.3, 0.03), ("convlstm", "de"): (9.0, 9.0, 0.2, 0.09)}
    for (arch, loss), acc in means.items():
        for fold in ("p00", "p01"):
            m.add(arch, loss, acc, population="cross-subject", fold=fold)
    t = cross_subject(m.context(best=2), "accumulated")
    assert [(r.group, r.label) for r in t.rows if r.kind == "model"] == [("+LSTM", "MSE+CE"), ("+3D", "MSE+CE")]
    assert len(t.marks) == len(t.rows)
    assert "best 2 of 4 complete network/loss combinations" in t.notes[0]


def test_sota_without_offsetnet_and_without_n_params():
    m = MemRuns()
    m.add("convlstm", "ce")
    t = sota(m.context(), "accumulated")
    assert [r.label for r in t.rows if r.kind == "model"] == ["BronchoTrack", "OffsetNet"]
    assert t.rows[0].values[0] is None and t.rows[1].values == [None] * 5
    assert any("no run logged n_params" in w for w in t.warnings)
    assert any("offsetnet/mse/personalized/s0/world" in w for w in t.warnings)


def test_ablation_takes_cost_from_the_injected_profiler_and_params_from_the_run():
    calls = []

    def profiler(arch):
        calls.append(arch)
        return {"params": 1.0e6, "latency_ms_b1": 2.5, "gmacs_per_pair": 0.25, "device": "cpu (2 threads)",
                "image_size": 64, "window": 10, "precision": "32"}

    m = MemRuns()
    m.add("lstm", "ce", n_params=14_164_000)
    m.add("conv3d", "ce")
    ctx = m.context(profiler=profiler)
    t = ablation(ctx, "accumulated")
    ablation(ctx, "pair")
    assert calls == ["lstm", "conv3d"]  # each architecture profiled once for both tables
    lstm, conv3d = t.rows[:2]  # paper order: +LSTM before +3D
    assert lstm.values[:3] == [pytest.approx(14.164), 2.5, 0.25]
    assert conv3d.values[0] == pytest.approx(1.0)  # no n_params logged: the profiler's count
    assert any("on cpu (2 threads), 64x64 input" in n for n in t.notes)
    assert t.rows[2].values[:3] == ["", "", ""]  # the reference rows have no cost


def test_ablation_without_a_profiler_does_not_warn_about_latency():
    m = MemRuns()
    m.add("lstm", "ce", n_params=5)
    t = ablation(m.context(profiler_note="--no-latency"), "pair")
    assert t.rows[0].values[1:3] == [None, None]
    assert not any("Latency" in w for w in t.warnings)
    assert "Latency and GMAC not measured (--no-latency)." in t.notes


def test_budget_and_stop_reasons_in_every_source():
    m = MemRuns()
    m.add("lstm", "ce", seed=0, **{"train.steps": 250.0, "train.pairs_seen": 5000.0, "train.epochs": 2.5})
    m.add("lstm", "ce", seed=1)
    t = personalized(m.context(), "pair")
    assert ("Budget per run: 250–300 optimiser steps, 5,000–6,000 pairs seen (batch × steps), 2.5–3.0 epochs; "
            "stop reasons: budget 2.") in t.source


class _Warnings(list):
    warn = list.append


def test_tracking_thresholds_read_params_and_the_metrics_of_runs_logged_before():
    params = {"eval.ctf_position": "5.0", "eval.ctf_position_mm": "5.0", "eval.ctf_angle": "10.0", "eval.rpe_gap": "10"}
    old = RunRecord("old", "FINISHED", 0, {}, dict(THRESHOLDS))  # before issue 36: the constants as metrics
    new = RunRecord("new", "FINISHED", 0, {}, {}, params=params)  # since: params, no such metrics
    texts = []
    for runs in ([old], [new], [old, new]):
        seen = _Warnings()
        texts.append(_thresholds_text(seen, runs))
        assert not seen, seen
    assert texts[0] == texts[1] == texts[2] and "rotation error below 10°" in texts[0] and "over 10 frames" in texts[0]
    changed = RunRecord("gap3", "FINISHED", 0, {}, {}, params={**params, "eval.rpe_gap": "3"})
    seen = _Warnings()
    assert "over 3 frames/10 frames" in _thresholds_text(seen, [old, changed])
    assert len(seen) == 1 and "different eval.rpe_gap (3, 10)" in seen[0]
    none = RunRecord("none", "FINISHED", 0, {}, {})
    assert "thresholds (not logged by these runs)" in _thresholds_text(_Warnings(), [none])


def test_profile_plans_reads_each_profile_of_the_config_file(tmp_path):
    path = tmp_path / "experiments.yaml"
    path.write_text("name: t\ngrid: {arch: [convlstm], rot_loss: [ce], population: [personalized]}\n"
                    "profiles:\n  wide:\n    grid: {arch: [baseline, lstm], rot_loss: [mse, ce]}\n"
                    "  broken:\n    grid: {arch: [no_such_net]}\n")
    plans = profile_plans(load_config(path))
    assert plans == {"wide": {(a, lo, "personalized") for a in ("baseline", "lstm") for lo in ("mse", "ce")}}
    assert profile_plans(Config(name="memory")) == {}  # no file to read the profiles from
