"""How a command stops when asked. Every Ctrl-C (SIGINT) and SIGTERM a command receives is recorded (`received`)
before anything else happens, so that no callback can make it forget one: an exception raised from a signal
handler inside a C callback (Numba's compiler) is swallowed there, and the command would go on as if it had
never been asked. The output rule reads the record before anything is moved into place (`check_not_stopped`,
`app.outputs`), so that a command that was told to stop publishes nothing, and the command line then exits with
128 + N.

Where each signal acts (`handled` for the whole command): within a fit's steps (`StopRequest`, which
`RunControl.stop_requested` reads) the first Ctrl-C or SIGTERM asks the fit to stop after its current step, which
saves a checkpoint; anywhere else, and on a second Ctrl-C, the signal also raises where the command is
(`KeyboardInterrupt`, `Terminated`), so that it removes what it half wrote."""

from __future__ import annotations

import signal
from contextlib import contextmanager
from typing import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# The signals of `STOP_SIGNALS` received since the command began; None outside a command (`handled`).
_received: list[int] | None = None


class Terminated(BaseException):
    """A stop signal other than Ctrl-C (SIGTERM) outside a fit's steps: raised where the command is, so that it
    removes what it half wrote, as after Ctrl-C, instead of dying with its staged folder and lock left behind."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def received() -> int | None:
    """The first stop signal the command received (`handled`), or None."""
    return _received[0] if _received else None


def _record(signum: int) -> None:
    if _received is not None:
        _received.append(signum)


def stop_error(signum: int) -> BaseException:
    """What a stop signal raises where the command is: `KeyboardInterrupt` for Ctrl-C, else `Terminated`."""
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


def check_not_stopped() -> None:
    """Raise the first stop signal's exception (`stop_error`) where one was received: called before an output is
    moved into place, so that a command told to stop publishes nothing, even where the signal's own exception was
    swallowed."""
    if _received:
        raise stop_error(_received[0])


def raised_if_stopped() -> bool:
    """A `RunControl.stop_requested` for work that keeps nothing to resume (a render, an export, a page, a
    search): never a request to stop between two steps, but the first stop signal's exception raised again where
    the work asks (`check_not_stopped`), so that a command whose signal a callback swallowed stops at its work's
    next check instead of doing all of it first."""
    check_not_stopped()
    return False


def _raise_where_the_command_is(signum: int, _frame: object) -> None:
    _record(signum)
    raise stop_error(signum)


@contextmanager
def handled() -> Iterator[None]:
    """A command: within the block, Ctrl-C and SIGTERM are recorded (`received`) and raise where the command is
    (`stop_error`), except within a fit's steps (`StopRequest`)."""
    global _received
    outer, _received = _received, []
    previous = {signum: signal.signal(signum, _raise_where_the_command_is) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _received = outer


class StopRequest:
    """Within the block, Ctrl-C or SIGTERM (recorded) asks the fit to stop after its current step, as does one
    received before the block began; a second Ctrl-C raises `KeyboardInterrupt`. `signals`: those it heard."""

    def __init__(self) -> None:
        self.signals: list[int] = []
        self._previous: dict[int, object] = {}

    def __call__(self) -> bool:
        return bool(self.signals)

    def _receive(self, signum: int, _frame: object) -> None:
        _record(signum)
        self.signals.append(signum)
        signal.signal(signal.SIGINT, _raise_where_the_command_is)

    def __enter__(self) -> "StopRequest":
        self.signals = list(_received or ())
        self._previous = {s: signal.signal(s, self._receive) for s in STOP_SIGNALS}
        if self.signals:  # asked before the fit began: the next Ctrl-C is the second
            signal.signal(signal.SIGINT, _raise_where_the_command_is)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
