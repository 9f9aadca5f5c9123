"""The learning-rate schedules of ``train.schedule``: ``onecycle`` against PyTorch's own ``OneCycleLR`` (an
independent implementation: the project's schedule is a ``LambdaLR`` factor of its own), in the loop and across
a resume, and its config check."""

from __future__ import annotations

import textwrap

import pytest
import torch
from loopfakes import FakeSource, TinyNet, samples, settings

from bronchocli import config as C
from bronchocli.errors import ConfigError
from bronchocli.training import checkpoint
from bronchocli.training.loop import Trainer
from bronchocli.training.network import PoseRegressor
from bronchocli.training.schedule import beta1, lr_factor


def trainer(s, seed: int = 0, **kw) -> Trainer:
    torch.manual_seed(seed)
    net = PoseRegressor(TinyNet(), (0.5,) * 3, (0.25,) * 3)
    return Trainer(net, samples(20), samples(8, seed=2), FakeSource(), s, device=torch.device("cpu"), **kw)


def _torch_onecycle(steps: int, pct_start: float, lr: float) -> list[tuple[float, float]]:
    """(lr, beta1) of each optimiser step under torch.optim.lr_scheduler.OneCycleLR's defaults (cosine)."""
    opt = torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=pct_start)
    out = []
    for _ in range(steps):
        g = opt.param_groups[0]
        out.append((g["lr"], g["betas"][0]))
        opt.step()
        if len(out) < steps:  # OneCycleLR refuses a step past its total
            sched.step()
    return out


@pytest.mark.parametrize("steps,warmup_steps", [(100, 30), (500, 150), (37, 5)])
def test_onecycle_follows_pytorchs_onecycle_rate_and_momentum_step_by_step(steps, warmup_steps):
    s = settings(steps=steps, warmup_steps=warmup_steps, schedule="onecycle", lr=2e-3)
    ref = _torch_onecycle(steps, warmup_steps / steps, 2e-3)
    assert [lr_factor(k, s) * 2e-3 for k in range(steps)] == pytest.approx([r[0] for r in ref], rel=1e-9, abs=1e-15)
    assert [beta1(k, s) for k in range(steps)] == pytest.approx([r[1] for r in ref], rel=1e-12)
    # the hand-computed landmarks: lr/25 first, lr at the peak step, lr/250,000 last; beta1 0.95, 0.85, 0.95
    assert lr_factor(0, s) == pytest.approx(1 / 25) and lr_factor(warmup_steps - 1, s) == pytest.approx(1.0)
    assert lr_factor(steps - 1, s) == pytest.approx(1 / 250_000)
    assert (beta1(0, s), beta1(warmup_steps - 1, s), beta1(steps - 1, s)) == pytest.approx((0.95, 0.85, 0.95))


def test_the_other_schedules_leave_adams_beta1_alone():
    assert beta1(3, settings(steps=10, schedule="cosine")) is None
    t = trainer(settings(steps=4, val_every=4, schedule="cosine", warmup_steps=2))
    t.fit()
    assert t.opt.param_groups[0]["betas"] == (0.9, 0.999)


def _seen(t) -> list[tuple[float, float]]:
    """(lr, beta1) that each optimiser step of ``t`` uses, read by a hook before the step."""
    seen: list[tuple[float, float]] = []
    t.opt.register_step_pre_hook(lambda opt, *_: seen.append((opt.param_groups[0]["lr"],
                                                              opt.param_groups[0]["betas"][0])))
    return seen


def _flat(pairs: list[tuple[float, float]]) -> list[float]:
    return [v for pair in pairs for v in pair]


def test_the_loop_steps_with_the_onecycle_rate_and_beta1_and_a_resume_continues_them(tmp_path):
    s = settings(steps=12, val_every=6, warmup_steps=4, schedule="onecycle", lr=1e-2)
    straight = trainer(s)
    seen = _seen(straight)
    straight.fit()
    ref = _torch_onecycle(12, 4 / 12, 1e-2)
    assert _flat(seen) == pytest.approx(_flat(ref), rel=1e-9)

    first = trainer(s, ckpt_dir=tmp_path)
    first.s = settings(steps=6, val_every=6, warmup_steps=4, schedule="onecycle", lr=1e-2)  # stopped half-way
    first.fit()
    second = trainer(s, seed=123)
    second.load_state(checkpoint.load(tmp_path / "last.pt"))
    resumed = _seen(second)
    second.fit()
    assert _flat(resumed) == pytest.approx(_flat(ref[6:]), rel=1e-9)  # the rate and beta1 continue where they stopped
    a, b = straight.net.state_dict(), second.net.state_dict()
    assert all(torch.allclose(a[k].float(), b[k].float(), atol=1e-6) for k in a)


def test_onecycle_without_a_rising_phase_is_refused_naming_the_warmup(tmp_path):
    path = tmp_path / "experiments.yaml"
    path.write_text(textwrap.dedent("""\
        name: t
        train: {steps: 100, warmup: 0.0, schedule: onecycle}
        """))
    with pytest.raises(ConfigError) as exc:
        C.load_config(path)
    msg = str(exc.value)
    assert msg == (f"invalid config: {path}:2: train: schedule onecycle rises over train.warmup of the steps: warmup "
                   "0.0 x steps 100 is under 2 steps (e.g. warmup: 0.3, OneCycleLR's default)")  # the reason alone
    path.write_text("name: t\ntrain: {steps: 100, warmup: 0.3, schedule: onecycle}\n")
    assert C.load_config(path).train.schedule == "onecycle"
