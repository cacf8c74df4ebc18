"""Errors and warnings that the CLI turns into one clear line on stderr.

Every user-facing failure (bad file, bad YAML, corrupt recording, infeasible instance)
is raised as a :class:`PerfrosError`; the CLI prints ``error: <message>`` and exits 2.
Messages name the file first, then the node/field, then the problem.
"""

from __future__ import annotations

from pathlib import Path


class PerfrosError(Exception):
    """A user error: printed as one line, exit code :attr:`exit_code`."""

    exit_code = 2


class InputError(PerfrosError):
    """A file (spec, recording, trace, plan) is missing, unreadable or invalid."""

    def __init__(self, path: str | Path | None, problem: str) -> None:
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class InfeasibleError(PerfrosError):
    """No plan satisfies the constraints: ``reason`` names the constraint and the parties,
    ``path`` the system (or the infeasible plan) it is about, ``consequence`` what cannot
    be done therefore (e.g. ``nothing to validate``)."""

    def __init__(self, reason: str, path: str | Path | None = None, consequence: str | None = None) -> None:
        self.reason = reason
        self.path = None if path is None else str(path)
        self.consequence = consequence
        message = f"infeasible: {reason}" + (f" ({consequence})" if consequence else "")
        super().__init__(f"{self.path}: {message}" if self.path else message)


class PerfrosWarning(UserWarning):
    """A warning for the user (printed to stderr by the CLI as ``warning: ...``)."""
