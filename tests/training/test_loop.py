"""The training loop on synthetic tensors: budget, schedule, accumulation, BatchNorm, best weights, resume."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from loopfakes import FakeSource, TinyNet, samples, settings
from torch import nn

from bronchocli.data.batches import Samples
from bronchocli.training import checkpoint
from bronchocli.training.loop import NonFiniteLoss, Settings, Trainer, lr_factor, recalibrate_bn
from bronchocli.training.network import PoseRegressor


def trainer(s: Settings, seed: int = 0, train: Samples | None = None, **kw) -> Trainer:
    torch.manual_seed(seed)
    net = PoseRegressor(TinyNet(), (0.5,) * 3, (0.25,) * 3)
    return Trainer(net, train or samples(20), samples(8, seed=2), FakeSource(), s, device=torch.device("cpu"), **kw)


def test_learning_rate_warms_up_linearly_then_decays_to_zero_on_a_cosine():
    s = settings(steps=100, warmup_steps=10, schedule="cosine")
    assert [lr_factor(k, s) for k in (0, 4, 9)] == pytest.approx([0.1, 0.5, 1.0])
    assert lr_factor(10, s) == pytest.approx(1.0)
    assert lr_factor(55, s) == pytest.approx(0.5)  # half-way through the decay
    assert lr_factor(99, s) == pytest.approx(0.5 * (1 + math.cos(math.pi * 89 / 90)))
    assert lr_factor(50, settings(steps=100, schedule="constant")) == 1.0


def test_the_budget_is_optimiser_steps_and_every_step_sees_the_same_number_of_pairs():
    t = trainer(settings(steps=6, micro_pairs=4, accum=3, val_every=3))
    fit = t.fit()
    assert fit.steps == 6 and t.micro == 18  # 3 micro-batches per step
    assert fit.pairs_seen == 6 * 4 * 3
    assert fit.validations == 2 and [h["step"] for h in fit.history] == [3.0, 6.0]
    assert fit.stop_reason == "budget"
    assert fit.epochs == pytest.approx(18 / 5)  # 20 samples in batches of 4 = 5 per epoch


def test_early_stopping_ends_on_the_best_weights(monkeypatch):
    t = trainer(settings(steps=20, val_every=2, patience=2))
    losses = iter([3.0, 2.0, 2.5, 2.6, 1.0])
    snapshots = {}

    def validate(samples=None):
        snapshots[t.step] = {k: v.clone() for k, v in t.net.state_dict().items()}
        return {"val_loss": next(losses), **{f"val.{m}": 0.0 for m in ("pos_l2", "rot_l2", "de", "ce")}}

    monkeypatch.setattr(t, "validate", validate)
    fit = t.fit()
    assert fit.stop_reason == "early_stop" and fit.steps == 8  # 2.5 and 2.6 do not improve on 2.0
    assert fit.best_step == 4 and fit.best_val_loss == 2.0
    final = t.net.state_dict()
    assert all(torch.equal(final[k], snapshots[4][k]) for k in final)
    assert not all(torch.equal(final[k], snapshots[8][k]) for k in final)


def test_stop_at_ratio_ends_at_the_first_validation_that_reaches_it_and_the_cost_is_read_there(monkeypatch):
    from dataclasses import replace

    from bronchocli.training.cost import COST_TARGET, cost_of_learning

    t = trainer(replace(settings(steps=20, val_every=2, micro_pairs=4), stop_at_ratio=0.9))
    ratios = iter([1.2, 0.95, 0.89, 0.5])

    def validate(samples=None):
        return {"val_loss": 1.0, "val.ratio.pos_l2": next(ratios),
                **{f"val.{m}": 0.0 for m in ("pos_l2", "rot_l2", "de", "ce")}}

    monkeypatch.setattr(t, "validate", validate)
    fit = t.fit()
    assert fit.stop_reason == "target" and fit.steps == 6  # 0.89 at the third validation
    core = [h["train.core_s"] for h in fit.history]
    assert all(c > 0 for c in core) and core == sorted(core)  # CPU seconds of training, growing
    assert COST_TARGET == 0.90
    assert cost_of_learning(fit.history) == {"cost.pairs_to_0.90": 6 * 4, "cost.step_to_0.90": 6.0,
                                             "cost.core_s_to_0.90": core[2]}
    assert cost_of_learning(fit.history, target=0.5) == {}  # never reached: nothing claimed
    assert cost_of_learning([{"step": 2.0, "train.pairs_seen": 8.0, "val.ratio.pos_l2": math.nan}]) == {}


def test_the_cost_as_one_number_ranks_every_run_that_learned_before_every_run_that_did_not():
    from bronchocli.training.cost import cost_value

    reached = cost_value({"cost.pairs_to_0.90": 8000.0, "train.pairs_seen": 8000.0, "val_best.ratio.pos_l2": 0.89})
    close = cost_value({"train.pairs_seen": 12000.0, "val_best.ratio.pos_l2": 0.93})
    far = cost_value({"train.pairs_seen": 12000.0, "val_best.ratio.pos_l2": 1.01})
    assert reached == 8000.0
    assert close == pytest.approx(12000 * 1.03) and far == pytest.approx(12000 * 1.11)
    assert reached < 12000 < close < far  # a run that never reached 0.90 costs more than its budget
    assert math.isnan(cost_value({"train.pairs_seen": 100.0}))


def test_batchnorm_recalibration_sets_the_plain_average_of_the_batch_statistics():
    bn_net = nn.Sequential(nn.BatchNorm1d(3))
    bn_net[0].running_mean.fill_(100.0)  # stale statistics from "earlier weights"
    batches = [torch.randn(8, 3) + i for i in range(4)]
    n = recalibrate_bn(bn_net, iter(batches), lambda: torch.autocast("cpu", enabled=False))
    assert n == 4
    expected = torch.stack([b.mean(0) for b in batches]).mean(0)
    assert torch.allclose(bn_net[0].running_mean, expected, atol=1e-6)
    expected_var = torch.stack([b.var(0, unbiased=True) for b in batches]).mean(0)
    assert torch.allclose(bn_net[0].running_var, expected_var, atol=1e-5)
    assert bn_net[0].momentum == 0.1 and bn_net.training  # restored


def test_a_resumed_run_continues_exactly_where_it_stopped(tmp_path):
    straight = trainer(settings(steps=8, val_every=4, bn_recalibrate=2, augment=True))
    straight.fit()

    first = trainer(settings(steps=8, val_every=4, bn_recalibrate=2, augment=True), ckpt_dir=tmp_path)
    first.s = settings(steps=4, val_every=4, bn_recalibrate=2, augment=True)  # stop half-way, as an interrupt would
    first.fit()
    state = checkpoint.load(tmp_path / "last.pt")
    second = trainer(settings(steps=8, val_every=4, bn_recalibrate=2, augment=True), seed=123)
    second.load_state(state)
    second.best_state = None  # the half-way "best" must not decide the end: compare the weights as trained
    second.fit()
    a, b = straight.net.state_dict(), second.net.state_dict()
    assert all(torch.allclose(a[k].float(), b[k].float(), atol=1e-6) for k in a)
    assert second.micro == straight.micro


def test_a_non_finite_loss_stops_the_run_with_the_reason():
    bad = samples(20)
    bad.labels[3, 0, 0] = np.inf
    t = trainer(settings(steps=20, val_every=10), train=bad)
    with pytest.raises(NonFiniteLoss, match="non-finite training loss by step"):
        t.fit()


def test_standardised_labels_are_undone_at_prediction():
    net = PoseRegressor(TinyNet(), (0.5,) * 3, (0.25,) * 3, label_mean=(5, 0, 0, 0, 0, 1),
                        label_std=(2, 1, 1, 10, 1, 1), standardized=True).eval()
    frames = FakeSource()(np.array([[0, 1], [2, 3]]))
    with torch.no_grad():
        z, _ = net.model((frames.float() / 255 - 0.5) / 0.25)
        pred, _ = net(frames)
    expected = z * torch.tensor([2, 1, 1, 10, 1, 1.0]) + torch.tensor([5, 0, 0, 0, 0, 1.0])
    assert torch.allclose(pred, expected, atol=1e-5)
    gt = pred + torch.tensor([2.0, 0, 0, 10.0, 0, 0])  # one std off in x and in alpha
    assert net.loss(pred, gt, "mse", 1.0).item() == pytest.approx(1 / 3 + 1 / 3, rel=1e-5)


def shifted_samples(n: int, seed: int) -> tuple[Samples, FakeSource]:
    """Pairs whose label is a visible function of the images: frame t+1 is frame t brightened by 8 x label."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 120, (n, 3, 8, 8))
    labels = rng.uniform(-1, 1, (n, 1, 6)).astype(np.float32)
    labels[..., 1:] = 0.0
    nxt = np.clip(base + 8.0 * (labels[:, 0, 0] + 1.0)[:, None, None, None] * 4, 0, 255)
    source = FakeSource(n=2 * n)
    source.bank = torch.from_numpy(np.concatenate([base, nxt]).astype(np.uint8))
    frames = np.stack([np.arange(n), np.arange(n) + n], 1)
    return Samples(frames, labels, np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64), ("t",)), source


def test_the_loop_learns_what_the_images_show_and_beats_the_training_mean():
    train, source = shifted_samples(64, seed=0)
    torch.manual_seed(0)
    mean = train.labels.reshape(-1, 6).mean(0)
    std = np.maximum(train.labels.reshape(-1, 6).std(0), 1e-3)
    net = PoseRegressor(TinyNet(), (0.5,) * 3, (0.25,) * 3, mean, std, standardized=True)
    s = settings(steps=150, micro_pairs=16, val_every=50, lr=3e-3, bn_recalibrate=4, warmup_steps=10,
                 schedule="cosine")
    t = Trainer(net, train, train.subset(range(32)), source, s, device=torch.device("cpu"))
    t.fit()
    net.eval()
    with torch.no_grad():
        pred, _ = net(source(train.frames))
    err = (pred[:, 0, 0] - torch.from_numpy(train.labels[:, 0, 0])).abs().mean().item()
    blind = np.abs(train.labels[:, 0, 0] - mean[0]).mean()
    assert err < 0.5 * blind  # far better than the image-blind constant
    assert pred[:, 0, 0].std().item() > 0.5 * train.labels[:, 0, 0].std()  # varies with the input


def _first_step_gradients(clip: float | None) -> list[torch.Tensor]:
    """The gradients the optimiser's first step reads, with ``train.grad_clip`` = ``clip``."""
    from dataclasses import replace

    t = trainer(replace(settings(steps=1, val_every=1), grad_clip=clip))
    seen: list[list[torch.Tensor]] = []
    t.opt.register_step_pre_hook(
        lambda *_: seen.append([p.grad.detach().clone() for p in t.net.parameters() if p.grad is not None]))
    t.fit()
    return seen[0]


def test_grad_clip_scales_the_gradient_down_to_the_clip_norm_and_keeps_its_direction():
    raw = _first_step_gradients(None)
    norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in raw])).item()
    assert norm > 1e-3
    clipped = _first_step_gradients(1e-3)  # the same seed and batch: the same raw gradients
    assert torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in clipped])).item() \
        == pytest.approx(1e-3, rel=1e-4)
    for g, c in zip(raw, clipped):
        torch.testing.assert_close(c, g * (1e-3 / norm), rtol=1e-4, atol=1e-9)
    untouched = _first_step_gradients(norm * 10)  # a norm below the clip is left as it is
    for g, c in zip(raw, untouched):
        torch.testing.assert_close(c, g)


class _DropoutNet(TinyNet):
    """TinyNet with dropout before its head: training draws from torch's global random stream every step."""

    def __init__(self) -> None:
        super().__init__()
        self.drop = nn.Dropout(0.5)

    def forward(self, x, state=None):
        b, t = x.shape[:2]
        pairs = torch.cat([x[:, 1:], x[:, :-1]], dim=2).reshape(b * (t - 1), 6, *x.shape[-2:])
        z = self.drop(torch.relu(self.bn(self.conv(pairs))).mean((2, 3)))
        return self.head(z).view(b, t - 1, 6), None


def _gradient_stream(val_every: int, draws: bool = False) -> list[torch.Tensor]:
    """Every optimiser step's gradients (flattened) of one run that validates every ``val_every`` steps, with
    BatchNorm re-estimation and the mode gap measured at each validation (``draws``: each validation also
    draws from torch's global random stream, as a validation with dropout on would)."""
    torch.manual_seed(0)
    net = PoseRegressor(_DropoutNet(), (0.5,) * 3, (0.25,) * 3)
    s = settings(steps=6, val_every=val_every, bn_recalibrate=2)
    t = Trainer(net, samples(20), samples(8, seed=2), FakeSource(), s, device=torch.device("cpu"))
    if draws:
        validate = t.validate
        t.validate = lambda *a, **kw: (torch.rand(1), validate(*a, **kw))[1]
    seen: list[torch.Tensor] = []
    t.opt.register_step_pre_hook(
        lambda *_: seen.append(torch.cat([p.grad.flatten() for p in t.net.parameters() if p.grad is not None])))
    t.fit()
    return seen


def test_training_does_not_depend_on_how_often_it_validates():
    """Validation's re-estimation and mode-gap batches come from fixed far positions of the batch order and run
    without dropout: the training steps (their batches, dropout draws, gradients) are the same at any cadence,
    so the cost of learning read at different `val_every` describes one training run."""
    often, rarely = _gradient_stream(1), _gradient_stream(6)
    assert len(often) == len(rarely) == 6
    for a, b in zip(often, rarely):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # the check can fail: a validation that consumed random numbers would change every later step's dropout
    drawn = _gradient_stream(1, draws=True)
    assert torch.equal(drawn[0], often[0]) and not torch.equal(drawn[1], often[1])
