"""The CUDA path's defects found by emulation (issue 21), each proven fixed on the CPU with CUDA faked.

Every test here failed before its fix: the MIG listing, the per-GPU frame-cache budget, an explicit device
that does not exist, the run's device tags, TF32 in the CUDA-vs-CPU comparison, the LSTM under bf16
autocast, BatchNorm re-estimation without host syncs, the GPU benchmark's nvidia-smi id and CPU precision,
and 16-mixed runs that skipped every step.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from loopfakes import FakeSource, samples, settings
from torch import nn

from bronchocli.data import batches
from bronchocli.diagnostics.dispatch import OpCounter
from bronchocli.models import build_model
from bronchocli.runs.client import client_for
from bronchocli.runs.contract import gpu_share
from bronchocli.sweep.placement import pin_env, share_counts, smi_gpu_ids, visible_gpus
from bronchocli.training import device
from bronchocli.training.loop import NothingTrained, Trainer, recalibrate_bn
from bronchocli.training.network import PoseRegressor

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"

MIG_LISTING = """\
GPU 0: NVIDIA A100-SXM4-40GB (UUID: GPU-5d5ba0d6-0000-0000-0000-000000000000)
  MIG 3g.20gb     Device  0: (UUID: MIG-aaaa0000-0000-0000-0000-000000000000)
  MIG 3g.20gb     Device  1: (UUID: MIG-aaaa0000-0000-0000-0000-000000000001)
GPU 1: NVIDIA A100-SXM4-40GB (UUID: GPU-5d5ba0d6-0000-0000-0000-000000000001)
"""


pytestmark = pytest.mark.usefixtures("one_thread")


# -- 2. MIG lines are not GPUs --------------------------------------------------------------------


def test_mig_instance_lines_of_nvidia_smi_are_not_counted_as_gpus():
    assert smi_gpu_ids(MIG_LISTING) == ["0", "1"]
    assert visible_gpus({}, smi=MIG_LISTING) == ["0", "1"]
    eight = "".join(f"GPU {i}: NVIDIA H100 (UUID: GPU-{i})\n  MIG 1g.10gb Device 0: (UUID: MIG-{i})\n"
                    for i in range(8))
    assert visible_gpus({}, smi=eight) == [str(i) for i in range(8)]
    env = pin_env("1", 3)
    assert env == {"CUDA_VISIBLE_DEVICES": "1", "CUDA_DEVICE_ORDER": "PCI_BUS_ID", "BRONCHOPOSE_GPU_SHARE": "3"}


# -- 7. --per-gpu K: the frame cache budget is shared -------------------------------------------------


def test_workers_sharing_a_gpu_each_keep_their_frame_cache_within_their_share(monkeypatch):
    assert share_counts(["0", "1", "0", "1", "0"]) == [3, 2, 3, 2, 3] and share_counts([None]) == [1]
    assert gpu_share({"BRONCHOPOSE_GPU_SHARE": "4"}) == 4 and gpu_share({}) == 1
    assert gpu_share({"BRONCHOPOSE_GPU_SHARE": "x"}) == 1
    free = 80 * 2**30
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (free, free))
    cache = 10 * 2**30  # 12.5 % of the free memory: fits one process's 40 %, not a quarter of it
    cuda = torch.device("cuda")
    assert batches._fits_on_device(cache, cuda, share=1)
    assert not batches._fits_on_device(cache, cuda, share=4)  # 4 copies would take 50 % together
    assert batches._fits_on_device(cache, cuda, share=2)
    # Each of K workers measures before any has allocated: K copies stay within the budget together.
    k = 4
    fits = [batches._fits_on_device(cache // 2, cuda, share=k) for _ in range(k)]
    assert all(fits) and k * cache // 2 <= batches.DEVICE_BUDGET * free


# -- 3. an explicit device that does not exist; the run's device tags -------------------------------------


def test_explicit_cuda_without_cuda_is_an_error_and_auto_falls_back(tiny_cfg, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(device.DeviceUnavailable, match="train.device: cuda, but torch .* sees no CUDA device"):
        device.device_for(tiny_cfg.with_values({"train.device": "cuda"}))
    assert device.device_for(tiny_cfg.with_values({"train.device": "auto"})).type in ("cpu", "mps")
    assert device.device_for(tiny_cfg.with_values({"train.device": "cpu"})).type == "cpu"


def test_train_with_cuda_on_a_machine_without_it_is_one_line_exit_2_and_leaves_no_run(cli, tiny_project,
                                                                                    monkeypatch):
    monkeypatch.chdir(tiny_project)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code, out, err = cli("train", "-a", "baseline", "-l", "mse", "-P", "personalized", "-q",
                         "--set", "train.device=cuda")
    assert code == 2, (out, err)
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "train.device: cuda" in lines[0] and "Traceback" not in err
    from bronchocli.config import load_config

    cfg = load_config(tiny_project / "experiments.yaml")
    client = client_for(cfg)
    exps = client.search_experiments()
    runs = client.search_runs([e.experiment_id for e in exps]) if exps else []
    assert not [r for r in runs if r.data.tags.get("cell_key")], "a run was left behind"


def test_every_run_is_tagged_with_its_device_precision_and_gpu_name(tiny_cfg, monkeypatch, tmp_path):
    (tmp_path / "none.json").write_text('{"version": 1, "devices": {}}')  # nothing measured: the defaults
    tiny_cfg = tiny_cfg.with_values({"train.speed_settings": str(tmp_path / "none.json")})
    cpu = device.env_tags(tiny_cfg.with_values({"train.device": "cpu"}), torch.device("cpu"), "baseline")
    assert cpu == {"env.device": "cpu", "env.precision": "32", "env.gpu_name": "none"}
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H100 80GB HBM3")
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)
    tags = device.env_tags(tiny_cfg, torch.device("cuda"), "baseline")
    assert tags == {"env.device": "cuda", "env.precision": "bf16-mixed", "env.gpu_name": "NVIDIA H100 80GB HBM3"}
    fp32 = device.env_tags(tiny_cfg.with_values({"train.precision": "32"}), torch.device("cuda"), "baseline")
    assert fp32["env.precision"].startswith("32 (tf32")


def test_a_run_logs_the_measured_speed_setting_and_an_explicit_precision_wins(tiny_project, monkeypatch, tmp_path):
    """``auto`` takes the architecture's measured setting for this device, logged as params and the env tag;
    ``--set train.precision=32`` (a config value) wins over it and says so."""
    from bronchocli import speed
    from bronchocli.config import load_config
    from bronchocli.training.run import run_cell

    monkeypatch.chdir(tiny_project)
    monkeypatch.setattr(device, "bf16_fast", lambda dev: True)  # as on this project's CPU (avx512_bf16)
    settings = tmp_path / "speed.json"
    speed.write(settings, "cpu", {"measured": {"date": "2026-11-26"}, "archs": {
        "offsetnet": {"precision": "bf16-mixed", "channels_last": False, "chosen": "bf16 contiguous",
                      "pairs_per_s": {"bf16 contiguous": 10.0}}}})
    cfg = load_config(tiny_project / "experiments.yaml").with_values(
        {"train.steps": 2, "train.val_every": 2, "train.speed_settings": str(settings)})
    cell = dict(arch="offsetnet", rot_loss="mse", population="personalized")
    logged = []
    for values in ({}, {"train.precision": "32"}):
        c = cfg.with_values(values)
        result = run_cell(c, c.cell(**cell), progress=False)
        assert result.status == "FINISHED", result.failure_reason
        run = client_for(c).get_run(result.run_id)
        logged.append((run.data.tags, run.data.params))
    (tags, params), (tags32, params32) = logged
    assert (tags["env.device"], tags["env.precision"], tags["env.gpu_name"]) == ("cpu", "bf16-mixed", "none")
    assert (params["speed.precision"], params["speed.channels_last"]) == ("bf16-mixed", "false")
    assert params["speed.source"].startswith("measured (speed.json settings, cpu, 2026-11-26)")
    assert tags32["env.precision"] == "32" and params32["speed.precision"] == "32"
    assert params32["speed.channels_last"] == "false"  # still the measured memory format: only precision was set
    assert "config overrides train.precision" in params32["speed.source"]


# -- 4. the CUDA-vs-CPU comparison runs without TF32 -----------------------------------------------------------


def test_exact_fp32_turns_tf32_off_inside_and_restores_it():
    device.set_tf32(True)
    try:
        with device.exact_fp32():
            assert torch.backends.cudnn.conv.fp32_precision == "ieee"
            assert torch.backends.cuda.matmul.fp32_precision == "ieee"
        assert torch.backends.cudnn.conv.fp32_precision == "tf32"
    finally:
        device.set_tf32(False)


def test_the_cuda_vs_cpu_comparison_runs_its_fp32_forward_without_tf32():
    from bronchocli.diagnostics import selftest

    seen = []
    net = PoseRegressor(build_model("offsetnet", image_size=32), (0.5,) * 3, (0.25,) * 3).eval()
    net.model.head.register_forward_hook(lambda *a: seen.append(torch.backends.cudnn.conv.fp32_precision))
    device.set_tf32(True)  # what a CUDA run sets for training
    try:
        check = selftest.device_agreement(net, torch.device("cpu"), size=32)
    finally:
        device.set_tf32(False)
    assert seen[:2] == ["tf32", "ieee"]  # the reference forward as configured, the compared one exact
    assert check.fp32_error == 0.0 and check.fp32_error <= check.fp32_tolerance


# -- 5. the LSTM stays in fp32 under bf16 autocast ------------------------------------------------------------


def test_the_lstm_runs_in_fp32_with_autocast_off_under_bf16_and_nothing_is_fp16():
    torch.manual_seed(0)
    net = PoseRegressor(build_model("lstm", image_size=32), (0.5,) * 3, (0.25,) * 3)
    inside = []
    net.model.lstm.register_forward_pre_hook(
        lambda m, args: inside.append((torch.is_autocast_enabled("cpu"), args[0].dtype)))
    frames = torch.randint(0, 256, (1, 3, 3, 32, 32), dtype=torch.uint8)
    with OpCounter() as ops, torch.autocast("cpu", dtype=torch.bfloat16):
        out, (h, c) = net(frames)
    assert inside == [(False, torch.float32)]
    assert h.dtype == c.dtype == torch.float32 and out.dtype == torch.float32
    assert ops.dtypes[torch.bfloat16] > 0 and ops.dtypes[torch.float16] == 0


# -- 6. BatchNorm re-estimation without host syncs -----------------------------------------------------------------


def test_batchnorm_reestimation_reads_nothing_back_from_the_device_and_averages_exactly():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(3, 4, 3), nn.BatchNorm2d(4), nn.ReLU(), nn.Conv2d(4, 4, 1), nn.BatchNorm2d(4))
    batches_ = [torch.randn(5, 3, 8, 8) + i for i in range(4)]
    with OpCounter() as ops:
        n = recalibrate_bn(net, iter(batches_), lambda: torch.autocast("cpu", enabled=False))
    assert n == 4 and ops.syncs == 0, ops.by_name
    with torch.no_grad():
        conv = [net[0](b) for b in batches_]  # what the first BatchNorm sees
    mean = torch.stack([c.mean((0, 2, 3)) for c in conv]).mean(0)
    var = torch.stack([c.transpose(0, 1).flatten(1).var(1, unbiased=True) for c in conv]).mean(0)
    assert torch.allclose(net[1].running_mean, mean, atol=1e-5)  # the plain average of the 4 batch statistics
    assert torch.allclose(net[1].running_var, var, atol=1e-4)
    assert net[1].momentum == 0.1 and int(net[1].num_batches_tracked) == 4


# -- 8. the GPU benchmark: nvidia-smi's id of torch's device, autocast in the CPU smoke run ----------------------


@pytest.fixture
def bench_gpu(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    sys.modules.pop("bench_gpu", None)
    import bench_gpu

    return bench_gpu


def test_gpu_benchmark_samples_the_gpu_torch_uses_not_the_index_under_cuda_visible_devices(bench_gpu, monkeypatch):
    props = SimpleNamespace(uuid="5d5ba0d6-0000-0000-0000-000000000003", pci_domain_id=0, pci_bus_id=0x41,
                            pci_device_id=0)
    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: props)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3")
    gpu = bench_gpu.smi_id(torch.device("cuda", 0))  # torch's cuda:0 is physical GPU 3 here
    assert gpu == "GPU-5d5ba0d6-0000-0000-0000-000000000003"
    assert bench_gpu.SmSampler(gpu).command()[:3] == ["nvidia-smi", "-i", gpu]
    props.uuid = ""
    assert bench_gpu.smi_id(torch.device("cuda", 0)) == "00000000:41:00.0"


def test_gpu_benchmark_cpu_smoke_run_uses_the_requested_autocast_precision(bench_gpu):
    device, precision = bench_gpu.run_settings(bench_gpu.parse_args(["--device", "cpu"]))
    assert device.type == "cpu" and precision == "bf16-mixed"
    import engine_bench

    with OpCounter() as ops:
        engine_bench.bare_step_rate("offsetnet", 16, 2, device, precision, seconds=0.0)
    assert ops.dtypes[torch.bfloat16] > 0


# -- 9. 16-mixed never trains nothing silently ------------------------------------------------------------------------


class Wide(nn.Module):
    """A pair model whose gradients are large (labels in the thousands): what made the default scale overflow."""

    temporal = recurrent = False

    def __init__(self) -> None:
        super().__init__()
        self.head = nn.Linear(6, 6)

    def forward(self, x, state=None):
        b, t = x.shape[:2]
        return self.head(x.mean((3, 4)).repeat(1, 1, 2)[:, 1:]).view(b, t - 1, 6), None


def _fp16_trainer(label_scale: float, steps: int = 4):
    torch.manual_seed(0)
    net = PoseRegressor(Wide(), (0.5,) * 3, (0.25,) * 3)
    s = settings(steps=steps, val_every=steps, precision="16-mixed", lr=1e-2)
    return Trainer(net, samples(20, scale=label_scale), samples(8, seed=2), FakeSource(), s,
                   device=torch.device("cpu"))


def test_a_short_16_mixed_run_takes_its_optimiser_steps():
    t = _fp16_trainer(label_scale=300.0)
    before = {k: v.clone() for k, v in t.net.state_dict().items()}
    t.fit()
    assert t.skipped_steps == 0
    assert not torch.equal(before["model.head.weight"], t.net.state_dict()["model.head.weight"])


def test_a_16_mixed_run_whose_every_step_is_skipped_fails_loudly(caplog):
    t = _fp16_trainer(label_scale=1e7)
    with pytest.raises(NothingTrained, match="all 4 optimiser steps .* skipped"):
        t.fit()
    assert "skipped 4 of the last optimiser steps" in caplog.text
