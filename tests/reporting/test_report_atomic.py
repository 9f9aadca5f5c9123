"""A report that fails half-way (a full disk) leaves its output folder as it was: all files or none (issue 22, 2)."""

from __future__ import annotations

import errno
import os
import signal

from bronchocli import io
from bronchocli.reporting import report


def test_a_report_failing_half_way_writes_nothing_and_says_so_in_one_line(cli, golden_store, tmp_path, monkeypatch):
    out = tmp_path / "r"
    out.mkdir()
    (out / "notes.txt").write_text("mine")  # what was there stays untouched
    real, written = io.write_bytes, []

    def fills_up(path, data):
        if len(written) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        written.append(path)
        return real(path, data)

    monkeypatch.setattr(report, "write_text", lambda path, text: fills_up(path, text.encode()))
    code, _, err = cli("report", "-c", str(golden_store.config), "--no-latency", "--out", str(out), "-q",
                       "--table", "personalized")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "No space left on device" in err, err
    assert len(written) == 3  # three files had been written when the disk filled up...
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # ...and none of them is left


def test_a_successful_report_moves_every_file_into_place(cli, golden_store, tmp_path):
    out = tmp_path / "r"
    code, out_text, err = cli("report", "-c", str(golden_store.config), "--no-latency", "--out", str(out), "-q",
                              "--table", "personalized")
    assert code == 0, err
    names = sorted(p.name for p in out.iterdir())
    assert names and all(not n.startswith(".") for n in names) and "table2-personalized-accumulated.md" in names
    assert f"wrote {len(names)} file(s)" in out_text


def test_a_staging_folder_left_by_a_killed_report_is_removed_by_the_next(tmp_path):
    """Issue 32, item 7: only this host's staging folders whose report process is gone go; nothing else does."""
    import os
    import socket
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()  # a pid that is gone
    host = socket.gethostname()
    out = tmp_path / "r"
    keep = [f".report-{os.getpid()}-0123abcd@{host}.tmp",  # a report running now (this process)
            f".report-{proc.pid}-0123abcd@another-host.tmp",  # another machine's: cannot tell, left alone
            ".report-notes", "figures"]  # a user's folders
    for name in [*keep, f".report-{proc.pid}-89abcdef@{host}.tmp"]:
        (out / name).mkdir(parents=True)
        (out / name / "table.md").write_text("x")
    with report.staged_outputs(out) as stage:
        assert stage.is_dir() and stage.name.endswith(f"@{host}.tmp")
    assert sorted(p.name for p in out.iterdir()) == sorted(keep)


def test_sigterm_half_way_is_what_ctrl_c_is_one_line_exit_143_nothing_written(cli, golden_store, tmp_path,
                                                                            monkeypatch):
    """SIGTERM (a `kill`, a shutdown) reaches `report` as Ctrl-C does: one line naming it, the shell's exit code
    143, the output folder as it was (issue 49)."""
    out = tmp_path / "r"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    real, written = io.write_bytes, []

    def killed_half_way(path, data):
        if len(written) == 3:
            os.kill(os.getpid(), signal.SIGTERM)  # a real signal to this process: its handler runs right here
        written.append(path)
        return real(path, data)

    monkeypatch.setattr(report, "write_text", lambda path, text: killed_half_way(path, text.encode()))
    code, _, err = cli("report", "-c", str(golden_store.config), "--no-latency", "--out", str(out), "-q",
                       "--table", "personalized")
    assert code == 143, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("interrupted by SIGTERM: ") and "run the same command" in err, err
    assert "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]  # nothing half-written taken as complete
