"""Issue 37.8: a submission refused by the launcher's up-front checks writes no 0600 secrets file (the spec is
sealed only once the checks pass)."""

from __future__ import annotations

REFUSING_SBATCH = """#!/bin/sh
echo "sbatch: error: invalid partition specified: nope" >&2
exit 1
"""


def test_a_refused_submission_leaves_no_secrets_file(cli, make_config, tmp_path, monkeypatch):
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "sbatch").write_text(REFUSING_SBATCH)
    (bin_ / "sbatch").chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_}:{__import__('os').environ['PATH']}")
    cfg = make_config(slurm={"shared_filesystem": True})
    code, out, err = cli("sweep", "run", "-c", str(cfg.paths.base / "experiments.yaml"), "--launcher", "slurm",
                         "--detach", "--set", "storage.url=postgresql+psycopg://bp:S3cret@127.0.0.1:9/sweeps")
    assert code == 2 and len(err.strip().splitlines()) == 1 and "invalid partition" in err, out + err
    assert "S3cret" not in out + err
    assert [p for p in tmp_path.rglob("secrets-*") if p.is_file()] == []
