"""`bronchopose weights ...`: backbone weights a user brings (``bronchocli.api.tools.install_weights``)."""

from __future__ import annotations

from pathlib import Path

import typer

from .common import console

app = typer.Typer(help="Install backbone weights for model.pretrained (the paper's ImageNet initialisation).",
                  no_args_is_help=True)


@app.command(name="install")
def install(
    files: list[Path] = typer.Argument(..., help="torchvision's efficientnet_b0_rwightman-7f5810bc.pth and/or "
                                       "resnet34-b627a593.pth, as downloaded on a machine with internet access."),
) -> None:
    """Install torchvision's ImageNet weights, brought as files, where `model.pretrained: imagenet` reads them.

    Each file must be torchvision's own (its sha256 starts with the digits in torchvision's file name) and hold
    the backbone's exact keys and shapes; it is copied atomically into PyTorch's hub cache
    ($TORCH_HOME/hub/checkpoints). Then `--profile paper` (imagenet) and `--profile gpu-bench`
    (imagenet-if-present) start from ImageNet weights, as the paper's authors did. A wrong file: one line, exit 2.
    """
    from ..api import tools  # lazy: torch loads only when the command runs

    for f in files:
        kind, dest = tools.install_weights(f)
        console.print(f"installed {kind} ImageNet weights: {dest}", highlight=False)
