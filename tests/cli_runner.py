"""Tests' helper: ``labrig ARGS`` in the test's own process, through the console entry point, as a user would type it."""

from __future__ import annotations

import sys
from typing import Any, Protocol

from labrig.cli import main


class _Captured(Protocol):
    @property
    def out(self) -> str: ...

    @property
    def err(self) -> str: ...


class _Capture(Protocol):
    def readouterr(self) -> _Captured: ...


def run_labrig(monkeypatch: Any, capsys: _Capture, *args: object) -> tuple[int, str, str]:
    """Run ``labrig ARGS`` with pytest's ``monkeypatch`` and ``capsys``; (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["labrig", *map(str, args)])
    try:
        main()
    except SystemExit as exc:
        code = exc.code
    else:
        raise AssertionError("labrig returned without exiting")
    captured = capsys.readouterr()
    return int(code or 0), captured.out, captured.err
