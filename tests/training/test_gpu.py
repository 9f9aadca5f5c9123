"""CUDA: a short bf16 run finishes with the CPU's metrics, and CUDA numerics match the CPU's on a fixed batch."""

from __future__ import annotations

import pytest
import torch
from run_metrics import EXPECTED

from bronchocli.models import build_model
from bronchocli.training.network import PoseRegressor
from bronchocli.training.run import run_cell

pytestmark = pytest.mark.gpu


def test_a_short_bf16_run_on_cuda_finishes_and_logs_every_cpu_metric(tiny_cfg):
    cfg = tiny_cfg.with_values({"train.device": "cuda", "train.precision": "bf16-mixed"})
    result = run_cell(cfg, cfg.cell(arch="convlstm", rot_loss="ce", population="personalized"), progress=False)
    assert result.status == "FINISHED", result.failure_reason
    assert not [m for m in EXPECTED if m not in result.metrics]
    assert result.metrics["train.pairs_seen"] == 4 * 6


@pytest.mark.parametrize("arch", ["baseline", "convlstm", "offsetnet"])
def test_cuda_matches_the_cpu_on_a_fixed_batch(arch):
    torch.manual_seed(0)
    net = PoseRegressor(build_model(arch, image_size=64), (0.5,) * 3, (0.25,) * 3).eval()
    frames = torch.randint(0, 256, (2, 4, 3, 64, 64), dtype=torch.uint8)
    with torch.no_grad():
        cpu, _ = net(frames)
        gpu_net = net.to("cuda")
        fp32, _ = gpu_net(frames.cuda())
        with torch.autocast("cuda", dtype=torch.bfloat16):
            bf16, _ = gpu_net(frames.cuda())
    scale = cpu.abs().max().item() + 1e-6
    assert (fp32.cpu() - cpu).abs().max().item() <= 1e-3 * scale
    assert (bf16.float().cpu() - cpu).abs().max().item() <= 5e-2 * scale
