"""A local weights server for tests: fabricated torchvision-format state dicts served on 127.0.0.1.

A fabricated state dict with torchvision's key names and shapes (tests/models/torchvision_keys.json) is served
under a name that carries the start of its own sha256, as torchvision's files do. The hub cache is a temporary
``TORCH_HOME``; ``BRONCHOPOSE_WEIGHTS_URL`` points the download at the server.
"""

from __future__ import annotations

import functools
import hashlib
import http.server
import io
import json
import threading
from pathlib import Path

import torch

from bronchocli.models import pretrained

KEYS = json.loads((Path(__file__).parent / "models" / "torchvision_keys.json").read_text())
CLASSIFIER = {"efficientnet_b0": {"classifier.1.weight": [1000, 1280], "classifier.1.bias": [1000]}, "resnet34": {}}
STEMS = {"efficientnet_b0": "efficientnet_b0_rwightman", "resnet34": "resnet34"}


def fabricate(kind: str, seed: int) -> dict[str, torch.Tensor]:
    """Random tensors under torchvision's key names and shapes (classifier included, as torchvision saves it)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, shape in {**KEYS[kind], **CLASSIFIER[kind]}.items():
        if k.endswith("num_batches_tracked"):
            out[k] = torch.tensor(7)
        elif k.endswith("running_var"):
            out[k] = torch.rand(shape, generator=g) + 0.5
        else:
            out[k] = torch.randn(shape, generator=g)
    return out


def serialised(state: dict[str, torch.Tensor]) -> bytes:
    buf = io.BytesIO()
    torch.save(state, buf)
    return buf.getvalue()


class Server:
    """A static file server on 127.0.0.1 (a thread) that counts the requests per file."""

    def __init__(self, root: Path):
        self.root, self.hits = root, []
        hits = self.hits

        class Handler(http.server.SimpleHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's naming
                hits.append(self.path.lstrip("/"))
                super().do_GET()

            def log_message(self, *args):  # keep the test output clean
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                                     functools.partial(Handler, directory=str(root)))
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/models/"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def serve_weights(tmp_path: Path, monkeypatch):
    """Both fabricated files on a local server, named <stem>-<sha256[:8]>.pth; an empty TORCH_HOME.

    Yields (server, states, names, hub checkpoints dir); the server stops afterwards."""
    (tmp_path / "www" / "models").mkdir(parents=True)
    states, names = {}, {}
    for seed, kind in enumerate(KEYS):
        states[kind] = fabricate(kind, seed)
        data = serialised(states[kind])
        names[kind] = f"{STEMS[kind]}-{hashlib.sha256(data).hexdigest()[:8]}.pth"
        (tmp_path / "www" / "models" / names[kind]).write_bytes(data)
    server = Server(tmp_path / "www")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch-home"))
    monkeypatch.setenv(pretrained.WEIGHTS_URL_ENV, server.url)
    monkeypatch.setattr(pretrained, "IMAGENET_FILES", names)
    yield server, states, names, tmp_path / "torch-home" / "hub" / "checkpoints"
    server.close()
