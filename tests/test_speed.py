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


ZEN4 = "processor\t: 0\nmodel name\t: AMD EPYC 9R14\nflags\t\t: fpu sse2 avx avx2 avx512f avx512bw avx512_bf16 fma\n"
ZEN3 = "processor\t: 0\nmodel name\t: AMD EPYC 7R13\nflags\t\t: fpu sse2 avx avx2 fma\n"
SAPPHIRE = "flags\t\t: sse2 avx2 avx512f amx_bf16 amx_tile\n"
GRAVITON3 = "processor\t: 0\nFeatures\t: fp asimd sve bf16 i8mm\n"


@pytest.mark.parametrize("info, key", [(ZEN4, "cpu:AVX512+bf16"), (ZEN3, "cpu:AVX2"),
                                       (SAPPHIRE, "cpu:AVX512+bf16"), (GRAVITON3, "cpu:NEON+bf16")])
def test_a_cpu_is_keyed_by_its_vector_instructions(info, key):
    assert speed.cpu_key(info) == key


def test_settings_measured_on_one_cpu_do_not_apply_to_a_cpu_with_other_instructions(tmp_path):
    """The shipped CPU settings were measured on a Zen 4 (native bf16); an AVX2 CPU where bf16 is emulated and
    other kernels win must not inherit them (the main job ran 3x slower in the measured-elsewhere setting)."""
    path = _file(tmp_path, ENTRY, key="cpu:AVX512+bf16")
    assert speed.choose("offsetnet", "cpu:AVX512+bf16", "auto", "auto", path=path).precision == "bf16-mixed"
    s = speed.choose("offsetnet", "cpu:AVX2", "auto", "auto", path=path)
    assert (s.precision, s.channels_last) == ("32", True) and s.source.startswith("default (no measurement of this architecture on cpu:AVX2")
    assert speed.training_rates("cpu:AVX2", path) == {}
    (tmp_path / "old").mkdir()
    legacy = _file(tmp_path / "old", ENTRY, key="cpu")  # written before the keys named the instructions
    s = speed.choose("offsetnet", "cpu:AVX2", "auto", "auto", path=legacy)
    assert s.precision == "bf16-mixed" and s.source.startswith("measured (speed.json settings, cpu, ")  # any CPU


def test_the_shipped_file_names_each_cpu_by_its_instructions():
    keys = set(speed.load()["devices"])
    assert keys and all(k.startswith("cuda:") or k.startswith("cpu:") for k in keys), keys
