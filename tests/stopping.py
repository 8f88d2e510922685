"""A stop request for the tests of stopped and resumed commands (imported by them; no tests here)."""

import signal

from cvqpg.app import signals


class CountedStop(signals.StopRequest):
    """A stop request that counts how often it is asked and, once `after` is set, stops after that many asks."""

    asked: list = []
    after: int | None = None

    def __call__(self) -> bool:
        self.asked.append(True)
        self.signals = [signal.SIGINT] if self.after is not None and len(self.asked) > self.after else []
        return bool(self.signals)
