"""`bronchopose weights install`: torchvision's ImageNet files a user brings, checked and put where
``model.pretrained: imagenet`` reads them; ``imagenet-if-present`` falls back to random initialisation, said."""

from __future__ import annotations

import hashlib
import pickle

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


class _Payload:
    def __reduce__(self):
        return (print, ("code ran",))


NOT_TORCH = "not a file torch.save writes: "
FOREIGN = {  # what a user may bring by mistake -> the clause that says what it is (issue 50)
    "random bytes": (lambda p: p.write_bytes(bytes(range(7, 256)) * 40),
                     NOT_TORCH + "neither a zip archive nor a pickle"),
    "a text file": (lambda p: p.write_text("efficientnet weights, see the wiki\n"), NOT_TORCH + "a text file"),
    "an empty file": (lambda p: p.write_bytes(b""), NOT_TORCH + "an empty file"),
    "another program's pickle": (lambda p: p.write_bytes(pickle.dumps({"a": 1}, protocol=4)),
                                 NOT_TORCH + "a Python pickle of another program"),
    "a truncated torch file": (lambda p: p.write_bytes(_saved(p)[:300]),
                               "a damaged PyTorch file: truncated or corrupted"),
    "a torch file holding objects": (lambda p: torch.save({"w": torch.zeros(1), "x": _Payload()}, p),
                                     "it holds Python objects besides tensors; refused unloaded, never run"),
}


def _saved(path) -> bytes:
    torch.save({"features.0.weight": torch.zeros(4, 4)}, path)
    return path.read_bytes()


@pytest.mark.parametrize("case", list(FOREIGN))
def test_anything_but_a_state_dict_is_refused_in_our_words(hub, tmp_path, cli, case, capfd):
    make, clause = FOREIGN[case]
    path = tmp_path / "efficientnet_b0_rwightman-7f5810bc.pth"
    make(path)
    code, out, err = cli("weights", "install", path)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert lines[0] == f"error: weights install: {path}: not a readable torch state dict ({clause})", lines[0]
    assert not any(t in out + err for t in ("weights_only", "IndexError", "KeyError", "Traceback", "likely succeed"))
    assert "code ran" not in capfd.readouterr().out  # the payload never ran
    assert not (pt.hub_checkpoints() / pt.IMAGENET_FILES["efficientnet_b0"]).exists()
