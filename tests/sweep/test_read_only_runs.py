"""A read-only runs/ folder (issue 60, item 5): `status` and `sweep gc` say in one line that the sweep storage's
folder is not writable and what to do, instead of SQLite's "unable to open database file"."""

from __future__ import annotations

import subprocess

from mounts import tmpfs
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.sweep.storage import SweepStore


def test_status_and_gc_in_a_read_only_runs_folder_say_so_in_one_line(tmp_path, cli):
    with tmpfs(tmp_path / "runs", "64m") as disk:
        config = write_config(tmp_path, extra=f"storage: {{url: 'sqlite:///{disk}/sweep.db'}}\n")
        cfg = load_config(config)
        store = SweepStore(cfg.paths.storage_url)
        store.ensure_schema()
        store.add_cells(cfg.name, [cfg.cell(arch="baseline", rot_loss="mse", population="personalized")])
        store.close()
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        try:
            for command in (["status"], ["sweep", "gc"]):
                code, out, err = cli(*command, "-c", str(config))
                assert code == 2 and len(err.strip().splitlines()) == 1, (command, out, err)
                assert f"its folder {disk} is not writable (read-only file system)" in err, err
                assert "unable to open database file" not in err and "Traceback" not in out + err
        finally:
            subprocess.run(["mount", "-o", "remount,rw", str(disk)], check=True)
