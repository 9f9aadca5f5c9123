"""The CLI: the explicit command list, --version, and clean exit-2 errors without tracebacks."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from bronchocli import __version__, cli


def run_console_script(*args: str, cwd=None) -> subprocess.CompletedProcess:
    """Run `bronchopose` exactly as a user would (the console-script entry point)."""
    code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1"}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd, env=env)


EXPECTED_COMMANDS = {"config", "data", "train", "tune", "ui", "sweep", "status", "report", "profile", "track",
                     "selftest"}


def test_the_command_list_is_explicit_and_matches_help():
    assert set(cli.COMMANDS) | set(cli.GROUPS) == EXPECTED_COMMANDS
    out = run_console_script("--help").stdout
    listed = set(re.findall(r"^│ (\w[\w-]*)\s", out, flags=re.M))
    assert EXPECTED_COMMANDS <= listed


def test_version():
    result = run_console_script("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"bronchopose {__version__}"


@pytest.mark.parametrize(
    "text, expected",
    [
        ("name: t\ngrid: {arch: [transformer]}\n", "grid.arch[0]"),
        ("name: t\ntrain: {lr: [1]}\n", "train.lr"),
        ("name: t\nunknown_section: 1\n", "unknown key 'unknown_section'"),
        ("name: t\ngrid: [\n", "YAML syntax error"),
    ],
)
def test_malformed_config_exits_2_with_one_clear_message(tmp_path, text, expected):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    result = run_console_script("config", "--config", str(path))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("error: ") and expected in result.stderr


def test_config_command_prints_resolved_yaml_and_grid(cli, repo):
    code, out, _ = cli("config", "--config", str(repo / "experiments.yaml"), "--set", "train.lr=0.5")
    assert code == 0 and "lr: 0.5" in out
    code, out, _ = cli("config", "-c", str(repo / "experiments.yaml"), "--grid", "--set", "grid.arch=[lstm]")
    assert code == 0 and re.search(r"\b6 cells\b", out)
