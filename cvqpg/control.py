"""What happens around the steps of a long computation (a fit, a fine-tuning, a rate search, a grid):
whether it shows progress, when it should stop, and whom it tells about each step. One object is passed
down the layers instead of three arguments."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

StepCallback = Callable[[int, float, float], None]  # (step index, loss, PSNR in dB)


class Stopped(Exception):
    """Work that keeps nothing to resume (a render, an export, a page) stopped on request (`RunControl.check`)."""


@dataclass(frozen=True)
class RunControl:
    """`progress`: show a progress bar. `stop_requested()`: true once the work should stop between two
    steps (saving a checkpoint where it can). `on_step(step, loss, psnr)`: called for every step as its
    values are read back."""

    progress: bool = True
    stop_requested: Callable[[], bool] | None = None
    on_step: StepCallback | None = None

    def should_stop(self) -> bool:
        """Whether `stop_requested` is given and asks to stop now."""
        return self.stop_requested is not None and self.stop_requested()

    def check(self) -> None:
        """Between the stages of work that keeps nothing to resume: `Stopped` where `stop_requested` asks to stop
        now (a caller may as well raise its own exception from `stop_requested`)."""
        if self.should_stop():
            raise Stopped("stopped on request")

    def report(self, step: int, loss: float, psnr: float) -> None:
        """Tell `on_step`, where given, about one step."""
        if self.on_step is not None:
            self.on_step(step, loss, psnr)

    def quiet(self) -> "RunControl":
        """The same control without a progress bar (for inner work under an outer bar)."""
        return replace(self, progress=False)

    def without_steps(self) -> "RunControl":
        """The same control without the step callback (for work whose steps are not the caller's)."""
        return replace(self, on_step=None)


SILENT = RunControl(progress=False)
