"""Two projects' finished cell runs compared metric by metric (the same plan run by two versions of the code).

    python benchmarks/compare_runs.py BEFORE/runs/mlflow.db AFTER/runs/mlflow.db

For every cell (arch, rotation loss, seed) finished in both MLflow SQLite stores it prints how many of the run's
evaluation metrics (``pair.*``, ``acc.*``, ``ratio.*``, ``val_best.*``, ``eval.mode_gap``) are identical to the bit
and which differ; exit 1 when one differs. Timed metrics are left out. Nothing is written.
"""

from __future__ import annotations

import sqlite3
import sys

KEPT = ("pair.", "acc.", "val_best.", "eval.mode_gap", "ratio.")


def cells(db: str) -> dict[tuple[str | None, ...], dict[str, float]]:
    c = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    out = {}
    for (rid,) in c.execute("select run_uuid from runs where status = 'FINISHED'"):
        tags = dict(c.execute("select key, value from tags where run_uuid = ?", (rid,)).fetchall())
        if tags.get("run_kind", "cell") != "cell" or "seed" not in tags:
            continue
        metrics = dict(c.execute("select key, value from latest_metrics where run_uuid = ?", (rid,)).fetchall())
        out[(tags.get("arch"), tags.get("rot_loss"), tags.get("seed"))] = {
            k: v for k, v in metrics.items() if k.startswith(KEPT)}
    return out


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.split("\n\n")[1].strip(), file=sys.stderr)
        return 2
    before, after = cells(argv[0]), cells(argv[1])
    bad = 0
    for key in sorted(set(before) & set(after)):
        a, b = before[key], after[key]
        differ = [(k, a[k], b[k]) for k in sorted(a) if k in b and a[k] != b[k]]
        print("/".join(map(str, key)), f"{sum(k in b for k in a) - len(differ)} metrics identical, "
              f"{len(differ)} differ", *differ[:5])
        bad += bool(differ)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
