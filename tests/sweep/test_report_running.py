"""`report` while cells of the sweep still run (issue 37.8): refused in one line naming them, before any work and
with nothing written (their rows would be rows of —); a claim whose worker is gone (no heartbeat within
sweep.stale_after_s) refuses nothing."""

from __future__ import annotations

from sqlalchemy import update

from bronchocli.reporting.entry import refuse_while_running
from bronchocli.sweep import SweepStore, prepare
from bronchocli.sweep.storage import cells_table


def test_report_refuses_while_a_live_worker_runs_a_cell_and_not_after_it_is_gone(cli, make_config, tmp_path):
    cfg = make_config(archs=("baseline", "lstm"), sweep={"heartbeat_s": 10.0, "stale_after_s": 3600.0})
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    refuse_while_running(cfg, cfg.name)  # nothing runs: nothing refused
    claim = store.claim(cfg.name, [plan.cells[1].key], "node7:42", max_retries=1, stale_after_s=60)
    out = tmp_path / "reports"
    code, stdout, err = cli("report", "-c", str(cfg.paths.base / "experiments.yaml"), "--table", "personalized",
                            "-q", "--out", str(out))
    assert code == 2 and len(err.strip().splitlines()) == 1, stdout + err
    assert "1 cell(s) still running" in err and plan.cells[1].label in err and "Traceback" not in stdout + err
    assert not out.exists() or not any(out.iterdir())

    with store.engine.begin() as conn:  # its worker died: no heartbeat for longer than sweep.stale_after_s
        conn.execute(update(cells_table).where(cells_table.c.token == claim.token)
                     .values(heartbeat=cells_table.c.heartbeat - 10 * cfg.sweep.stale_after_s))
    refuse_while_running(cfg, cfg.name)
    assert store.running(cfg.name, cfg.sweep.stale_after_s) == []
