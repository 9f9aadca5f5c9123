"""The per-architecture speed settings file (bronchocli/speed.py): lookup, overrides, fallbacks, writing."""

from __future__ import annotations

import json

import pytest

from bronchocli import speed
from bronchocli.errors import BronchoError


def _file(tmp_path, entry, key="cpu"):
    path = tmp_path / "speed.json"
    speed.write(path, key, entry)
    return path


ENTRY = {"measured": {"date": "2026-11-26"}, "archs": {
    "offsetnet": {"precision": "bf16-mixed", "channels_last": False, "chosen": "bf16 contiguous",
                  "pairs_per_s": {"fp32 CL": 20.0, "bf16 contiguous": 34.0}},
    "convlstm": {"precision": "32", "channels_last": True, "chosen": "fp32 CL", "pairs_per_s": {"fp32 CL": 60.0}}}}


def test_auto_takes_the_measured_setting_of_the_architecture(tmp_path):
    path = _file(tmp_path, ENTRY)
    s = speed.choose("offsetnet", "cpu", "auto", "auto", path=path)
    assert (s.precision, s.channels_last) == ("bf16-mixed", False) and s.source.startswith("measured")
    s = speed.choose("convlstm", "cpu", "auto", "auto", path=path)
    assert (s.precision, s.channels_last) == ("32", True)
    assert s.params() == {"speed.precision": "32", "speed.channels_last": "true", "speed.source": s.source}


def test_explicit_values_win_one_by_one(tmp_path):
    path = _file(tmp_path, ENTRY)
    s = speed.choose("offsetnet", "cpu", "32", "auto", path=path)
    assert (s.precision, s.channels_last) == ("32", False) and "config overrides train.precision" in s.source
    s = speed.choose("offsetnet", "cpu", "auto", True, path=path)
    assert (s.precision, s.channels_last) == ("bf16-mixed", True) and "model.channels_last" in s.source
    assert speed.choose("offsetnet", "cpu", "32", False, path=path).source == "config"


def test_unmeasured_devices_and_architectures_get_the_defaults(tmp_path):
    path = _file(tmp_path, ENTRY)
    s = speed.choose("lstm", "cpu", "auto", "auto", path=path)
    assert (s.precision, s.channels_last) == ("32", True) and s.source.startswith("default")
    s = speed.choose("offsetnet", "cuda:NVIDIA H200", "auto", "auto", path=path)
    assert (s.precision, s.channels_last) == ("bf16-mixed", True)
    s = speed.choose("offsetnet", "cuda:Tesla T4", "auto", "auto", path=path, bf16_ok=False)
    assert s.precision == "16-mixed"


def test_bf16_falls_back_to_fp32_on_a_cpu_without_native_bf16(tmp_path):
    s = speed.choose("offsetnet", "cpu", "auto", "auto", path=_file(tmp_path, ENTRY), bf16_ok=False)
    assert (s.precision, s.channels_last) == ("32", False)


def test_writing_keeps_other_devices_and_rates_come_from_the_chosen_setting(tmp_path):
    path = _file(tmp_path, ENTRY)
    speed.write(path, "cuda:NVIDIA H200", {"measured": {}, "archs": {}})
    data = json.loads(path.read_text())
    assert set(data["devices"]) == {"cpu", "cuda:NVIDIA H200"}
    assert speed.training_rates("cpu", path) == {"offsetnet": 34.0, "convlstm": 60.0}


def test_a_bad_settings_file_is_one_line(tmp_path):
    with pytest.raises(BronchoError, match="train.speed_settings .*missing.json: no such file"):
        speed.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(BronchoError, match="not a speed settings file"):
        speed.load(bad)


def test_the_shipped_file_is_valid_and_names_every_architecture_it_measured():
    data = speed.load()
    from bronchocli.registry import arch_names  # every measured name is a registered architecture

    for key, entry in data["devices"].items():
        assert set(entry["archs"]) <= set(arch_names()), key
        for arch, m in entry["archs"].items():
            assert m["precision"] in ("32", "bf16-mixed", "16-mixed") and isinstance(m["channels_last"], bool)
            assert m["chosen"] in m["pairs_per_s"], (key, arch)
