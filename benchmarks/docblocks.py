"""The documents' measured numbers, from the results files that recorded them (one source).

Every measured figure that README.md, CONTRIBUTING.md, docs/ or benchmarks/README.md quotes lives in a results
file: ``benchmarks/results/<name>.json`` (``machine``, ``date``, ``command``, ``figures``; optionally
``summary``, a row of benchmarks/README.md's Summary table) or ``bronchocli/speed_settings.json`` (written by
``bronchopose profile --speed``, read as ``speed_settings``). A document quotes a figure through a generated
span, so the prose cannot drift from the measurement:

- inline: ``<!-- n: FILE/key/path as FORMAT -->VALUE<!-- /n -->`` — VALUE is the figure at ``key/path`` of
  FILE's JSON (``figures/...`` for a results file), formatted by FORMAT (optional; see ``fmt``);
- a block: ``<!-- numbers: NAME -->`` ... ``<!-- /numbers -->`` — the lines ``BLOCKS[NAME]`` renders from the
  results files (the Summary table of benchmarks/README.md; docs/reports.md's calibration tables);
  ``<!-- numbers: lines FILE/key/path -->`` renders the list of lines recorded at that key (a report's table,
  kept verbatim by the benchmark that recorded it, e.g. bench_study.py).

``python benchmarks/docblocks.py`` checks every document and exits 1 naming each span that differs from its
results file; ``--write`` rewrites the spans from the files (atomically). tests/test_doc_numbers.py runs the
check, so a figure changed in the prose, or a results file re-measured without regenerating the prose, fails.
A benchmark records a new measurement with ``record(...)`` (bench_calibration.py ``--record`` does).

What experiments.yaml states (a profile's size, budget, objective, seeds) is quoted the same way from the entry
``config`` (benchmarks/docconfig.py: ``<!-- n: config/PLAN/KEY -->``, the block ``profiles``), and the check also
names a number typed beside a profile's name in README.md, CONTRIBUTING.md or docs/ that the config contradicts.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import sys
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(1, str(Path(__file__).resolve().parents[1]))
import docconfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SPEED_SETTINGS = ROOT / "bronchocli" / "speed_settings.json"
CONFIG = ROOT / "experiments.yaml"
# the log of measurements, each in its dated section: what a plan was then, so its typed numbers are not checked
# against today's config (its figures are spans like everywhere else)
LOG = Path("benchmarks") / "README.md"
REQUIRED = ("title", "machine", "date", "command", "figures")
# A figure's name means one thing in every results file: where its parts are recorded beside it, it is their sum
# (install_s is torch and the project installed, never the clone or the venv; total_s the whole command)
SUMS = {"install_s": ("torch_s", "project_s"),
        "total_s": ("clone_venv_s", "torch_s", "project_s", "sweep_s", "report_s")}

# "as", not "|", before the format: a pipe would split a Markdown table's cell even inside a comment
INLINE = re.compile(r"<!-- n: (?P<ref>[^>]+?)(?: as (?P<fmt>[^>]*?))?\s*-->(?P<text>.*?)<!-- /n -->", re.S)
BLOCK = re.compile(r"(?P<open><!-- numbers: (?P<name>[\w-]+)(?: (?P<ref>[^\s>]+))? -->\n)(?P<body>.*?)"
                   r"(?P<close><!-- /numbers -->)", re.S)


class NumbersError(ValueError):
    """A results file or a span that cannot be read: one line naming the file, key and value."""


def documents(root: Path = ROOT) -> list[Path]:
    """The files whose spans are checked."""
    paths = [root / "README.md", root / "CONTRIBUTING.md", root / "benchmarks" / "README.md",
             root / "experiments.yaml", *sorted((root / "docs").glob("*.md"))]
    return [p for p in paths if p.exists()]


def load_results(results_dir: Path = RESULTS, speed_settings: Path = SPEED_SETTINGS,
                 config: Path | None = None) -> dict[str, dict]:
    """Every results file by name (its file stem), validated; ``speed_settings`` as it is shipped; ``config``:
    every plan of experiments.yaml (``CONFIG`` unless given), docconfig.facts."""
    out: dict[str, dict] = {}
    for path in sorted(results_dir.glob("*.json")):
        if path.stem in ("speed_settings", "config"):
            raise NumbersError(f"{path}: {path.stem!r} is a reserved name (pick another file name)")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise NumbersError(f"{path}: not JSON ({exc})") from None
        missing = [k for k in REQUIRED if not data.get(k)]
        if missing:
            raise NumbersError(f"{path}: missing {', '.join(missing)} (a results file needs {', '.join(REQUIRED)})")
        try:
            dt.date.fromisoformat(str(data["date"]))
        except ValueError:
            raise NumbersError(f"{path}: date {data['date']!r} is not YYYY-MM-DD") from None
        for problem in inconsistent(data["figures"]):
            raise NumbersError(f"{path}: {problem}")
        out[path.stem] = data
    if speed_settings.exists():
        out["speed_settings"] = json.loads(speed_settings.read_text(encoding="utf-8"))
    out["config"] = docconfig.facts(config or CONFIG)
    return out


def inconsistent(node, at: str = "figures") -> list[str]:
    """Every place in ``node`` where a figure of ``SUMS`` is recorded beside all its parts and is not their sum."""
    out = []
    if isinstance(node, dict):
        for name, parts in SUMS.items():
            if isinstance(node.get(name), (int, float)) and all(isinstance(node.get(p), (int, float)) for p in parts):
                total = sum(node[p] for p in parts)
                if abs(node[name] - total) > 0.15:
                    out.append(f"{at}/{name} is {node[name]}, not {' + '.join(parts)} = {total:g} "
                               f"({name} means that sum in every results file)")
        for key, value in node.items():
            out += inconsistent(value, f"{at}/{key}")
    return out


def lookup(results: dict[str, dict], ref: str):
    """The value at ``FILE/key/path``; ``A ÷ B``: the value at A divided by the one at B (lists of equal length
    element by element: a ratio per seed)."""
    if "÷" in ref:
        a, b = (lookup(results, part) for part in ref.split("÷", 1))
        if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            return [x / y for x, y in zip(a, b)]
        if isinstance(a, (int, float)) and isinstance(b, (int, float)):
            return a / b
        raise NumbersError(f"{ref!r}: can divide two numbers or two lists of one length, not {a!r} and {b!r}")
    name, *keys = ref.strip().split("/")
    if name not in results:
        raise NumbersError(f"unknown results file {name!r} in {ref!r} (known: {', '.join(sorted(results))})")
    node = results[name]
    for i, key in enumerate(keys):
        if isinstance(node, list) and key.isdigit() and int(key) < len(node):
            node = node[int(key)]
        elif isinstance(node, dict) and key in node:
            node = node[key]
        else:
            raise NumbersError(f"{ref!r}: no key {'/'.join(keys[:i + 1])!r} in {name}")
    return node


def duration(seconds: float) -> str:
    """Seconds as the prose shows them, rounded (never floored) to the unit shown: 1939 -> '32 min 19 s';
    6776.4 -> '1 h 53 min'; under a minute: '28.6 s'."""
    if seconds < 60:
        return f"{seconds:g} s"
    if seconds >= 3600 - 30:  # shown in minutes: 3,599 s is '1 h 0 min', not '59 min 59 s' floored to the hour
        h, m = divmod(int(round(seconds / 60)), 60)
        return f"{h} h {m} min"
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s} s"


def fmt(value, spec: str | None) -> str:
    """A figure as the prose shows it. ``spec``: none (the value as recorded), a format spec (``.3f``),
    ``dur`` (seconds as 'M min S s'), ``range SPEC`` (a list as 'min–max'), ``join SPEC`` (a list as 'a / b')."""
    spec = (spec or "").strip()
    one = (lambda v, s: "—" if v is None else format(v, s) if s else str(v))  # None: not reached, not measured
    if spec == "dur":
        return duration(float(value))
    if spec.split(" ")[0] in ("range", "join"):
        word, _, inner = spec.partition(" ")
        if not isinstance(value, list) or not value:
            raise NumbersError(f"format {spec!r} needs a list, got {value!r}")
        if word == "range":  # ends that print alike are printed once ("251", not "251–251")
            lo, hi = one(min(value), inner), one(max(value), inner)
            return lo if lo == hi else f"{lo}–{hi}"
        return " / ".join(one(v, inner) for v in value)
    if isinstance(value, (dict, list)):
        raise NumbersError(f"a {type(value).__name__} needs a format (range, join), got {spec!r}")
    return one(value, spec)


def summary_table(results: dict[str, dict]) -> list[str]:
    """benchmarks/README.md's Summary: per figure, the rows of its latest measurement (several machines measured
    that day: a row each), its goal once; and one row per device of the shipped speed settings. A summary's
    ``of`` names the figure when results files of several dates measure the same one (their ``figure`` texts may
    differ); without it the ``figure`` text is the figure. Earlier measurements stay in the sections below."""
    rows = []
    for name, d in results.items():
        if name == "config":
            continue
        if name == "speed_settings":
            rows += [("speed_settings " + r[3], *r) for r in speed_rows(d)]
            continue
        got = d.get("summary")
        for s in ([got] if isinstance(got, dict) else got or []):
            rows.append((s.get("of", s["figure"]), d["date"], s.get("order", 0), name, d.get("cpu", d["machine"]),
                         s["figure"], s.get("command", d["command"]), s["result"], s.get("goal", "—"),
                         f"[{name}](results/{name}.json)"))
    latest: dict[str, str] = {}
    for r in rows:
        latest[r[0]] = max(latest.get(r[0], r[1]), r[1])
    lines = ["| date | machine | figure | command | result | goal / limit | source |",
             "|---|---|---|---|---|---|---|"]
    shown: set[str] = set()
    for of, date, _, _, cpu, figure, command, result, goal, src in sorted(
            (r for r in rows if r[1] == latest[r[0]]), key=lambda r: (r[1], r[2], r[3])):
        lines.append(f"| {date} | {cpu} | {figure} | `{command}` | {result} | {'″' if of in shown else goal} | {src} |")
        shown.add(of)
    return lines


def speed_rows(settings: dict) -> list[tuple]:
    """The per-architecture speed settings of each device in bronchocli/speed_settings.json, as Summary rows."""
    rows = []
    for key, entry in settings.get("devices", {}).items():
        m = entry.get("measured", {})
        archs = entry.get("archs", {})
        kept = sorted(a for a, x in archs.items() if x["chosen"] == x["default"])
        changed = "; ".join(f"{a} **{x['chosen']} {x['ratio']:.2f}×**" for a, x in archs.items()
                            if x["chosen"] != x["default"])
        rates = " / ".join(f"{x['pairs_per_s'][x['chosen']]:g}" for x in archs.values())
        rows.append((m.get("date", "?"), 0, "speed_settings", f"`{key}`: {m.get('device', '?')}",
                     f"per-architecture speed settings ({', '.join(archs)}), {m.get('image_size')}², "
                     f"{m.get('pairs_per_step')} pairs/step",
                     f"bronchopose profile --speed bronchocli/speed_settings.json --device cpu --image-size "
                     f"{m.get('image_size')} --batch {m.get('pairs_per_step')} --threads {m.get('threads')} -a all",
                     f"{changed or 'every default kept'}; {', '.join(kept)} keep {archs[kept[0]]['default'] if kept else '—'}"
                     f" (pairs/s in the chosen setting: {rates})",
                     f"loss within {m.get('loss_tolerance', 0.05):.0%} of fp32 ✔",
                     "[speed_settings.json](../bronchocli/speed_settings.json)"))
    return rows


def calibration_block(results: dict[str, dict]) -> list[str]:
    """docs/reports.md's calibration tables, as bench_calibration.py recorded them."""
    return list(lookup(results, "calibration/figures/docs_table"))


def learning_cost_block(results: dict[str, dict]) -> list[str]:
    """benchmarks/README.md's "Cost of learning" table of runs, as bench_learning_cost.py recorded it."""
    return list(lookup(results, "learning-cost/figures/docs_table"))


BLOCKS: dict[str, Callable[[dict[str, dict]], list[str]]] = {
    "summary": summary_table,
    "calibration": calibration_block,
    "learning-cost": learning_cost_block,
    "profiles": lambda results: docconfig.profiles_block(results["config"]),
}


def render(text: str, results: dict[str, dict], where: str = "") -> str:
    """``text`` with every span regenerated from the results files."""
    def block(m: re.Match) -> str:
        name = m["name"]
        if name == "lines" and m["ref"]:
            try:
                lines = lookup(results, m["ref"])
            except NumbersError as exc:
                raise NumbersError(f"{where}: {exc}") from None
            if not isinstance(lines, list):
                raise NumbersError(f"{where}: block lines {m['ref']}: not a list of lines")
            return m["open"] + "\n".join(map(str, lines)) + "\n" + m["close"]
        if name not in BLOCKS:
            raise NumbersError(f"{where}: unknown block {name!r} (known: {', '.join(BLOCKS)})")
        return m["open"] + "\n".join(BLOCKS[name](results)) + "\n" + m["close"]

    def inline(m: re.Match) -> str:
        try:
            value = fmt(lookup(results, m["ref"]), m["fmt"])
        except NumbersError as exc:
            raise NumbersError(f"{where}: {exc}") from None
        return m.group(0)[: m.start("text") - m.start()] + value + "<!-- /n -->"

    return INLINE.sub(inline, BLOCK.sub(block, text))


def spans(text: str) -> Iterable[tuple[str, str]]:
    """(what, text) of every span in order: blocks by name, inline figures by reference."""
    for m in BLOCK.finditer(text):
        yield f"block {m['name']}", m["body"]
    for m in INLINE.finditer(text):
        yield f"{m['ref'].strip()}", m["text"]


def check(paths: Iterable[Path], results: dict[str, dict], root: Path = ROOT) -> list[str]:
    """One line per span whose text differs from what its results file gives, and per number typed beside a
    profile's name that experiments.yaml contradicts (empty: every document agrees)."""
    paths = list(paths)
    described = [p for p in paths if p != root / LOG]
    diffs: list[str] = docconfig.typed(described, results["config"], root) if "config" in results else []
    for path in paths:
        rel = path.relative_to(root) if path.is_relative_to(root) else path
        text = path.read_text(encoding="utf-8")
        try:
            want = render(text, results, str(rel))
        except NumbersError as exc:
            diffs.append(str(exc))
            continue
        for (what, got), (_, expected) in zip(spans(text), spans(want)):
            if got != expected:
                line = text.count("\n", 0, text.find(got)) + 1 if got else 0
                diffs.append(f"{rel}:{line}: {what}: the document says {short(got)!r}, "
                             f"the results file gives {short(expected)!r}")
    return diffs


def short(s: str, n: int = 160) -> str:
    return s if len(s) <= n else s[:n] + " …"


def write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write(paths: Iterable[Path], results: dict[str, dict], root: Path = ROOT) -> list[Path]:
    """Regenerate every span of ``paths``; the files that changed."""
    changed = []
    for path in paths:
        rel = path.relative_to(root) if path.is_relative_to(root) else path
        text = path.read_text(encoding="utf-8")
        new = render(text, results, str(rel))
        if new != text:
            write_atomic(path, new)
            changed.append(path)
    return changed


def machine() -> str:
    """This machine in a results file's words: CPU model, cores, its vector instructions, torch."""
    model, flags = "unknown CPU", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model == "unknown CPU":
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    vec = next((f for f in ("avx512_bf16", "avx512f", "avx2") if f in flags), "no avx2")
    return f"{model}, {os.cpu_count()} cores, {vec}, Python {sys.version.split()[0]}"


def record(name: str, *, title: str, machine: str, command: str, figures: dict, date: str | None = None,
           results_dir: Path = RESULTS, **extra) -> Path:
    """Write ``results/<name>.json`` (atomically): what a benchmark calls after measuring."""
    data = {"title": title, "machine": machine, "date": date or dt.date.today().isoformat(), "command": command,
            **extra, "figures": figures}
    path = results_dir / f"{name}.json"
    write_atomic(path, json.dumps(data, indent=2, ensure_ascii=False) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="rewrite every span from the results files")
    args = ap.parse_args(argv)
    try:
        results = load_results(RESULTS, SPEED_SETTINGS)
        if args.write:
            for path in write(documents(ROOT), results, ROOT):
                print(f"rewrote {path.relative_to(ROOT)}")
            return 0
        diffs = check(documents(ROOT), results, ROOT)
    except NumbersError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for line in diffs:
        print(line)
    print("every document agrees with its results files" if not diffs else
          f"{len(diffs)} span(s) differ: re-measure, or run `python benchmarks/docblocks.py --write`")
    return 1 if diffs else 0


if __name__ == "__main__":
    raise SystemExit(main())
