"""One seed, one dataset, on every host: the default dataset's poses are pinned, and no CPU dispatch moves them.

The pose fingerprint (dataset.json's ``pose_fingerprint``: SHA-256 of the patients' CSVs) of the default
config (experiments.yaml) is planned without rendering, and must equal the value committed here: a host, a
NumPy/OpenBLAS/glibc build or a code change that makes another dataset from the same config and seed fails.
The value changes only with ``GENERATOR_VERSION`` (a deliberate new dataset): update it in the same commit.

The heavy test re-plans it in fresh processes whose NumPy, OpenBLAS and glibc take other kernels than this
CPU's (the switches of docs/reproduction.md, "One seed, one dataset"): the bits must not move.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bronchocli.config import load_config
from bronchocli.generation.pipeline import GENERATOR_VERSION, planned_pose_fingerprint

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_POSE_FINGERPRINT = "29a6a538fb3e70dd1e7264e3722b32fd18f8f6d8a13786bd132480500c73e261"  # GENERATOR_VERSION 2

# Each emulates another host: OpenBLAS's kernels of older/other CPUs, NumPy without its AVX2/AVX-512 loops,
# glibc's libm without its FMA/AVX2 variants, one thread.
DISPATCH_VARIANTS = {
    "openblas-haswell": {"OPENBLAS_CORETYPE": "Haswell"},
    "openblas-prescott": {"OPENBLAS_CORETYPE": "Prescott"},
    "numpy-baseline-simd": {"NPY_DISABLE_CPU_FEATURES": "AVX512_ICL,X86_V4,X86_V3"},
    "glibc-no-fma": {"GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F"},
    "one-thread": {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"},
}
PLAN = ("import sys; from bronchocli.config import load_config; "
        "from bronchocli.generation.pipeline import planned_pose_fingerprint; "
        "print(planned_pose_fingerprint(load_config(sys.argv[1])))")


def test_the_default_datasets_poses_are_the_committed_ones():
    assert GENERATOR_VERSION == 2, "a new generator version makes a new dataset: update DEFAULT_POSE_FINGERPRINT"
    got = planned_pose_fingerprint(load_config(ROOT / "experiments.yaml"))
    assert got == DEFAULT_POSE_FINGERPRINT, (
        f"experiments.yaml's dataset plans other poses on this host ({got[:12]} != {DEFAULT_POSE_FINGERPRINT[:12]}): "
        "some pose-producing step is not host-independent (docs/reproduction.md, 'One seed, one dataset')")


@pytest.mark.heavy
@pytest.mark.parametrize("variant", sorted(DISPATCH_VARIANTS))
def test_no_cpu_dispatch_moves_the_poses(variant):
    env = {**os.environ, **DISPATCH_VARIANTS[variant]}
    out = subprocess.run([sys.executable, "-c", PLAN, str(ROOT / "experiments.yaml")], env=env, cwd=ROOT,
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == DEFAULT_POSE_FINGERPRINT


@pytest.mark.heavy
def test_frames_too_do_not_depend_on_the_cpu_dispatch(tmp_path):
    """A tiny rendered dataset, generated under every switch at once and without: the same frames, byte for byte."""
    args = ["--patients", "1", "--trajectories", "1", "--image-size", "32", "--workers", "1", "--no-progress",
            "--set", "dataset.generate.max_frames=4"]
    prints = []
    every_switch = {**{k: v for d in DISPATCH_VARIANTS.values() for k, v in d.items()}, "OPENBLAS_CORETYPE": "Prescott"}
    for name, extra in (("this-cpu", {}), ("every-switch", every_switch)):
        out = tmp_path / name
        subprocess.run([sys.executable, "-m", "bronchocli.cli", "data", "generate", *args, "--out", str(out)],
                       env={**os.environ, **extra}, cwd=ROOT, capture_output=True, text=True, check=True)
        meta = json.loads((out / "dataset.json").read_text())
        prints.append((meta["pose_fingerprint"], meta["fingerprint"]))
    assert prints[0] == prints[1]
