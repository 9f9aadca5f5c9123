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
                     "selftest", "weights"}


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
def test_malformed_config_exits_2_with_one_clear_message(cli, tmp_path, text, expected):
    """In-process (the console script's own error path, ``cli``): the process itself is under test above."""
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    code, _, err = cli("config", "--config", str(path))
    assert code == 2
    assert "Traceback" not in err
    assert err.startswith("error: ") and expected in err


def test_config_command_prints_resolved_yaml_and_grid(cli, repo):
    code, out, _ = cli("config", "--config", str(repo / "experiments.yaml"), "--set", "train.lr=0.5")
    assert code == 0 and "lr: 0.5" in out
    code, out, _ = cli("config", "-c", str(repo / "experiments.yaml"), "--grid", "--set", "grid.seed=[0]")
    assert code == 0 and re.search(r"\b12 cells\b", out)  # the default plan: 4 architectures x 3 losses, one seed
    # the table6 profile's sota stage sets arch itself: a --set grid.arch would change nothing, so it is refused
    code, out, _ = cli("config", "-c", str(repo / "experiments.yaml"), "--profile", "table6", "--grid",
                       "--set", "grid.seed=[0]")
    assert code == 0 and re.search(r"\b2 cells\b", out)  # BronchoTrack and OffsetNet, one seed
    code, _, err = cli("config", "-c", str(repo / "experiments.yaml"), "--profile", "table6", "--grid",
                       "--set", "grid.arch=[lstm]")
    assert code == 2 and "has no effect: the stages decide the cells" in err



def _complete(monkeypatch, words: str) -> list[str]:
    """What the shell gets for ``words`` (Typer's bash completion protocol, in-process)."""
    import contextlib
    import io

    monkeypatch.setenv("_BRONCHOPOSE_COMPLETE", "complete_bash")
    monkeypatch.setenv("COMP_WORDS", words)
    monkeypatch.setenv("COMP_CWORD", str(len(words.split(" ")) - 1))
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as done:
        cli.main([])
    assert done.value.code in (0, None)
    return out.getvalue().split()


def test_choices_complete_in_the_shell_and_are_listed_in_help(monkeypatch):
    from bronchocli.cells import POPULATIONS
    from bronchocli.registry import arch_names
    from bronchocli.reporting.tables import TABLES

    assert _complete(monkeypatch, "bronchopose train --arch ") == list(arch_names())
    assert _complete(monkeypatch, "bronchopose train --arch c") == [a for a in arch_names() if a.startswith("c")]
    assert _complete(monkeypatch, "bronchopose tune --population ") == list(POPULATIONS)
    assert _complete(monkeypatch, "bronchopose report --table ") == ["all", *TABLES]  # the registry, not a copy
    assert _complete(monkeypatch, "bronchopose report --eval ") == ["accumulated", "pair", "both"]
    monkeypatch.delenv("_BRONCHOPOSE_COMPLETE")
    shown = run_console_script("train", "--help").stdout
    assert "<baseline|lstm|convlstm|conv3d|offsetnet>" in "".join(c for c in shown if c not in " \n│")
    assert "--install-completion" in run_console_script("--help").stdout
