"""How a run trained, as the MLflow UI charts it: training curves every ``runs.log_every`` steps, validation
metrics at every validation, one name per figure, and MLflow's system metrics sampled during the run."""

from __future__ import annotations

import math
import sys

import pytest

from bronchocli.runs.client import client_for
from bronchocli.training.run import run_cell

CURVES = ("train_loss", "lr", "grad_norm", "pairs_per_s")


def _run(cfg, **values):
    cfg = cfg.with_values(values)
    cell = cfg.cell(arch="baseline", rot_loss="mse", population="personalized")
    result = run_cell(cfg, cell, progress=False)
    assert result.status == "FINISHED", result.failure_reason
    return client_for(cfg), result.run_id


def _steps(client, run_id: str, key: str) -> list[int]:
    return sorted(m.step for m in client.get_metric_history(run_id, key))


@pytest.fixture(scope="module")
def curved(tiny_cfg):
    """8 steps, a validation every 4, a curve point every 2 steps; system metrics sampled every 0.2 s."""
    return _run(tiny_cfg, **{"name": "curves", "train.steps": 8, "train.val_every": 4, "runs.log_every": 2,
                             "runs.system_metrics_interval_s": 0.2})


def test_training_curves_have_a_point_every_log_every_steps(curved):
    client, run_id = curved
    for key in CURVES:
        assert _steps(client, run_id, key) == [2, 4, 6, 8], key
    assert _steps(client, run_id, "val_loss") == [4, 8]  # validation metrics at every validation
    lr = {m.step: m.value for m in client.get_metric_history(run_id, "lr")}
    assert lr[2] > lr[8] >= 0  # warm-up then cosine decay: the rate each step used, not a constant
    for key in ("train_loss", "grad_norm", "pairs_per_s"):
        values = [m.value for m in client.get_metric_history(run_id, key)]
        assert all(math.isfinite(v) and v > 0 for v in values), (key, values)


def test_no_metric_is_logged_twice_or_again_at_step_zero(curved):
    client, run_id = curved
    metrics = client.get_run(run_id).data.metrics
    for key in ("train.pairs_seen", "train.epochs", "train.skipped_steps", "val_loss", *CURVES):
        assert 0 not in _steps(client, run_id, key), key  # logged during training only: no final point at step 0
    assert _steps(client, run_id, "train.pairs_seen") == [4, 8] and metrics["train.pairs_seen"] == 8 * 6
    for gone in ("best_val_loss", "epoch", "pairs_seen", "skill.train_mean.pair.pos_l2",
                 "skill.zero_motion.pair.pos_l2"):
        assert gone not in metrics, gone  # one name per figure
    assert "val_best.loss" in metrics and "skill.pair.pos_l2" in metrics


def test_no_metric_goes_back_to_step_zero_after_later_steps(curved):
    """Every metric of a trained run: no point at step 0 is logged after a point at a later step (the curve would
    jump back: a system metric's first sample is at step 0, before the others), and the run value is the curve's
    end. ``train.core_s`` is logged at every validation, so the end of the run adds no point of it."""
    client, run_id = curved
    metrics = client.get_run(run_id).data.metrics
    back = {}
    for key, value in metrics.items():
        points = client.get_metric_history(run_id, key)
        later = [p.timestamp for p in points if p.step > 0]
        if later and any(p.step == 0 and p.timestamp > min(later) for p in points):
            back[key] = [(p.step, p.timestamp) for p in points]
        last = max(points, key=lambda p: (p.step, p.timestamp))
        assert last.value == value or math.isnan(last.value) and math.isnan(value), key  # the curve's end
    assert not back, f"metrics logged at step 0 after later steps: {back}"
    assert _steps(client, run_id, "train.core_s") == [4, 8] and metrics["train.core_s"] > 0
    assert 0 in _steps(client, run_id, "pair.pos_l2.mean")  # a one-off test metric stays at step 0


def test_system_metrics_are_sampled_during_the_run(curved):
    client, run_id = curved
    metrics = client.get_run(run_id).data.metrics
    assert "system/cpu_utilization_percentage" in metrics
    assert {"system/system_memory_usage_megabytes", "system/system_memory_usage_percentage"} <= set(metrics)
    assert 0 < metrics["system/system_memory_usage_percentage"] <= 100


def test_a_missing_gpu_library_is_harmless_and_the_switch_turns_sampling_off(tiny_cfg, monkeypatch):
    from mlflow.system_metrics.metrics import gpu_monitor  # lazy: the module whose import of pynvml is faked

    monkeypatch.setitem(sys.modules, "pynvml", None)  # `import pynvml` raises ImportError
    monkeypatch.delattr(gpu_monitor, "pynvml", raising=False)
    client, run_id = _run(tiny_cfg, **{"name": "nogpu", "train.steps": 2, "train.val_every": 2,
                                       "runs.system_metrics_interval_s": 0.2})
    metrics = client.get_run(run_id).data.metrics
    assert "system/cpu_utilization_percentage" in metrics
    assert not any(k.startswith("system/gpu") for k in metrics)
    client, run_id = _run(tiny_cfg, **{"name": "nosys", "train.steps": 2, "train.val_every": 2,
                                       "runs.system_metrics": False})
    assert not any(k.startswith("system/") for k in client.get_run(run_id).data.metrics)


def test_final_points_log_a_curves_end_at_its_last_step_never_at_zero():
    from bronchocli.training.artifacts import final_points

    history = [{"step": 4.0, "train.core_s": 1.0, "val_loss": 2.0}, {"step": 8.0, "train.core_s": 2.0, "val_loss": 1.5}]
    at_zero, at_last = final_points({"train.core_s": 2.0, "train.epochs": 3.0, "pair.pos_l2.mean": 0.5}, history)
    assert at_zero == {"train.epochs": 3.0, "pair.pos_l2.mean": 0.5} and at_last == {}  # the last validation has it
    at_zero, at_last = final_points({"train.core_s": 2.5, "pair.pos_l2.mean": 0.5}, history)
    assert at_zero == {"pair.pos_l2.mean": 0.5} and at_last == {"train.core_s": 2.5}  # differs: at step 8
    assert final_points({"train.core_s": 2.0}, []) == ({"train.core_s": 2.0}, {})  # no validation: its only point
