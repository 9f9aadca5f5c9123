"""``model.frozen_stages`` and ``train.backbone_lr``: the levers pretrained backbones open (issue 56).

Frozen stages keep their initial weights and BatchNorm statistics through training steps and BatchNorm
re-estimation; the backbones' rate is a fixed fraction of the head's at every step of the schedule.
"""

from __future__ import annotations

import pytest
import torch

from bronchocli.models import build_model
from bronchocli.training.batchnorm import batchnorms, recalibrate_bn
from bronchocli.training.optimiser import param_groups
from bronchocli.training.network import PoseRegressor


def _net(frozen: int, backbone: str = "efficientnet_lite0") -> PoseRegressor:
    torch.manual_seed(0)
    model = build_model("convlstm", image_size=64, backbone=backbone)
    model.freeze_stages(frozen)
    return PoseRegressor(model, (0.5,) * 3, (0.25,) * 3)


def _frames() -> torch.Tensor:
    return torch.randint(0, 256, (2, 4, 3, 64, 64), generator=torch.Generator().manual_seed(1), dtype=torch.uint8)


def _snapshot(modules) -> dict[str, torch.Tensor]:
    return {f"{i}.{k}": v.clone() for i, m in enumerate(modules) for k, v in m.state_dict().items()}


@pytest.mark.parametrize("backbone", ["efficientnet_b0", "efficientnet_lite0"])
def test_frozen_stages_keep_their_weights_and_statistics_through_training_steps(backbone):
    net = _net(3, backbone)
    stages = net.model.backbone_cur.stages()
    frozen, free = [m for s in stages[:3] for m in s], [m for s in stages[3:] for m in s]
    before_frozen, before_free = _snapshot(frozen), _snapshot(free)
    opt = torch.optim.Adam(param_groups(net, 1e-3, 1.0)[0]["params"], lr=1e-3)
    net.train()
    assert all(not m.training for m in frozen) and all(m.training for m in free)
    for _ in range(2):
        out, _ = net(_frames())
        out.square().mean().backward()
        opt.step()
        opt.zero_grad()
    after_frozen, after_free = _snapshot(frozen), _snapshot(free)
    assert all(torch.equal(before_frozen[k], after_frozen[k]) for k in before_frozen)
    changed = [k for k in before_free if not torch.equal(before_free[k], after_free[k])]
    assert any(k.endswith("running_mean") for k in changed) and any(k.endswith("weight") for k in changed)


def test_batchnorm_re_estimation_leaves_frozen_stages_alone():
    net = _net(9)  # the whole backbone frozen: only the head's BatchNorms are re-estimated
    frozen_bns = [m for m in net.model.backbone_cur.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    assert frozen_bns and not set(map(id, frozen_bns)) & set(map(id, batchnorms(net)))
    before = [m.running_var.clone() for m in frozen_bns]
    head_bn = net.model.fusion[1]
    head_before = head_bn.running_mean.clone()
    recalibrate_bn(net, iter([_frames()]), lambda: torch.autocast("cpu", enabled=False))
    assert all(torch.equal(b, m.running_var) for b, m in zip(before, frozen_bns))
    assert not torch.equal(head_before, head_bn.running_mean)


def test_the_backbones_rate_is_a_fraction_of_the_heads_at_every_step():
    net = _net(2)
    groups = param_groups(net, 1e-3, 0.1)
    assert [g["lr"] for g in groups] == [1e-3, pytest.approx(1e-4)]
    in_backbones = {id(p) for b in net.model.backbones() for p in b.parameters()}
    assert not any(id(p) in in_backbones for p in groups[0]["params"])
    assert all(id(p) in in_backbones and p.requires_grad for p in groups[1]["params"])
    opt = torch.optim.Adam(groups, lr=1e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 1.0 / (k + 1))
    for _ in range(3):
        opt.step()
        sched.step()
        assert opt.param_groups[1]["lr"] == pytest.approx(0.1 * opt.param_groups[0]["lr"])
    assert len(param_groups(_net(9), 1e-3, 0.1)) == 1  # nothing left to train in the backbones
    assert len(param_groups(net, 1e-3, 1.0)) == 1


def test_more_stages_than_the_backbone_has_is_refused():
    model = build_model("baseline", image_size=64)
    with pytest.raises(ValueError, match="9 stages"):
        model.freeze_stages(10)
