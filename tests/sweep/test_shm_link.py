"""`runs/` a symbolic link to a tmpfs under /dev/shm is the user's choice, not a system folder (issue 50): `sweep
run`, `sweep gc` and `status` work there; a link into /etc is still refused, naming the value as configured."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest
from sweep_fakes import FAKE, runs_by_cell
from tinydata import write_tiny_dataset


@pytest.fixture
def shm():
    if not Path("/dev/shm").is_dir():
        pytest.skip("no /dev/shm here")
    folder = Path(tempfile.mkdtemp(prefix="bronchopose-test-", dir="/dev/shm"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_runs_linked_into_dev_shm_runs_the_sweep_and_its_housekeeping(cli, make_config, fake_dir, tmp_path, shm):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    (tmp_path / "runs").symlink_to(shm, target_is_directory=True)  # runs/: a tmpfs under /dev/shm
    cfg = make_config(grid_order=True)
    path = str(tmp_path / "experiments.yaml")
    for args in (["sweep", "run", *FAKE], ["sweep", "gc"], ["status"]):
        code, out, err = cli(*args, "-c", path)
        assert code == 0, out + err
        assert "system folder" not in out + err and "Traceback" not in out + err
    assert runs_by_cell(cfg) == {c: 1 for c in runs_by_cell(cfg)} and len(runs_by_cell(cfg)) == 2
    assert any(shm.rglob("*.log"))  # the workers' logs went through the link into the tmpfs


def test_a_link_into_a_system_tree_is_refused_naming_what_was_configured(cli, make_config, tmp_path):
    make_config()
    (tmp_path / "runs").symlink_to("/etc", target_is_directory=True)
    code, _, err = cli("status", "-c", str(tmp_path / "experiments.yaml"))
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert lines[0].startswith("error: data.cache_dir runs/cache (that is /etc/cache): a system folder"), lines[0]
