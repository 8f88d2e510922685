"""File names and defaults that the command line shows before it runs anything.

Plain values, kept apart from the modules that use them (each imports its own from here), so that
`cvqpg --version` and every `--help` answer without importing PyTorch or Numba.
"""

from __future__ import annotations

# The compressed model file (`codec`).
SUFFIX = ".cvq"

# `--depth auto` (`depth`): the estimator, and the file of its map in the run folder.
DEPTH_MODEL = "depth-anything/Depth-Anything-V2-Small-hf"
DEPTH_FILE = "depth.png"

# The built-in scenes (`scenes.SCENES`), in the order `--scene` lists them.
SCENE_NAMES = ("demo", "star")

# `cvqpg view` (`view`): its page in the run folder, and its focal sweep.
VIEW_FILE = "view.html"
DEFAULT_SWEEP = (0.5e-3, 6e-3, 41)  # START (m), STOP (m), COUNT

# The display a hologram is shown on (`display`): its encodings (`display.ENCODINGS`), the phase-only ones that
# `cvqpg export` writes, a phase-only SLM's phase levels, and the 4f filter's aperture (a fraction of the Nyquist
# frequency) that `dpac` takes by default (docs/method.md §8).
DISPLAY_ENCODINGS: tuple[str, ...] = ("complex", "dpac", "phase")
ENCODINGS: tuple[str, ...] = ("dpac", "phase")
DEFAULT_LEVELS = 256
DEFAULT_APERTURE = 0.5

# A fit's checkpoint period in seconds of work (`app.runner`).
CHECKPOINT_SECONDS = 180.0
# The folder of an unfinished fit or encode, beside the output it becomes: `OUT.partial`.
PARTIAL_SUFFIX = ".partial"
# An encode's folder (`app.encoding`): the budget and the fine-tuning steps, beside config.json.
BUDGET_FILE = "budget.json"
# `cvqpg batch` (`app.batch`): the folder of a batch folder's records, which marks it as one.
BATCH_RECORDS = ".batch"

# Where the tasks of `bench` and `batch` run (`app.executors`): this machine, or a Ray cluster.
EXECUTORS = ("local", "ray")

# Fine-tuning steps at the chosen rung where the caller gives none (the rate–distortion benchmark's).
RATE_FINETUNE_STEPS = 100
# `cvqpg encode`'s optimisation: float steps, then quantisation-aware ones at the bit depths rate control chose.
# About a Table 1 fit's steps, split so: on 640×480 and 320×240 grayscale fits, 1500 + 600 wrote files above
# 2000 + 100 at the same budget (docs/compression.md, "Where encode's steps go").
ENCODE_STEPS = 1500
ENCODE_FINETUNE_STEPS = 600
