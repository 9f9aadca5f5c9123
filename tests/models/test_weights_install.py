"""`bronchopose weights install`: torchvision's ImageNet files a user brings, checked and put where
``model.pretrained: imagenet`` reads them; ``imagenet-if-present`` falls back to random initialisation, said."""

from __future__ import annotations

import hashlib

import pytest
import torch

from bronchocli.errors import BronchoError
from bronchocli.models import build_model, initialisation
from bronchocli.models import pretrained as pt
from bronchocli.models.backbones import EfficientNetB0Features, ResNet34


def _torchvision_like(path, seed: int = 5) -> dict:
    """A synthetic efficientnet_b0 state dict of torchvision's keys and shapes (features + classifier)."""
    torch.manual_seed(seed)
    state = {k: torch.randn_like(v) if v.is_floating_point() else v
             for k, v in EfficientNetB0Features().state_dict().items()}
    state["classifier.1.weight"] = torch.randn(1000, 1280)
    state["classifier.1.bias"] = torch.randn(1000)
    torch.save(state, path)
    return state


@pytest.fixture
def hub(tmp_path, monkeypatch):
    """PyTorch's hub cache in tmp_path, and torchvision's efficientnet file name made to carry the synthetic file's
    sha256 prefix (as torchvision's names carry their files')."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None)
    src = tmp_path / "downloaded.pth"
    state = _torchvision_like(src)
    digest = hashlib.sha256(src.read_bytes()).hexdigest()
    monkeypatch.setitem(pt.IMAGENET_FILES, "efficientnet_b0", f"efficientnet_b0_rwightman-{digest[:8]}.pth")
    return src, state


def test_an_installed_file_is_what_imagenet_initialisation_loads(hub, cli):
    src, state = hub
    code, out, err = cli("weights", "install", src)
    assert code == 0, err
    dest = pt.hub_checkpoints() / pt.IMAGENET_FILES["efficientnet_b0"]
    assert dest.read_bytes() == src.read_bytes() and str(dest) in out.replace("\n", "")
    model = build_model("convlstm", image_size=64, pretrained="imagenet")
    for backbone in model.backbones():
        for k, v in backbone.state_dict().items():
            assert torch.equal(v, state[k]), k
    assert initialisation("imagenet-if-present", ["baseline"])["baseline"] == f"imagenet:{dest.name}"


def test_a_file_that_is_not_torchvisions_is_refused_in_one_line(hub, tmp_path, cli):
    other = tmp_path / "other.pth"
    _torchvision_like(other, seed=6)  # right keys and shapes, other bytes: its checksum is not torchvision's
    code, out, err = cli("weights", "install", other)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "sha256" in err and "not torchvision's" in err
    assert not (pt.hub_checkpoints() / pt.IMAGENET_FILES["efficientnet_b0"]).exists()


def test_right_checksum_wrong_shapes_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    state = ResNet34().state_dict()
    state["fc.weight"] = torch.zeros(10, 512)  # a 10-class head: not torchvision's resnet34
    state["fc.bias"] = torch.zeros(10)
    path = tmp_path / "r.pth"
    torch.save(state, path)
    monkeypatch.setitem(pt.IMAGENET_FILES, "resnet34", f"resnet34-{hashlib.sha256(path.read_bytes()).hexdigest()[:8]}.pth")
    with pytest.raises(BronchoError, match="shape mismatches: fc.weight"):
        pt.install_weights(path)


def test_imagenet_if_present_without_the_file_starts_random_and_says_so(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None)
    torch.manual_seed(0)
    with pytest.warns(UserWarning, match="starts from random weights"):
        model = build_model("baseline", image_size=64, pretrained="imagenet-if-present")
    torch.manual_seed(0)
    random = build_model("baseline", image_size=64)
    for k, v in random.state_dict().items():
        assert torch.equal(v, model.state_dict()[k]), k
    with pytest.warns(UserWarning, match="resnet34 starts from random weights"):
        assert initialisation("imagenet-if-present", ["offsetnet"])["offsetnet"] == "random"
