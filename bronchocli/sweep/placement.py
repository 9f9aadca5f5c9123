"""Which GPU each local sweep worker uses, decided in the parent without importing torch.

The GPUs of this machine are those of an existing ``CUDA_VISIBLE_DEVICES``
(honoured as given: ids or UUIDs), else those ``nvidia-smi -L`` lists, else
none. Worker ``i`` is pinned to GPU ``i mod G`` by setting its own
``CUDA_VISIBLE_DEVICES`` before anything in it imports torch, so N workers
on G GPUs pack ``ceil(N / G)`` cells onto each GPU, and the run inside sees
one device, ``cuda:0``. ``nvidia-smi -L`` numbers GPUs in PCI bus order and
lists a MIG-enabled GPU's instances on indented ``MIG ...`` lines under it:
ids are the numbers of the ``GPU N:`` lines only, and a pinned worker gets
``CUDA_DEVICE_ORDER=PCI_BUS_ID`` so CUDA numbers the GPUs as nvidia-smi does.
The workers sharing one GPU are told how many they are
(``BRONCHOPOSE_GPU_SHARE``), so each keeps its frame cache within its share
of the GPU's memory (see ``data.batches.FrameSource``).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Sequence

from ..errors import BronchoError
from ..runs.contract import GPU_SHARE_ENV

ENV = "CUDA_VISIBLE_DEVICES"
SHARE_ENV = GPU_SHARE_ENV  # worker processes sharing this worker's GPU (itself included)
_SMI_GPU = re.compile(r"^GPU (\d+):")


def visible_gpus(env: dict[str, str] | None = None, smi: str | None = None) -> list[str]:
    """The GPU ids this process may use (strings, as CUDA_VISIBLE_DEVICES takes them)."""
    env = os.environ if env is None else env
    if ENV in env:
        return [g.strip() for g in env[ENV].split(",") if g.strip() and g.strip() != "-1"]
    if smi is None:
        exe = shutil.which("nvidia-smi")
        if exe is None:
            return []
        try:
            smi = subprocess.run([exe, "-L"], capture_output=True, text=True, timeout=10).stdout
        except (OSError, subprocess.SubprocessError):
            return []
    return smi_gpu_ids(smi)


def smi_gpu_ids(listing: str) -> list[str]:
    """The GPU indices of an ``nvidia-smi -L`` listing; its ``MIG ...`` instance lines are not GPUs."""
    return [m.group(1) for m in map(_SMI_GPU.match, listing.splitlines()) if m]


def parse_gpus(spec: str, available: Sequence[str]) -> list[str]:
    """``--gpus``: ``auto`` (every visible GPU), ``none``, or a comma list of ids among the visible ones."""
    if spec == "auto":
        return list(available)
    if spec == "none":
        return []
    chosen = [g.strip() for g in spec.split(",") if g.strip()]
    unknown = [g for g in chosen if g not in available]
    if unknown or not chosen:
        raise BronchoError(f"--gpus {spec!r}: {', '.join(unknown) or 'no GPU'} not among this machine's GPUs "
                           f"({', '.join(available) or 'none visible'}); use auto, none or a list such as 0,1")
    return chosen


def assign(workers: int, gpus: Sequence[str]) -> list[str | None]:
    """The GPU of each worker: round-robin, so K = ceil(workers / len(gpus)) cells share a GPU; None: CPU."""
    if not gpus:
        return [None] * workers
    return [gpus[i % len(gpus)] for i in range(workers)]


def share_counts(assignment: Sequence[str | None]) -> list[int]:
    """For each worker of :func:`assign`'s list, how many workers share its GPU (1 for CPU workers)."""
    return [assignment.count(g) if g is not None else 1 for g in assignment]


def pin_env(gpu: str, share: int = 1) -> dict[str, str]:
    """The environment that pins a worker process to ``gpu`` (set before torch is imported)."""
    return {ENV: gpu, "CUDA_DEVICE_ORDER": "PCI_BUS_ID", SHARE_ENV: str(max(1, share))}


def default_workers(gpus: Sequence[str], per_gpu: int) -> int:
    return max(1, len(gpus) * per_gpu)
