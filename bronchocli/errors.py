"""User-facing errors: the CLI prints their message (no traceback) and exits with code 2."""

from __future__ import annotations


class BronchoError(Exception):
    """A problem with the user's input (file, flag, config value) that they can fix."""

    exit_code = 2


class ConfigError(BronchoError):
    """experiments.yaml (or a --set override) is malformed; the message lists every problem."""


class DataError(BronchoError):
    """A dataset on disk is missing, malformed or inconsistent."""


class Interrupted(BronchoError):
    """Ctrl-C stopped a command cleanly; the message says how to continue (exit code 130)."""

    exit_code = 130
