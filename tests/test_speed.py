"""The per-architecture speed settings file (bronchocli/speed.py): lookup, overrides, fallbacks, writing."""

from __future__ import annotations

import json
import math

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


FROZEN = "efficientnet_lite0, frozen 7"
HEAD_ONLY = {"measured": {"date": "2026-12-07", "frozen_stages": 7}, "archs": {
    "convlstm": {"precision": "32", "channels_last": False, "chosen": "fp32 contiguous",
                 "pairs_per_s": {"fp32 CL": 100.0, "fp32 contiguous": 130.0}}}}


def test_a_run_on_a_cached_frozen_prefix_takes_that_trainings_measurement_first(tmp_path):
    """Issue 56: a step on a cached frozen prefix trains the last stages and the head only, so its own measurement
    applies; an architecture that measurement lacks gets its whole network's."""
    path = _file(tmp_path, ENTRY)
    speed.write(path, "cpu", HEAD_ONLY, FROZEN)
    s = speed.choose("convlstm", "cpu", "auto", "auto", path=path, frozen=FROZEN)
    assert (s.precision, s.channels_last) == ("32", False) and f"cpu, {FROZEN}, 2026-12-07" in s.source
    whole = speed.choose("convlstm", "cpu", "auto", "auto", path=path)  # no frozen prefix: the whole network's
    assert (whole.precision, whole.channels_last) == ("32", True) and "frozen" not in whole.source
    other = speed.choose("offsetnet", "cpu", "auto", "auto", path=path, frozen=FROZEN)  # not in the frozen entry
    assert other.precision == "bf16-mixed" and "frozen" not in other.source
    assert speed.choose("convlstm", "cpu", "auto", "auto", path=path, frozen="efficientnet_b0, frozen 7").channels_last


def test_measuring_the_whole_network_again_keeps_the_frozen_prefix_entries(tmp_path):
    path = _file(tmp_path, ENTRY)
    speed.write(path, "cpu", HEAD_ONLY, FROZEN)
    speed.write(path, "cpu", ENTRY)  # the whole network measured again
    data = json.loads(path.read_text())["devices"]["cpu"]
    assert data["archs"] == ENTRY["archs"] and data["frozen"] == {FROZEN: HEAD_ONLY}
    assert speed.frozen_key("efficientnet_lite0", 7) == FROZEN and speed.frozen_key("efficientnet_b0", 0) is None


def test_a_flat_reference_qualifies_no_candidate():
    """The loss check cannot fail when the reference does not learn: nothing but the default may be chosen then
    (the ConvLSTM head on a cached prefix: flat in 50 steps, while bf16 kept the baseline from learning)."""
    from bronchocli.diagnostics.speed import Trial, choose, loss_gap, reference_learns

    flat, learning = [1.66, 1.60, 1.59, 1.60, 1.58], [1.86, 1.39, 1.13, 0.90, 0.83]
    mean_only = [2.01, 1.56, 1.54, 1.55, 1.53]  # the 3-D-conv head: the labels' mean in the first block, then flat
    assert not reference_learns(flat) and not reference_learns(mean_only) and reference_learns(learning)
    assert loss_gap([2.0, 1.8, 1.8, 1.7, 1.7], learning) > 0.05  # bf16 on the baseline: caught when it learns
    base = Trial("32", True, 100.0, flat, gap=0.0)
    fast = Trial("bf16-mixed", False, 170.0, flat, gap=math.inf)  # what measure_arch gives a flat reference's rivals
    assert choose([base, fast], ("32", True)) is base


def test_a_candidate_computing_the_function_as_exactly_qualifies_without_a_loss_curve():
    """fp32 in the other memory format (gradients as close to float64's as the default's) qualifies even when the
    reference's curve is flat or drifts; a candidate that changes the arithmetic (bf16) needs the loss curve."""
    from bronchocli.diagnostics.speed import Trial, choose

    flat = [1.66, 1.60, 1.59, 1.60, 1.58]
    base = Trial("32", True, 100.0, flat, gap=0.0, exact=True)
    contiguous = Trial("32", False, 121.0, flat, gap=math.inf, exact=True)
    bf16 = Trial("bf16-mixed", True, 180.0, flat, gap=math.inf, exact=False)
    assert contiguous.qualifies and not bf16.qualifies
    assert choose([base, contiguous, bf16], ("32", True)) is contiguous
    slow = Trial("32", False, 104.0, flat, gap=math.inf, exact=True)  # below speed.MIN_GAIN: the default stays
    assert choose([base, slow], ("32", True)) is base
    drifted = Trial("32", False, 121.0, flat, gap=0.09, exact=False)  # neither check passes
    assert not drifted.qualifies and choose([base, drifted], ("32", True)) is base
    tracks = Trial("bf16-mixed", True, 180.0, flat, gap=0.01, exact=False)  # a loss curve that tracks suffices
    assert choose([base, tracks], ("32", True)) is tracks


def _speed_trainer(tmp_path, arch, precision="32", channels_last=True, frozen=0, cache=None):
    from bronchocli.diagnostics.selftest import synthetic_cache
    from bronchocli.diagnostics.speed import _trainer
    import torch

    cache = cache or synthetic_cache(tmp_path, frames=48, size=32)
    return _trainer(arch, torch.device("cpu"), precision, channels_last, cache, pairs=10, steps=4, seed=0,
                    on_step=lambda step, total: None, backbone="efficientnet_lite0", frozen=frozen)


@pytest.mark.parametrize("arch,frozen", [("baseline", 0), ("convlstm", 7)])
def test_trainer_gradients_are_autograds_and_leave_the_training_as_it_was(tmp_path, one_thread, arch, frozen):
    """training.probe.batch_gradients returns what torch.autograd gives the loss of that batch (computed here
    independently), and a training that asked for them first runs exactly as one that did not."""
    import torch

    from bronchocli.training.probe import batch_gradients

    t = _speed_trainer(tmp_path, arch, frozen=frozen)
    before = {k: v.clone() for k, v in t.net.state_dict().items()}
    torch.manual_seed(5)  # stochastic depth: the same draws for both computations
    rng = torch.get_rng_state()
    loss, grads = batch_gradients(t, 0)
    assert torch.equal(torch.get_rng_state(), rng)
    assert all(torch.equal(before[k], v) for k, v in t.net.state_dict().items())  # BatchNorm statistics too
    assert all(p.grad is None for p in t.net.parameters())
    params = [p for p in t.net.parameters() if p.requires_grad]
    frames, labels = t._batch(0)
    state, total, chunks = None, 0.0, 0
    t.net.train()
    torch.manual_seed(5)
    for start in range(0, labels.shape[1], t.s.chunk):
        out, state = t.net(frames[:, start: start + t.s.chunk + 1], state)
        total = total + t.net.loss(out.float(), labels[:, start: start + t.s.chunk], t.s.rot_loss, t.s.rot_weight,
                                   t.s.rot_scale)
        chunks += 1
    expected = torch.autograd.grad(total, params, allow_unused=True)
    flat = torch.cat([g.flatten() for g in expected if g is not None])
    t.net.load_state_dict(before)
    assert loss == pytest.approx(float(total.detach()) / chunks, rel=1e-5)
    torch.testing.assert_close(grads, flat, rtol=1e-5, atol=1e-7)
    torch.manual_seed(7)
    asked = t.fit().history
    fresh = _speed_trainer(tmp_path, arch, frozen=frozen)
    torch.manual_seed(7)
    fresh = fresh.fit().history
    assert [h["train_loss"] for h in asked] == [h["train_loss"] for h in fresh]


@pytest.mark.parametrize("arch", ["lstm", "conv3d"])
def test_the_gradient_check_tells_a_memory_format_from_a_change_of_arithmetic(tmp_path, one_thread, arch):
    """Real kernels against float64 (an independent computation of the same function): fp32 contiguous within
    speed.GRAD_TOLERANCE of it; fp32 channels-last within 1e-2 (on the Zen 3 its 3-D-conv head's gradients lie
    2e-3 - 9e-3 away: the check's "as exactly as the default" covers that); bf16 autocast far outside both."""
    from bronchocli.diagnostics.speed import exact_gradients, grad_gap, no_stochastic_depth
    from bronchocli.training.probe import batch_gradients
    from bronchocli.diagnostics.selftest import synthetic_cache
    import torch

    cache = synthetic_cache(tmp_path, frames=48, size=96)
    exact = exact_gradients(arch, torch.device("cpu"), cache, pairs=10, seed=0, backbone="efficientnet_lite0",
                            frozen=7)

    def gradients(precision, channels_last):
        t = _speed_trainer(tmp_path, arch, precision, channels_last, frozen=7, cache=cache)
        with no_stochastic_depth(t.net):
            return batch_gradients(t, 0)[1]

    assert grad_gap(gradients("32", False), exact) <= speed.GRAD_TOLERANCE
    assert grad_gap(gradients("32", True), exact) <= 1e-2
    assert grad_gap(gradients("bf16-mixed", True), exact) > 5e-2
    assert grad_gap(exact, exact) == 0 and grad_gap(None, exact) == math.inf and grad_gap(exact[:-1], exact) == math.inf


def test_profile_speed_measures_the_training_on_a_cached_frozen_prefix_as_its_own_entry(cli, tmp_path, one_thread):
    """`profile --speed FILE --backbone B --frozen-stages N` trains on a cached prefix (the default plan's recipe)
    and writes the device's frozen entry, keeping the whole network's; without --speed the options are refused."""
    import torch

    from bronchocli.training.device import device_key

    path = tmp_path / "speed.json"
    speed.write(path, device_key(torch.device("cpu")), ENTRY)  # a whole-network measurement already there
    code, out, err = cli("profile", "--speed", path, "-a", "baseline", "--image-size", "32", "--batch", "2",
                         "--threads", "1", "--backbone", "efficientnet_lite0", "--frozen-stages", "7")
    assert code == 0, out + err
    entry = json.loads(path.read_text())["devices"][device_key(torch.device("cpu"))]
    assert entry["archs"] == ENTRY["archs"]  # kept
    frozen = entry["frozen"][FROZEN]
    assert frozen["measured"]["frozen_stages"] == 7 and frozen["measured"]["backbone"] == "efficientnet_lite0"
    m = frozen["archs"]["baseline"]
    assert m["chosen"] in m["pairs_per_s"] and isinstance(m["reference_learns"], bool)
    assert all(math.isfinite(m["grad_error"][n]) for n in ("fp32 CL", "fp32 contiguous"))  # against float64's
    assert "fp32 contiguous gradient error" in out
    assert f"({FROZEN}: a cached frozen prefix)" in out
    code, out, err = cli("profile", "-a", "baseline", "--frozen-stages", "7")
    assert code == 2 and "--backbone and --frozen-stages are options of --speed" in err and "Traceback" not in err
    before = path.read_text()  # refused before anything is measured or written:
    code, out, err = cli("profile", "--speed", path, "-a", "offsetnet", "-a", "lstm", "--frozen-stages", "7")
    assert code == 2 and err.strip() == ("error: --frozen-stages 7: offsetnet has no backbone stages to freeze (its "
                                         "own backbones); measure it without --frozen-stages"), err
    code, out, err = cli("profile", "--speed", path, "-a", "baseline", "--backbone", "b7", "--frozen-stages", "7")
    assert code == 2 and err.strip() == "error: --backbone b7: not one of efficientnet_b0, efficientnet_lite0", err
    assert path.read_text() == before
