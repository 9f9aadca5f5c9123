"""Sizes on disk: one folder walker and one byte formatter for every command that prints them."""

from __future__ import annotations

import os

import pytest

from bronchocli.io import fmt_bytes, folder_bytes


@pytest.mark.parametrize("n, text", [
    (None, "none"), (0, "0 B"), (999, "999 B"), (1000, "1.0 KB"), (1500, "1.5 KB"), (2_500_000, "2.5 MB"),
    (999_949, "999.9 KB"), (3_200_000_000, "3.2 GB"), (4.5e12, "4.5 TB"), (7.0e15, "7000.0 TB"),
])
def test_bytes_are_printed_in_decimal_units(n, text):
    assert fmt_bytes(n) == text


def test_folder_bytes_counts_files_below_not_links_and_filters_by_name(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "x.pt").write_bytes(b"1" * 1000)
    (tmp_path / "a" / "b" / ".x.pt.123-ab.tmp").write_bytes(b"2" * 300)
    os.symlink(tmp_path / "a" / "x.pt", tmp_path / "a" / "link.pt")  # counted as the link, not its target
    link = os.lstat(tmp_path / "a" / "link.pt").st_size
    assert folder_bytes(tmp_path) == 1300 + link
    assert folder_bytes(tmp_path, only=lambda name: name.endswith(".tmp")) == 300
    assert folder_bytes(tmp_path / "missing") == 0


def test_stale_temporary_files_are_only_those_atomic_writes_make(tmp_path):
    """Issue 32, item 1: a user's ``.notes.tmp`` is not a temporary file of an interrupted write."""
    from bronchocli.io import remove_stale_temps, temp_name

    ours = temp_name(tmp_path / "sub" / "a.csv")
    ours.parent.mkdir()
    ours.write_text("half")
    theirs = [tmp_path / ".notes.tmp", tmp_path / "sub" / ".draft.1-xyz.tmp", tmp_path / "keep.tmp"]
    for p in theirs:
        p.write_text("mine")
    assert remove_stale_temps(tmp_path) == 1 and not ours.exists() and all(p.exists() for p in theirs)
