"""`bronchopose selftest` on the CPU (as CI runs it), its one-line exit 2 without CUDA, and exit 1 naming failures."""

from __future__ import annotations

import torch

from bronchocli.diagnostics import selftest


def test_selftest_on_the_cpu_trains_resumes_and_reports_throughput(cli):
    code, out, err = cli("selftest", "--device", "cpu", "--arch", "convlstm")
    assert code == 0, (out, err)
    for row in ("torch", "cuDNN", "CUDA devices", "train convlstm", "resume convlstm", "throughput",
                "selftest passed"):
        assert row in out, row
    assert "train loss" in out and "of the bare step" in out and "bitwise identical" in out


def test_selftest_with_cuda_on_a_machine_without_it_is_one_line_exit_2(cli, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code, out, err = cli("selftest", "--device", "cuda")
    assert code == 2 and out == ""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "--device cuda" in lines[0] and "no CUDA device" in lines[0]


def test_selftest_exits_1_naming_the_checks_that_failed(cli, monkeypatch):
    def broken(arch, device, precision, cache):
        if arch == "lstm":
            raise RuntimeError("cuDNN error: CUDNN_STATUS_NOT_SUPPORTED")
        return True, "fine"

    monkeypatch.setattr(selftest, "check_training", broken)
    monkeypatch.setattr(selftest, "check_resume", lambda *a: (False, "weights differ"))
    monkeypatch.setattr(selftest, "check_throughput", lambda *a: (True, "fast"))
    code, out, err = cli("selftest", "--device", "cpu", "--arch", "baseline", "--arch", "lstm")
    assert code == 1
    assert "selftest failed: train lstm, resume baseline" in " ".join(out.split())
    assert "CUDNN_STATUS_NOT_SUPPORTED" in out


def test_unknown_architecture_or_precision_is_exit_2(cli):
    assert cli("selftest", "--arch", "resnet")[0] == 2
    code, _, err = cli("selftest", "--device", "cpu", "--precision", "fp8")
    assert code == 2 and "--precision 'fp8'" in err
