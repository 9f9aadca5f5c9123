"""CUDA (marker ``gpu``): a short bf16 run finishes with the CPU's metrics, CUDA numerics match the CPU's, selftest.

The CUDA-vs-CPU comparison is ``diagnostics.selftest.device_agreement``: the fp32 forward runs with TF32 off
(cuDNN convolutions use TF32 by default: 1.6e-3 of the output scale for OffsetNet, emulated, against a
reduction-order difference of ~1e-6 without it), so its limit can be tight enough to catch TF32 itself.
"""

from __future__ import annotations

import pytest
import torch
from run_metrics import EXPECTED

from bronchocli.diagnostics import selftest
from bronchocli.training.run import run_cell

pytestmark = pytest.mark.gpu


def test_a_short_bf16_run_on_cuda_finishes_and_logs_every_cpu_metric(tiny_cfg):
    cfg = tiny_cfg.with_values({"train.device": "cuda", "train.precision": "bf16-mixed"})
    result = run_cell(cfg, cfg.cell(arch="convlstm", rot_loss="ce", population="personalized"), progress=False)
    assert result.status == "FINISHED", result.failure_reason
    assert not [m for m in EXPECTED if m not in result.metrics]
    assert result.metrics["train.pairs_seen"] == 4 * 6


@pytest.mark.parametrize("arch", ["baseline", "lstm", "convlstm", "conv3d", "offsetnet"])
def test_cuda_matches_the_cpu_on_a_fixed_batch(arch):
    torch.manual_seed(0)
    net = selftest.network(arch, torch.device("cpu"), size=64).eval()
    a = selftest.device_agreement(net, torch.device("cuda"), size=64)
    assert a.fp32_error <= a.fp32_tolerance, (a.fp32_error / a.scale, selftest.FP32_TOLERANCE)
    assert a.bf16_error <= a.bf16_tolerance, (a.bf16_error / a.scale, selftest.BF16_TOLERANCE)


@pytest.mark.parametrize("precision", ["bf16-mixed", "16-mixed"])
def test_selftest_passes_on_cuda(precision):
    checks = selftest.run(torch.device("cuda"), precision)
    assert not [c for c in checks if not c.ok], [(c.name, c.detail) for c in checks if not c.ok]
