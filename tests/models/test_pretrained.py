"""Loading torchvision-format backbone weights from a local file, and the errors for files that do not fit."""

from __future__ import annotations

import pytest
import torch

from bronchocli.errors import BronchoError
from bronchocli.models import build_model
from bronchocli.models.backbones import EfficientNetB0Features, ResNet34


def _efficientnet_file(path, seed: int = 7):
    """A torchvision-style efficientnet_b0 state dict: our features + a classifier Linear(1280, 1000)."""
    torch.manual_seed(seed)
    state = EfficientNetB0Features().state_dict()
    for k, v in state.items():  # make every tensor distinctive, BN statistics included
        if v.is_floating_point():
            state[k] = torch.randn_like(v)
    state["classifier.1.weight"] = torch.randn(1000, 1280)
    state["classifier.1.bias"] = torch.randn(1000)
    torch.save(state, path)
    return state


@pytest.mark.parametrize("name", ["baseline", "convlstm"])
def test_efficientnet_weights_load_into_both_backbones(name, tmp_path):
    state = _efficientnet_file(tmp_path / "efficientnet_b0.pth")
    model = build_model(name, image_size=64, pretrained=tmp_path / "efficientnet_b0.pth")
    for backbone in model.backbones():
        for k, v in backbone.state_dict().items():
            assert torch.equal(v, state[k]), k
    # Two copies, not one shared network: training one leaves the other alone.
    cur, prev = model.backbones()
    assert cur.features[0][0].weight.data_ptr() != prev.features[0][0].weight.data_ptr()


def test_wrapped_state_dict_and_old_checkpoints_without_bn_counters_load(tmp_path):
    state = _efficientnet_file(tmp_path / "plain.pth")
    old = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    torch.save({"state_dict": old, "epoch": 3}, tmp_path / "wrapped.pth")
    model = build_model("baseline", image_size=64, pretrained=str(tmp_path / "wrapped.pth"))
    assert torch.equal(model.backbone_prev.features[8][0].weight, state["features.8.0.weight"])


def test_resnet34_weights_load_into_offsetnet(tmp_path):
    torch.manual_seed(3)
    state = {k: torch.randn_like(v) if v.is_floating_point() else v for k, v in ResNet34().state_dict().items()}
    torch.save(state, tmp_path / "resnet34.pth")
    model = build_model("offsetnet", image_size=64, pretrained=tmp_path / "resnet34.pth")
    assert torch.equal(model.backbone_cur.fc.weight, state["fc.weight"])
    assert torch.equal(model.backbone_prev.layer3[5].bn2.running_var, state["layer3.5.bn2.running_var"])


def test_corrupted_state_dict_gives_one_clear_error(tmp_path):
    state = _efficientnet_file(tmp_path / "ok.pth")
    del state["features.3.1.block.1.0.weight"]
    state["features.9.0.weight"] = torch.zeros(1)
    state["features.0.0.weight"] = torch.zeros(16, 3, 3, 3)
    torch.save(state, tmp_path / "broken.pth")
    with pytest.raises(BronchoError) as err:
        build_model("lstm", image_size=64, pretrained=tmp_path / "broken.pth")
    msg = str(err.value)
    assert "broken.pth" in msg and "torchvision efficientnet_b0" in msg
    assert "1 missing keys: features.3.1.block.1.0.weight" in msg
    assert "1 unexpected keys: features.9.0.weight" in msg
    assert "features.0.0.weight [16, 3, 3, 3] (expected [32, 3, 3, 3])" in msg
    assert "\n" not in msg


def test_wrong_backbone_family_is_rejected(tmp_path):
    _efficientnet_file(tmp_path / "efficientnet_b0.pth")
    with pytest.raises(BronchoError, match=r"not a torchvision resnet34 state dict: \d+ missing keys: conv1.weight"):
        build_model("offsetnet", image_size=64, pretrained=tmp_path / "efficientnet_b0.pth")


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(BronchoError, match="nope.pth: file not found"):
        build_model("baseline", image_size=64, pretrained=tmp_path / "nope.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(BronchoError, match="junk.pth: not a readable torch state dict"):
        build_model("baseline", image_size=64, pretrained=tmp_path / "junk.pth")
    torch.save([1, 2, 3], tmp_path / "list.pth")
    with pytest.raises(BronchoError, match="list.pth: expected a state dict"):
        build_model("baseline", image_size=64, pretrained=tmp_path / "list.pth")
