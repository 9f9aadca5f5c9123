"""Profiling: MAC counts against published figures and hand formulas, memory tracking, the CLI end to end."""

from __future__ import annotations

import json

import pytest
import torch

from bronchocli.errors import BronchoError
from bronchocli.models import build_model
from bronchocli.models import profile as profiling
from bronchocli.models.backbones import EfficientNetB0Features, ResNet34

CPU = torch.device("cpu")


def test_backbone_macs_match_torchvision_published_figures():
    # torchvision lists 3.66 GFLOPS (multiply-adds) for resnet34 and 0.39 for efficientnet_b0 at 224x224;
    # the classifier Linear(1280, 1000) of efficientnet_b0 adds 1.28 M.
    x = torch.randn(1, 3, 224, 224)
    assert profiling.count_macs(ResNet34().eval(), x) / 1e9 == pytest.approx(3.664, abs=5e-4)
    efficientnet = profiling.count_macs(EfficientNetB0Features().eval(), x) + 1_280_000
    assert efficientnet / 1e9 == pytest.approx(0.386, abs=5e-4)


def test_offsetnet_pair_macs_are_two_resnets_and_the_head():
    x = torch.randn(1, 2, 3, 64, 64)
    resnet = profiling.count_macs(ResNet34().eval(), x[:, 0])
    assert profiling.count_macs(build_model("offsetnet", image_size=64).eval(), x) == 2 * resnet + 2000 * 6


class _TinyLSTM(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(4, 8)
        self.lstm = torch.nn.LSTM(8, 16, num_layers=2, batch_first=True)

    def forward(self, x):
        return self.lstm(self.lin(x))


@pytest.mark.parametrize("mkldnn", [True, False])
def test_lstm_macs_are_counted_once_by_formula(mkldnn):
    # batch 3, 5 steps: Linear 4*8 per step; LSTM layer 1: 4*16*(8+16), layer 2: 4*16*(16+16).
    expected = 15 * (4 * 8 + 4 * 16 * 24 + 4 * 16 * 32)
    previous = torch.backends.mkldnn.enabled
    torch.backends.mkldnn.enabled = mkldnn  # without MKLDNN the LSTM decomposes into counted matmuls
    try:
        assert profiling.count_macs(_TinyLSTM(), torch.randn(3, 5, 4)) == expected
    finally:
        torch.backends.mkldnn.enabled = previous


def test_live_tensor_tracker_follows_allocations_and_frees():
    with torch.inference_mode(), profiling._LiveTensorBytes() as tracker:
        a = torch.ones(1000)  # 4000 B
        b = a * 2  # 8000 B live
        b.view(10, 100).relu_()  # a view, in place: nothing new
        del a  # 4000 B
        c = torch.ones(500)  # 6000 B
    assert (tracker.peak, tracker.live) == (8000, 6000)
    del b, c


def test_profile_arch_row():
    row = profiling.profile_arch("conv3d", image_size=64, batch=2, repeats=1, warmup=0, window=2)
    assert row["params"] == 13_983_486 and row["params_m"] == 13.983
    assert row["window"] == 2 and row["batch"] == 2
    assert row["gmacs_per_pair"] > 0 and row["latency_ms_b1"] > 0 and row["latency_ms_bN"] > 0
    assert row["peak_mem_mb"] > 0 and row["weights_mb"] > 13_983_486 * 4 / 2**20
    assert row["pairs_per_s_bN"] == pytest.approx(1e3 / row["latency_ms_bN"])


def test_bad_options_raise_clear_errors():
    with pytest.raises(BronchoError, match="--arch resnet: unknown"):
        profiling.arch_names(["resnet"])
    assert profiling.arch_names(["lstm", "all"]) == list(profiling.ARCHITECTURES)
    with pytest.raises(BronchoError, match="--precision 16-mixed needs --device cuda"):
        profiling.profile_arch("baseline", image_size=64, precision="16-mixed")
    with pytest.raises(BronchoError, match="--batch 0: must be at least 1"):
        profiling.profile_arch("baseline", image_size=64, batch=0)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message shown without CUDA")
def test_cuda_without_cuda_is_a_clear_error(cli):
    code, _, err = cli("profile", "--arch", "baseline", "--device", "cuda")
    assert code == 2 and "--device cuda: CUDA is not available" in err


def test_profile_command_json(cli):
    code, out, _ = cli(
        "profile", "--arch", "baseline", "--image-size", "64", "--batch", "2", "--repeats", "1",
        "--warmup", "0", "--window", "2", "--format", "json",
    )
    assert code == 0
    rows = json.loads(out)
    assert [r["arch"] for r in rows] == ["baseline"]
    assert rows[0]["params"] == 13_967_582 and rows[0]["image_size"] == 64
    assert rows[0]["device"].startswith("cpu")


def test_profile_command_table_and_errors(cli):
    code, out, _ = cli("profile", "-a", "lstm", "--image-size", "64", "--batch", "1", "--repeats", "1", "--window", "1")
    assert code == 0 and "lstm" in out and "14.164" in out and "GMAC" in out
    assert cli("profile", "--arch", "nope")[0] == 2
    assert cli("profile", "--format", "yaml")[0] == 2
