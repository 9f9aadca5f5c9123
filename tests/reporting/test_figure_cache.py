"""Figures are redrawn only when their inputs change (reporting/figure_cache.py), through the report's
staging and publishing."""

from __future__ import annotations

from bronchocli.reporting.figure_cache import RECORD, FigureCache
from bronchocli.reporting.report import publish, staged_outputs


def _report(out, key, calls, warning="figures: one warning"):
    """One report's figure phase: a group keyed by ``key`` drawing one file; returns the published files."""
    with staged_outputs(out) as stage:
        cache = FigureCache(out, stage)
        warnings: list[str] = []

        def draw():
            calls.append(key)
            warnings.append(warning)
            path = stage / "fig-a.png"
            path.write_bytes(key.encode())
            return [path]
        files = cache.once("runs", key, warnings, draw)
        cache.save()
        return publish(stage, out, files), warnings, cache.reused


def test_unchanged_inputs_reuse_the_published_figures_and_their_warnings(tmp_path):
    out, calls = tmp_path / "reports", []
    files, warnings, reused = _report(out, "runs-1", calls)
    assert calls == ["runs-1"] and files == [out / "fig-a.png"] and (out / RECORD).is_file() and not reused
    files, warnings, reused = _report(out, "runs-1", calls)
    assert calls == ["runs-1"], "drawn again although nothing changed"
    assert files == [out / "fig-a.png"] and warnings == ["figures: one warning"] and reused == ["runs"]
    files, _, _ = _report(out, "runs-2", calls)  # a new run: drawn again
    assert calls == ["runs-1", "runs-2"] and (out / "fig-a.png").read_bytes() == b"runs-2"


def test_a_missing_figure_is_drawn_again(tmp_path):
    out, calls = tmp_path / "reports", []
    _report(out, "k", calls)
    (out / "fig-a.png").unlink()
    _report(out, "k", calls)
    assert calls == ["k", "k"] and (out / "fig-a.png").is_file()
