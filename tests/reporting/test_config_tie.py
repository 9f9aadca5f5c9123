"""Tables come from the runs of the config's cells only: a changed config and a re-sweep replace the old runs."""

from __future__ import annotations

import pytest
from report_fakes import errors_frame, fabricate_run, fast_sqlite, metrics_from_errors, new_store, trajectory_keys

CONFIG = """name: tie
runs: {{uri: "{uri}", experiment: tie-exp}}
dataset: {{root: data/none}}
grid: {{arch: [lstm, convlstm], rot_loss: [ce], population: [personalized], seed: [0]}}
train: {{steps: {steps}}}
"""


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """Config A (steps 100) swept, then config B (steps 200) swept in the same sweep name: {name: (path, ids)}."""
    import numpy as np

    from bronchocli.config import load_config

    root = tmp_path_factory.mktemp("tie")
    fast_sqlite(root)
    client, exp_id, uri = new_store(root, "tie-exp")
    rng = np.random.default_rng(0)
    out = {}
    for i, (name, steps, level) in enumerate((("A", 100, 9.0), ("B", 200, 2.0))):
        path = root / f"{name}.yaml"
        path.write_text(CONFIG.format(uri=uri, steps=steps))
        cfg = load_config(path)
        ids = {}
        for j, arch in enumerate(("lstm", "convlstm")):
            df = errors_frame(trajectory_keys(), (level + j, 10.0, 0.1, 0.01), rng)
            ids[arch] = fabricate_run(client, exp_id, arch=arch, rot_loss="ce", population="personalized",
                                      sweep="tie", cell_key=cfg.cell(arch=arch, rot_loss="ce",
                                                                     population="personalized").key,
                                      metrics=metrics_from_errors(df), errors=df,
                                      start_time=1_700_000_000_000 + 1000 * (2 * i + j))
        out[name] = (path, ids)
    return out


def _position(md: str) -> float:
    """The +LSTM row's position L2 mean."""
    row = next(line for line in md.splitlines() if line.startswith("| +LSTM | MSE+CE |"))
    return float(row.split(" | ")[2].strip("*").split()[0])


def _report(cli, path, out, *extra):
    code, stdout, stderr = cli("report", "-c", str(path), "-t", "personalized", "-e", "accumulated", "-f", "md",
                               "--no-figures", "--no-latency", "-q", "--out", str(out), *extra)
    assert code == 0, stderr
    return (out / "table2-personalized-accumulated.md").read_text(), stdout, " ".join(stderr.split())


def test_the_new_config_shows_only_its_own_runs(cli, swept, tmp_path):
    path_b, ids_b = swept["B"]
    _, ids_a = swept["A"]
    md, stdout, stderr = _report(cli, path_b, tmp_path / "b")
    for run_id in ids_b.values():
        assert run_id in md
    for run_id in ids_a.values():
        assert run_id not in md
    assert _position(md) == pytest.approx(2.0, rel=0.1)  # config B's level, not A's 9.0
    assert stderr.count("left out 2 run(s) of sweep 'tie'") == 1
    assert "2 run(s) of other configs left out" in " ".join(stdout.split())


def test_the_old_config_still_reports_its_own_runs(cli, swept, tmp_path):
    path_a, ids_a = swept["A"]
    md, _, _ = _report(cli, path_a, tmp_path / "a")
    assert all(run_id in md for run_id in ids_a.values()) and _position(md) == pytest.approx(9.0, rel=0.1)


def test_other_configs_on_request_and_a_stored_sweep_without_config(cli, swept, tmp_path):
    path_a, ids_a = swept["A"]
    _, ids_b = swept["B"]
    md, _, stderr = _report(cli, path_a, tmp_path / "both", "--include-other-configs")
    assert all(run_id in md for run_id in ids_b.values())  # B's runs are the latest of each cell
    assert "mixes configs: 2 cell(s)" in stderr
    md, _, stderr = _report(cli, path_a, tmp_path / "sweep", "--sweep", "tie")
    assert all(run_id in md for run_id in ids_b.values()) and "mixes configs" in stderr
    assert "every cell run of the sweep" in md
