"""issue 40.2: ``--set train.precision=32`` (YAML reads a number) trains in fp32, as the docs say it does."""

from __future__ import annotations

from bronchocli import speed
from bronchocli.config import load_config, parse_override
from bronchocli.runs.client import client_for
from bronchocli.training import device
from bronchocli.training.run import run_cell


def test_set_precision_32_written_as_a_number_trains_in_fp32(tiny_project, monkeypatch, tmp_path):
    """The architecture's measured setting here is bf16 (what ``auto`` would train in); ``--set
    train.precision=32`` is parsed as the number 32, read as the canonical ``"32"`` and the run trains in fp32:
    its logged precision param and device tag say ``32``."""
    monkeypatch.chdir(tiny_project)
    monkeypatch.setattr(device, "bf16_fast", lambda dev: True)  # bf16 is what auto would choose
    settings = tmp_path / "speed.json"
    speed.write(settings, "cpu", {"measured": {"date": "2026-11-26"}, "archs": {
        "offsetnet": {"precision": "bf16-mixed", "channels_last": False, "chosen": "bf16 contiguous",
                      "pairs_per_s": {"bf16 contiguous": 10.0}}}})
    assert parse_override("train.precision=32") == ("train.precision", 32)  # a number, not the text "32"
    cfg = load_config(tiny_project / "experiments.yaml", overrides=[
        "train.precision=32", "train.steps=2", "train.val_every=2", f"train.speed_settings={settings}"])
    assert cfg.train.precision == "32" and "precision: '32'" in cfg.to_yaml()  # the resolved config
    result = run_cell(cfg, cfg.cell(arch="offsetnet", rot_loss="mse", population="personalized"), progress=False)
    assert result.status == "FINISHED", result.failure_reason
    run = client_for(cfg).get_run(result.run_id)
    assert run.data.params["speed.precision"] == "32" and run.data.params["train.precision"] == "32"
    assert run.data.tags["env.precision"] == "32"
    assert "config overrides train.precision" in run.data.params["speed.source"]
