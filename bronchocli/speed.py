"""Per-architecture speed settings per device: the precision and memory format a run uses when the config says
``auto``, chosen by a measurement, never by hand.

``bronchopose profile --speed FILE`` (``diagnostics/speed.py``) trains every architecture for a few dozen
steps in each candidate setting (fp32 / bf16 autocast, channels-last on / off), keeps the candidates that compute
the network's function as exactly as the default (one batch's gradients against float64's: :data:`GRAD_TOLERANCE`)
or whose loss curve tracks the fp32 reference's within :data:`LOSS_TOLERANCE`, and writes the fastest of those per
architecture into a settings file under the device's key (``cuda:<GPU name>``, or for a CPU its vector
instructions, ``cpu:AVX512+bf16``, ``cpu:AVX2``: ``cpu_key``). Which setting is fastest depends on them: on a
CPU with native bf16 OffsetNet trains 1.68x faster in bf16 autocast, while on an AVX2 CPU bf16 is emulated
and the kernels that win differ. The project ships the files measured on its own CPU machines
(``speed_settings.json`` beside this module); ``train.speed_settings`` points at another one. A device the file
does not name gets the old defaults (``DEFAULTS``); a bare ``cpu`` key (a file written before the keys named
the instructions) stands for any CPU.

What is fastest also depends on what a step computes. With a pretrained backbone frozen up to stage n and that
prefix computed once per dataset (``model.frozen_stages``, ``training/frozen_features.py``), a step trains only the
last stages on 3x3 maps and the architecture's head, and the whole network's measurement does not carry over (the
shipped file's ``frozen`` entries beside its whole-network ones show by how much). Such a
training is measured as its own entry, ``frozen["<backbone>, frozen <n>"]`` of the device
(``profile --speed FILE --backbone B --frozen-stages N``; ``frozen_key``), which a run that trains that way uses
first (``choose(..., frozen=...)``), falling back to the whole network's.

This module reads and writes the file only (no torch: the sweep orders its cells by the measured costs
without loading torch).
"""

from __future__ import annotations

import json
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .errors import BronchoError
from .io import write_json

SHIPPED = Path(__file__).with_name("speed_settings.json")
VERSION = 1
LOSS_TOLERANCE = 0.05  # mean relative gap between a candidate's and fp32's training loss per 10-step block
# A candidate computes the network's function exactly enough when one batch's gradients, from the weights every
# candidate starts from, lie within this relative L2 distance of the float64 computation's (or as close as the
# default's): fp32 in either memory format (another order of the sums). Such a candidate trains as the default does
# up to rounding, whatever its loss curve: a training curve amplifies a rounding difference chaotically (fp32
# contiguous drifted 6-9 % from fp32 channels-last in 50 steps, below and above it, with the same test results in
# real runs; benchmarks/README.md, "The main job"), so the curve cannot vouch for it, and the gradients can.
# Measured on the Zen 3 at 96² on the cached prefix (the shipped file's grad_error; docs/training.md): fp32
# 1.5e-6 - 2.1e-3 (channels-last the less exact for the 3-D-conv head); bf16 0.13-0.33 (tests/test_speed.py asserts
# > 5e-2).
GRAD_TOLERANCE = 1e-3
MIN_GAIN = 1.05  # a candidate replaces the default only when this much faster (below: noise on a shared machine)
# What a device without a measurement gets (the defaults before measured settings existed): fp32 on the CPU,
# bf16 autocast on a GPU that has it (else 16-mixed), channels-last everywhere.
DEFAULTS = {"cpu": ("32", True), "cuda": ("bf16-mixed", True), "mps": ("32", True)}


@dataclass(frozen=True)
class SpeedSetting:
    """What one run uses: precision, memory format, and where each came from (logged as run params)."""

    precision: str  # "32", "bf16-mixed" or "16-mixed"
    channels_last: bool
    source: str  # "config", "measured (<file>, <device key>, <date>)" or "default (...)"

    def params(self) -> dict[str, str]:
        return {"speed.precision": self.precision, "speed.channels_last": str(self.channels_last).lower(),
                "speed.source": self.source}


def load(path: Path | None = None) -> dict[str, Any]:
    """The settings file (``path``, else the shipped one); an unreadable or malformed file is one line, exit 2."""
    path = Path(path) if path is not None else SHIPPED
    if not path.is_file():
        if path == SHIPPED:
            return {"version": VERSION, "devices": {}}
        raise BronchoError(f"train.speed_settings {path}: no such file (write one with "
                           f"`bronchopose profile --speed {path}`)")
    try:
        data = json.loads(path.read_text())
        if not isinstance(data.get("devices"), dict):
            raise ValueError("no 'devices' mapping")
    except (OSError, ValueError, AttributeError) as exc:
        raise BronchoError(f"train.speed_settings {path}: not a speed settings file ({exc})") from None
    return data


def cpu_info() -> str:
    """The text of ``/proc/cpuinfo`` ("" where there is none)."""
    try:
        return Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""


def cpu_key(cpuinfo: str | None = None) -> str:
    """This CPU's key in a settings file: ``cpu:<vector instructions>``, ``+bf16`` where it has native bf16
    (``avx512_bf16`` or AMX on x86, ``bf16`` on Arm), from ``/proc/cpuinfo`` (``cpuinfo``: its text); else
    ``cpu:<machine>`` (no torch needed: the sweep's planner reads the measured rates with it)."""
    if cpuinfo is None:
        cpuinfo = cpu_info()
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        name, _, value = line.partition(":")
        if name.strip() in ("flags", "Features"):
            flags = set(value.split())
            break
    if "avx512f" in flags:
        isa = "AVX512"
    elif "avx2" in flags:
        isa = "AVX2"
    elif "asimd" in flags:
        isa = "NEON"
    else:
        isa = platform.machine() or "unknown"
    bf16 = bool(flags & {"avx512_bf16", "amx_bf16", "bf16"})
    return f"cpu:{isa}" + ("+bf16" if bf16 else "")


def entry_key(data: dict[str, Any], key: str) -> str | None:
    """The key of the measurements that apply to device ``key``: its own, or for a CPU a bare ``cpu`` entry (a
    file written before the keys named the instructions stands for any CPU); None when there are none."""
    if key in data["devices"]:
        return key
    return "cpu" if key.startswith("cpu:") and "cpu" in data["devices"] else None


def device_entry(data: dict[str, Any], key: str) -> dict[str, Any] | None:
    found = entry_key(data, key)
    return None if found is None else data["devices"][found]


def frozen_key(backbone: str, frozen_stages: int) -> str | None:
    """The name of a training on a cached frozen prefix in the settings (``<backbone>, frozen <n>``); None for
    none."""
    return f"{backbone}, frozen {frozen_stages}" if frozen_stages > 0 else None


def choose(arch: str, key: str, precision: str, channels_last: bool | str, *, path: Path | None = None,
           bf16_ok: bool = True, frozen: str | None = None) -> SpeedSetting:
    """The setting for ``arch`` on device ``key`` given the config's ``train.precision`` and
    ``model.channels_last`` (each ``auto`` or explicit: an explicit value always wins).

    ``bf16_ok`` is False where the device cannot run bf16 fast (a CPU without avx512_bf16/AMX): a measured
    bf16 setting then falls back to fp32. ``frozen``: the run trains on a cached frozen prefix (``frozen_key``):
    that training's measurement where the file has one, else the whole network's."""
    kind = key.split(":", 1)[0]
    default_prec, default_cl = DEFAULTS.get(kind, ("32", True))
    if kind == "cuda" and not bf16_ok:
        default_prec = "16-mixed"
    if precision != "auto" and channels_last != "auto":
        return SpeedSetting(precision, bool(channels_last), "config")
    data = load(path)
    entry = device_entry(data, key)
    scope = ((entry or {}).get("frozen") or {}).get(frozen) if frozen else None
    measured = (scope or {}).get("archs", {}).get(arch)
    if measured is None:
        scope, frozen = entry, None
        measured = (entry or {}).get("archs", {}).get(arch)
    if measured is not None:
        prec, cl = measured["precision"], bool(measured["channels_last"])
        if prec == "bf16-mixed" and not bf16_ok:
            prec = default_prec
        where = path.name if path is not None else "shipped"
        source = (f"measured ({where} settings, {entry_key(data, key)}{f', {frozen}' if frozen else ''}, "
                  f"{scope.get('measured', {}).get('date', '?')})")
    else:
        prec, cl = default_prec, default_cl
        source = f"default (no measurement of this architecture on {key})"  # the arch is a param already
    if precision != "auto":
        prec = precision
    if channels_last != "auto":
        cl = bool(channels_last)
    if precision != "auto" or channels_last != "auto":
        source += "; config overrides " + ("train.precision" if precision != "auto" else "model.channels_last")
    return SpeedSetting(prec, cl, source)


def training_rates(key: str, path: Path | None = None) -> dict[str, float]:
    """Measured training pairs/s of each architecture in its chosen setting on device ``key`` (may be empty)."""
    try:
        entry = device_entry(load(path), key)
    except BronchoError:
        return {}
    out = {}
    for arch, m in (entry or {}).get("archs", {}).items():
        rate = m.get("pairs_per_s", {}).get(m.get("chosen", ""))
        if rate:
            out[arch] = float(rate)
    return out


def write(path: Path, key: str, entry: dict[str, Any], frozen: str | None = None) -> None:
    """Put ``entry`` under device ``key`` of the settings file at ``path`` (other devices kept), atomically;
    ``frozen``: as that device's measurement of a training on a cached frozen prefix (``frozen_key``; the
    device's other measurements kept). A whole-network entry keeps the device's frozen-prefix ones."""
    path = Path(path)
    data: dict[str, Any] = {"version": VERSION, "devices": {}}
    if path.is_file():
        try:
            data = json.loads(path.read_text())
            data.setdefault("devices", {})
        except ValueError:
            raise BronchoError(f"--speed {path}: exists and is not a speed settings file; choose another path"
                               ) from None
    data["version"] = VERSION
    old = data["devices"].get(key) or {}
    if frozen:
        data["devices"][key] = {**old, "frozen": {**(old.get("frozen") or {}), frozen: entry}}
    else:
        data["devices"][key] = {**entry, **({"frozen": old["frozen"]} if old.get("frozen") else {})}
    write_json(path, data)
