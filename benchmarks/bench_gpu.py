"""GPU engine benchmark: bare step vs engine per architecture and size, SM utilisation, memory, start-up, packing.

    python benchmarks/bench_gpu.py [--archs ...] [--sizes 128 256] [--batch 80] [--steps 300] [--pack 1 2 4]
    python benchmarks/bench_gpu.py --device cpu --sizes 64 --steps 6 --seconds 2 --pack 1   # smoke run on a CPU
                                                      # (in --precision too: bf16 autocast by default)

For every (architecture, size), bf16 on CUDA (``--precision``):

* bare step pairs/s and images/s (2 images per pair; engine_bench.py says what is timed);
* engine pairs/s (``Trainer.fit``: training steps only, and with validation included), engine / bare;
* mean SM utilisation during the engine run (``nvidia-smi`` sampled every 100 ms) and peak memory;
* achieved TFLOP/s = pairs/s x GMAC per pair x 6 (forward and backward), as a fraction of the GPU's measured
  bf16 matmul peak (an 8192^3 matmul);
* ``--pack``: aggregate engine pairs/s of K identical cells running at once on one GPU (K processes);
* start-up: a fresh ``bronchopose train`` process until its first optimiser step (the run's
  ``train.process_first_step_s``), on a tiny CSV-format dataset written here.

Prints Markdown tables (copy them into benchmarks/README.md with the GPU model, driver and torch version).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import statistics
import subprocess
import sys
import tempfile
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import torch
from engine_bench import bare_step_rate, engine_rate
from PIL import Image

from bronchocli.models.profile import count_macs, random_frames
from bronchocli.registry import arch_names

HERE = Path(__file__).resolve().parent


def smi_id(device: torch.device) -> str:
    """How ``nvidia-smi -i`` names torch's ``device``: its UUID, else its PCI bus id.

    torch's index counts the devices of ``CUDA_VISIBLE_DEVICES`` (``cuda:0`` may be physical GPU 3) and may
    follow another order than nvidia-smi's, so neither index can be handed to nvidia-smi.
    """
    props = torch.cuda.get_device_properties(device)
    uuid = str(getattr(props, "uuid", "") or "")
    if uuid:
        return uuid if uuid.startswith(("GPU-", "MIG-")) else f"GPU-{uuid}"
    return f"{props.pci_domain_id:08x}:{props.pci_bus_id:02x}:{props.pci_device_id:02x}.0"


class SmSampler(threading.Thread):
    """Samples ``nvidia-smi`` GPU utilisation of one GPU (``smi_id``) every 100 ms while running."""

    def __init__(self, gpu: str) -> None:
        super().__init__(daemon=True)
        self.gpu, self.values, self._halt = gpu, [], threading.Event()

    def command(self) -> list[str]:
        return ["nvidia-smi", "-i", self.gpu, "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits",
                "-lms", "100"]

    def run(self) -> None:
        try:
            proc = subprocess.Popen(self.command(), stdout=subprocess.PIPE, text=True)
        except OSError:
            return
        while not self._halt.is_set():
            line = proc.stdout.readline()
            if not line:
                break
            try:
                self.values.append(float(line.strip()))
            except ValueError:
                pass
        proc.terminate()

    def stop(self) -> float:
        self._halt.set()
        self.join(timeout=2)
        return statistics.mean(self.values) if self.values else float("nan")


def matmul_peak_tflops(device: torch.device, n: int = 8192, repeats: int = 20) -> float:
    a = torch.randn(n, n, device=device, dtype=torch.bfloat16)
    b = torch.randn(n, n, device=device, dtype=torch.bfloat16)
    for _ in range(3):
        a @ b
    torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        a @ b
    torch.cuda.synchronize(device)
    return 2 * n ** 3 * repeats / (time.perf_counter() - t0) / 1e12


def gmac_per_pair(arch: str, size: int) -> float:
    from bronchocli.models import build_model

    model = build_model(arch, image_size=size).eval()
    return count_macs(model, random_frames(1, 10, size, torch.device("cpu"))) / 10 / 1e9


def _packed(args: tuple) -> float:
    arch, size, batch, precision, steps = args
    return engine_rate(arch, size, batch, torch.device("cuda"), precision, steps).pairs_per_s


def packed_rate(arch: str, size: int, batch: int, precision: str, steps: int, k: int) -> float:
    with mp.get_context("spawn").Pool(k) as pool:
        return sum(pool.map(_packed, [(arch, size, batch, precision, steps)] * k))


CSV_CONFIG = """\
    name: bench-startup
    dataset:
      root: data
      format: csv
      csv: {columns: {patient: patient, lobe: lobe, trajectory: trajectory, frame: frame, filename: filename}}
    splits: {train: 1, val: 1, test: 1}
    data: {window: 3}
    train: {batch_size: 6, steps: 2, val_every: 2, bn_recalibrate: 1}
    runs: {model_artifact: none}
"""


def write_csv_dataset(root: Path, size: int) -> None:
    rng = np.random.default_rng(0)
    rows = []
    for patient in ("p00", "p01"):
        for lobe in ("ur", "bl"):
            for traj in range(3):
                for frame in range(12):
                    name = f"{patient}/{lobe}/t{traj}_f{frame:02d}.png"
                    path = root / name
                    path.parent.mkdir(parents=True, exist_ok=True)
                    Image.fromarray(rng.integers(0, 256, (size, size, 3), dtype=np.uint8)).save(path)
                    rows.append(f"{patient},{lobe},{traj},{frame},{frame * 2.0},{traj},{0.1 * frame},"
                                f"{frame},{0},{0},{name}")
    header = "patient,lobe,trajectory,frame,x,y,z,rx,ry,rz,filename"
    (root / "poses.csv").write_text(header + "\n" + "\n".join(rows) + "\n")


def startup_seconds(device: str) -> tuple[float, float]:
    """(import of the training engine, a fresh `bronchopose train` process until its first step), seconds."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import bronchocli.training.run"], check=True)
    imports = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_csv_dataset(root / "data", 64)
        (root / "experiments.yaml").write_text(textwrap.dedent(CSV_CONFIG))
        cmd = [sys.executable, "-m", "bronchocli.cli", "train", "-a", "baseline", "-l", "mse", "-P", "personalized",
               "-q", "--set", f"train.device={device}"]
        code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
        subprocess.run([sys.executable, "-c", code, *cmd[3:]], cwd=root, check=True, capture_output=True)
        sys.path.insert(0, str(HERE.parent))
        from bronchocli.config import load_config
        from bronchocli.runs.client import client_for, experiment_id
        from bronchocli.runs.records import search_runs

        cfg = load_config(root / "experiments.yaml")
        client = client_for(cfg)
        (run,) = search_runs(client, [experiment_id(client, cfg)])
        return imports, run.data.metrics.get("train.process_first_step_s", float("nan"))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--archs", nargs="+", default=list(arch_names()))
    ap.add_argument("--sizes", nargs="+", type=int, default=[128, 256])
    ap.add_argument("--batch", type=int, default=80, help="image pairs per step (temporal: 8 windows of 10)")
    ap.add_argument("--steps", type=int, default=300, help="engine optimiser steps per measurement")
    ap.add_argument("--seconds", type=float, default=10.0, help="bare-step timing per measurement")
    ap.add_argument("--precision", default="bf16-mixed", choices=["32", "bf16-mixed", "16-mixed"],
                    help="on every device: the CPU smoke run exercises autocast too")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--pack", nargs="+", type=int, default=[1, 2, 4], help="cells per GPU for the packing table")
    ap.add_argument("--compile", action="store_true", help="also time torch.compile (and its compile time)")
    return ap.parse_args(argv)


def run_settings(args: argparse.Namespace) -> tuple[torch.device, str]:
    """The device and the precision every measurement uses: ``--precision`` as asked, on the CPU too."""
    return torch.device(args.device), args.precision


def main() -> None:
    args = parse_args()
    device, precision = run_settings(args)
    cuda = device.type == "cuda"
    name = torch.cuda.get_device_name(device) if cuda else platform.processor() or platform.machine()
    driver = subprocess.run(["nvidia-smi", "-i", smi_id(device), "--query-gpu=driver_version", "--format=csv,noheader"],
                            capture_output=True, text=True).stdout.strip() if cuda else "-"
    peak = matmul_peak_tflops(device) if cuda else float("nan")
    print(f"device: {name}; driver {driver}; torch {torch.__version__} (CUDA {torch.version.cuda}); "
          f"precision {precision}; bf16 matmul peak {peak:.0f} TFLOP/s\n")
    print("| arch | size | bare pairs/s | bare img/s | engine pairs/s (train) | engine incl. val | engine/bare "
          "| SM util % | peak MB | frames on GPU | TFLOP/s | of peak |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        for arch in args.archs:
            bare = bare_step_rate(arch, size, args.batch, device, precision, args.seconds)
            sampler = SmSampler(smi_id(device)) if cuda else None
            if sampler:
                sampler.start()
            eng = engine_rate(arch, size, args.batch, device, precision, args.steps)
            util = sampler.stop() if sampler else float("nan")
            overall = eng.pairs_per_s * eng.train_s / (eng.train_s + eng.val_s)
            tflops = eng.pairs_per_s * gmac_per_pair(arch, size) * 6 / 1e3
            print(f"| {arch} | {size} | {bare:.0f} | {2 * bare:.0f} | {eng.pairs_per_s:.0f} | {overall:.0f} | "
                  f"{eng.pairs_per_s / bare:.2f} | {util:.0f} | {eng.peak_mb:.0f} | {eng.resident} | "
                  f"{tflops:.1f} | {tflops / peak:.1%} |", flush=True)
            if args.compile:
                t0 = time.perf_counter()
                compiled = bare_step_rate(arch, size, args.batch, device, precision, args.seconds, compile=True)
                print(f"|   torch.compile | {size} | {compiled:.0f} | | | | | | | | | "
                      f"(incl. compile: {time.perf_counter() - t0:.0f} s) |", flush=True)
    if cuda and args.pack:
        print("\n| arch | size | cells on one GPU | aggregate engine pairs/s |")
        print("|---|---|---|---|")
        for size in args.sizes[:1]:
            for arch in ("baseline", "convlstm", "offsetnet"):
                for k in args.pack:
                    rate = packed_rate(arch, size, args.batch, precision, args.steps, k)
                    print(f"| {arch} | {size} | {k} | {rate:.0f} |", flush=True)
    imports, first = startup_seconds(args.device)
    print(f"\nstart-up: `import bronchocli.training.run` {imports:.1f} s; a fresh `bronchopose train` process to "
          f"its first optimiser step {first:.1f} s")
    print(json.dumps({"device": name, "driver": driver, "torch": torch.__version__, "peak_tflops": peak}))


if __name__ == "__main__":
    main()
