"""How a command stops when asked: Ctrl-C or SIGTERM during a fit asks it to stop after its current step
(`StopRequest`, read by `RunControl.stop_requested`), a second Ctrl-C aborts; SIGTERM elsewhere raises `Terminated`
where the command is (`terminated_on_sigterm`), so that it removes what it half wrote, as after Ctrl-C."""

from __future__ import annotations

import signal
from contextlib import contextmanager
from typing import Iterator


class StopRequest:
    """Ctrl-C or SIGTERM asks the fit to stop after its current step; a second Ctrl-C aborts."""

    def __init__(self) -> None:
        self.signals: list[int] = []
        self._previous: dict[int, object] = {}

    def __call__(self) -> bool:
        return bool(self.signals)

    def _receive(self, signum: int, _frame: object) -> None:
        self.signals.append(signum)
        signal.signal(signal.SIGINT, signal.default_int_handler)

    def __enter__(self) -> "StopRequest":
        self._previous = {s: signal.signal(s, self._receive) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


class Terminated(BaseException):
    """SIGTERM outside a fit's steps (which `StopRequest` ends cleanly): raised where the command is, so that it
    removes what it half wrote, as after Ctrl-C, instead of dying with its staged folder and lock left behind."""


def _terminate(_signum: int, _frame: object) -> None:
    raise Terminated


@contextmanager
def terminated_on_sigterm() -> Iterator[None]:
    """SIGTERM raises `Terminated` within the block."""
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
