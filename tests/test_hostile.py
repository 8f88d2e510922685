"""Hostile input at the command line, every case of it in one table: each refusal is exit code 2, one line
`cvqpg <command>: error: …` naming the problem (by its flag, never by a library parameter's name), and the folder it
ran in left exactly as it was (every path, its bytes and its mode). Library functions are held to their exceptions
in the other test modules; the command line's refusals are held here.

The table (`CASES`) is grouped by class: degenerate or non-finite numbers (`NUMBERS`), unknown choices and usage
typos (`USAGE`), missing, wrong or damaged inputs (`INPUTS`), and outputs that cannot be written or would destroy
something (`OUTPUTS`: a foreign file or folder under `--overwrite`, a symbolic link, the current folder, a resume
whose place is taken). A row is `(id, argv, fragment, *marks)`:
- `id`: unique within its group, `<command>-<what is wrong>`;
- `argv`: the command line after `cvqpg`, split as a shell would; `{name}` stands for an asset of `PLACES`
  (`{tmp}`: the folder the commands run in, also their current folder);
- `fragment`: text the one error line must hold (the flag, path or remedy that a user needs);
- `marks`: none, or `PERMISSIONS` where the case relies on file permissions, which do not hold for root (skipped
  there), and `SLOW` where the command works for seconds before it refuses (`pytest -m "not slow"` leaves it out).
To add a case, append a row to its group; to add an asset, name it in `PLACES` and make it in `template`.

Every case runs in one shared copy of a template folder of tiny assets made once through the CLI (`template`):
a refusal must change nothing, so the folder is checked against its first state after each case, and restored
from the template when a case changed it (that case fails). A second table (`SUCCESSES`) holds that a command
given `--overwrite` replaces its own output as a whole and nothing else, each in a copy of its own; beside it, a
second writer of one output is refused, and refused resumes keep their interrupted folders.
"""

from __future__ import annotations

import faulthandler
import functools
import json
import math
import os
import re
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import time
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from cvqpg import FitConfig, codec, fit
from cvqpg.app.batch import BatchInput, BatchSettings, plan_item
from cvqpg.app.compilation import probe_planes
from cvqpg.app.outputs import claimed
from cvqpg.cli import main
from cvqpg.config import RunOptions
from cvqpg.fitting import blank_state
from cvqpg.ops.propagation import FUSED_PLANES_AT_ONCE, plane_groups
from cvqpg.runs import read_run
from cvqpg.storage import save_checkpoint
from cvqpg.targets import check_depth_geometry, prepare_depth, prepare_image

ROOT = Path(__file__).resolve().parents[1]
RECORDED_CELL = ROOT / "results" / "paper" / "cells" / "bento_gray-10_baseline_s100"
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0

# The template's assets, named in the cases by placeholder. Folder names are distinctive, so that a fragment
# such as "run_a" cannot match a message by chance.
PLACES = {
    "run": "run_a",                        # the shared finished 32×24 RGB run, 2 planes (conftest); also model.cvq,
                                           # export/, render/, ...
    "run2": "run_b",                       # finished 48×36 grayscale run, 1 plane
    "model": "run_a/model.safetensors",
    "cvq": "run_a/model.cvq",              # compressed model of run_a
    "badcvq": "run_a/bad.cvq",             # model.cvq with bytes flipped, inside the run folder
    "brokencvq": "broken.cvq",             # the same damage, outside any run folder
    "emptycvq": "empty.cvq",
    "image": "photo.png",                  # 32×24 RGB
    "depth": "depth.png",                  # 32×24 horizontal ramp
    "square": "square_depth.png",          # 24×24: another aspect ratio
    "flat": "flat_depth.png",              # constant
    "binary": "binary_depth.png",          # two levels: separates 2 planes, not 5
    "nandepth": "nan_depth.tiff",          # float ('F') depth with NaN pixels
    "text": "notes.txt",
    "textpng": "notes.png",                # text named .png
    "folder": "folder",                    # an empty folder
    "cut": "cut.png",                      # truncated PNG
    "empty": "empty.png",                  # 0 bytes
    "notarun": "notarun",                  # a folder with a file, no config.json
    "unfinished": "unfinished",            # config.json only
    "loose": "loose/model.safetensors",    # a model outside its run folder
    "mixed": "mixed",                      # run_a's files plus run_b's model as foreign.safetensors
    "damaged": "damaged",                  # run_a's files with a garbage model.safetensors
    "bench": "bench",                      # finished `cvqpg bench --preset star` folder
    "records": "records",                  # a results root: records/paper/cells/<one recorded cell>
    "badrecords": "badrecords",            # a results root whose one cell was fitted with other settings
    "page": "page.html",                   # an existing page
    "readonly": "readonly",                # chmod 0o555 (the permission cases are skipped as root)
    "scenes": "scenes",                    # a --scenes folder of one scene (image.png, depth.png)
    "gpurun": "gpu_run",                   # an unfinished run_a whose config says it was fitted on CUDA
    "gpucheckpoint": "gpu_checkpoint",     # an unfinished run_a whose checkpoint was written on CUDA
    "oldformat": "old_format",             # run_a with a model of format version 0
    "lacking": "lacking",                  # run_a with a model without its curvature tensor
    "misshapen": "misshapen",              # run_a with a model whose amplitude has one channel of three
    "cuttarget": "cut_target",             # run_a with target_plane1.png truncated
    "cutmetrics": "cut_metrics",           # run_a with metrics.json truncated
    "cutexport": "cut_export",             # run_a with export/metrics.json truncated
    "cutdisplay": "cut_display",           # run_a with export/display_plane0.png truncated
    "twin": "twin",                        # run_a's files with the model of a run of the same size and optics
                                           # (another seed), also as foreign.safetensors
    "guarded": "guarded",                  # an unfinished run_a whose config.json asks for a 16384 px guard band
    "guardedrun": "guarded_run",           # run_a whose config.json asks for a 16384 px guard band
    "held": "held",                        # a user's folder; held.partial an interrupted run that would finish there
    "filed": "filed",                      # a user's file; filed.partial an interrupted run that would finish there
    "linked": "linked",                    # -> notarun; linked.partial an interrupted run that would finish there
    "encoded": "enc.cvq.partial",          # an interrupted encode's folder
    "foreigncvq": "foreign.cvq",           # a user's text file named .cvq; foreign.cvq.partial an interrupted encode
    "tampered": "tampered.cvq.partial",    # an interrupted encode whose budget.json was changed to 1 byte
    "modelfolder": "model_folder",         # run_a's files with a folder at model.safetensors
    "modelless": "modelless",              # run_a's files but model.safetensors: finished, its model gone
    "stranded": "stranded",                # stranded.partial: a finished run (run_b) never moved into place
    "filedwork": "filed_work",             # filed_work.partial: a file
    "lost": "lost",                        # a finished run whose image is gone
    "linkdir": "linkdir",                  # -> notarun
    "linkrender": "linkrender",            # -> run_a/render
    "linkrun": "linkrun",                  # -> run_b
    "linkcvq": "linkcvq.cvq",              # -> run_a/model.cvq
    "linkpage": "linkpage.html",           # -> page.html
    "dangling": "dangling.safetensors",    # -> nowhere
    "trailing": "run_a/trailing.cvq",      # model.cvq with bytes after its end (the checksum made to hold)
    "nodict": "run_a/nodict.cvq",          # model.cvq whose header is deflated without its preset dictionary
    "lockdir": "locked.cvq",               # a folder at the lock's path beside it: .locked.cvq.cvqpg-lock/
    "bdone": "b_done",                     # a finished batch folder of one item, `tiny` of {scenes}
    # Copies of it, each with something that is not the batch's in its way:
    "bforeign": "b_foreign",               # tiny/: a user's run (run_b), where the batch's finished one was
    "bfailed": "b_failed",                 # tiny/: a user's run, where the item failed
    "bcvq": "b_cvq",                       # tiny.cvq: a user's file (no record names it)
    "blink": "b_link",                     # tiny.partial, tiny.cvq.partial: links to a user's folder (notarun)
    "bwork": "b_work",                     # tiny.partial: a user's folder of other files
    "bdotbatch": "b_dot_batch",            # .batch: a file
    "bsummary": "b_summary",               # summary.csv: a folder
    "block": "b_lock",                     # .batch/summary.lock: a folder
    "blog": "b_log",                       # tiny.error.log: a folder
    "brecord": "b_record",                 # .batch/tiny.json: a folder
    "longname": "long_name.csv",           # a manifest naming its item in 240 bytes
    "nulname": "nul_name.csv",             # a manifest whose name holds a NUL byte
    "tabname": "tab_name.csv",             # a manifest whose name holds a tab
    "twocolumns": "two_columns.csv",       # a manifest naming its image column twice
    "hugelut": "huge_lut.csv",             # a lookup table of finite phases far beyond a turn (1e300 rad)
    "degreelut": "degree_lut.csv",         # a lookup table in degrees (0..359)
    "danglingwork": "dangling.cvq",        # dangling.cvq.partial: a link to nowhere, where an encode's work goes
    "metricsfolder": "metrics_folder",     # run_a with a folder at metrics.json
    "metricslink": "metrics_link",         # run_a with metrics.json a link to photo.png
    "badmetrics": "bad_metrics",           # run_a whose metrics.json holds a number as its mean
    "infbudget": "inf_budget.cvq.partial",  # an interrupted encode whose budget.json holds 1e400 bytes
    "floatsteps": "float_steps.cvq.partial",  # an interrupted encode whose budget.json holds 1e30 tuning steps
    # Copies of {bench}, with something that is not the bench's where it writes:
    "benchlink": "bench_link",             # its CVQPG cell's folder a link to a user's folder (notarun)
    "cellslink": "cells_link",             # cells/ a link to a user's folder
    "benchrecord": "bench_record",         # its CVQPG cell's metrics.json a folder
    "benchbadrecord": "bench_bad_record",  # its CVQPG cell's metrics.json a number as its mean
    "loop": "loop",                        # -> loop: a loop of symbolic links
}

FIT = "--size 32 24 --steps 1 --quiet --out new_run"  # a fit that is wrongly accepted ends soon
SWEEP = "--distances 0.001 0.002 2"  # the same for a page
BENCH = "--preset star --size 32 24 --steps 2 --scene-names star --quiet --out new_bench"
RD_BENCH = "--preset compression --scenes {scenes} --fits bench --size 32 24 --steps 2 --quiet --out new_bench"
ENCODE = "encode {image} --depth {depth} --size 32 24 --steps 1 --finetune 1 --quiet"  # as FIT, into a file
BATCH = "batch {scenes} --size 32 24 --steps 1 --quiet"  # a batch that is wrongly accepted ends soon


class Case(NamedTuple):
    id: str
    argv: str
    fragment: str
    permissions: bool  # relies on file permissions, which do not apply to root


PERMISSIONS, SLOW = "permissions", "slow"
# Under pytest-xdist, every test that may start Ray runs on one worker, one after another: two Ray sessions of one
# machine, started at once by two workers, find each other's cluster.
RAY_GROUP = pytest.mark.xdist_group("ray")


def cases(group: str, *rows: tuple) -> list:
    """The table's rows as parameters: slow where marked, and a case that may start Ray on the Ray tests' worker
    (`RAY_GROUP`)."""
    return [pytest.param(Case(f"{group}:{name}", argv, fragment, PERMISSIONS in marks), id=f"{group}:{name}",
                         marks=[*([pytest.mark.slow] if SLOW in marks else []),
                                *([RAY_GROUP] if "--executor ray" in argv else [])])
            for name, argv, fragment, *marks in rows]


# ---------------------------------------------------------------------------------------------------------------
# Non-finite, degenerate and out-of-range numbers.
NUMBERS = cases(
    "numbers",
    ("fit-ratio-inf", f"fit {FIT} --ratio inf", "--ratio"),
    ("fit-ratio-nan", f"fit {FIT} --ratio nan", "--ratio"),
    ("fit-ratio-0", f"fit {FIT} --ratio 0", "--ratio"),
    ("fit-ratio-negative", f"fit {FIT} --ratio -1", "--ratio"),
    ("fit-ratio-above-pixel-count", f"fit {FIT} --ratio 3", "--ratio"),
    ("fit-pitch-inf", f"fit {FIT} --pitch inf", "--pitch"),
    ("fit-pitch-nan", f"fit {FIT} --pitch nan", "--pitch"),
    ("fit-pitch-0", f"fit {FIT} --pitch 0", "--pitch must lie in [1e-07, 0.001], got 0.0"),
    ("fit-pitch-negative-joined", f"fit {FIT} --pitch=-3.74e-6", "--pitch must lie in [1e-07, 0.001]"),
    ("fit-pitch-1e-30", f"fit {FIT} --pitch 1e-30", "--pitch must lie in [1e-07, 0.001], got 1e-30"),
    ("fit-plane-span-nan", f"fit {FIT} --plane-span nan", "--plane-span"),
    ("fit-plane-span-inf", f"fit {FIT} --plane-span inf", "--plane-span"),
    ("fit-plane-span-negative", f"fit {FIT} --plane-span -0.004", "--plane-span must lie in [0, 10], got -0.004"),
    ("fit-plane-center-negative", f"fit {FIT} --plane-center -1", "--plane-center"),
    ("fit-plane-center-puts-a-plane-behind", f"fit {FIT} --plane-center -0.001", "plane distances"),
    ("fit-plane-center-inf", f"fit {FIT} --plane-center inf", "--plane-center"),
    ("fit-wavelength-0", f"fit {FIT} --color gray --wavelengths 0", "--wavelengths"),
    ("fit-wavelengths-inf", f"fit {FIT} --wavelengths inf 1 2", "--wavelengths"),
    ("fit-wavelengths-nan", f"fit {FIT} --wavelengths 639e-9 nan 473e-9", "--wavelengths"),
    ("fit-wavelengths-one-0", f"fit {FIT} --wavelengths 639e-9 0 473e-9", "--wavelengths must lie in [1e-07, 2e-05]"),
    ("fit-wavelengths-1-m", f"fit {FIT} --wavelengths 1 1 1", "--wavelengths must lie in [1e-07, 2e-05], got 1.0"),
    ("fit-wavelengths-negative", f"fit {FIT} --wavelengths 0.000000639 -0.000000532 0.000000473", "--wavelengths"),
    ("fit-wavelengths-too-few", f"fit {FIT} --wavelengths 639e-9", "need 3 value(s)"),
    ("fit-planes-0", f"fit {FIT} --planes 0", "--planes"),
    ("fit-planes-negative", f"fit {FIT} --planes -2", "--planes"),
    ("fit-steps-0", f"fit {FIT} --steps 0", "--steps must lie in [1, 100000000], got 0"),
    ("fit-steps-negative", f"fit {FIT} --steps -5", "--steps must lie in [1, 100000000], got -5"),
    ("fit-num-gaussians-0", f"fit {FIT} --num-gaussians 0", "--num-gaussians must lie in [1, 2147483648], got 0"),
    ("fit-num-gaussians-huge", f"fit {FIT} --num-gaussians 10000000", "need between 1 and the pixel count"),
    ("fit-num-gaussians-negative", f"fit {FIT} --num-gaussians -3", "--num-gaussians"),
    ("fit-size-0", f"fit {FIT} --size 0 0", "--size"),
    ("fit-size-8", f"fit {FIT} --size 8 8", "--size must lie in [16, 65536], got 8"),
    ("fit-size-negative", f"fit {FIT} --size -32 24", "--size"),
    ("fit-size-beyond-memory", f"fit {FIT} --size 60000 60000", "GiB are available"),
    ("fit-size-beyond-its-range", f"fit {FIT} --size 100000 100000", "--size must lie in [16, 65536], got 100000"),
    ("fit-warmup-negative", f"fit {FIT} --curvature-warmup -1", "--curvature-warmup"),
    ("fit-warmup-beyond-steps", f"fit {FIT} --curvature-warmup 99999",
     "--curvature-warmup must lie in [0, "),
    ("fit-seed-beyond-64-bits", f"fit {FIT} --seed 100000000000000000000000", "--seed must lie in [0, "),
    ("fit-checkpoint-every-negative", f"fit {FIT} --checkpoint-every -1", "--checkpoint-every"),
    ("fit-seed-negative", f"fit {FIT} --seed -1", "--seed"),
    ("fit-time-0", "fit --size 32 24 --quiet --out new_run --time 0", "--time"),
    ("fit-time-negative", "fit --size 32 24 --quiet --out new_run --time -2", "--time"),
    ("fit-time-nan", "fit --size 32 24 --quiet --out new_run --time nan", "--time"),
    ("fit-time-and-steps", f"fit {FIT} --time 1", "--time"),
    ("export-levels-1", "export {run} --levels 1 --out new_export", "phase levels"),
    ("export-levels-0", "export {run} --levels 0 --out new_export", "--levels"),
    ("export-levels-negative", "export {run} --levels -4 --out new_export", "--levels"),
    ("export-aperture-negative", "export {run} --aperture -1 --out new_export", "--aperture"),
    ("export-aperture-nan", "export {run} --aperture nan --out new_export", "--aperture"),
    ("export-aperture-inf", "export {run} --aperture inf --out new_export", "--aperture"),
    ("export-slm-0", "export {run} --slm 0 0 --out new_export", "--slm"),
    ("export-slm-smaller-than-hologram", "export {run} --slm 10 10 --out new_export", "--slm 10×10 is smaller than"),
    ("export-slm-negative", "export {run} --slm -32 24 --out new_export", "--slm"),
    ("render-distance-0", "render {run} --distance 0 --out new_render", "--distance 0 m must lie in [1e-06, 10] m"),
    ("render-distance-1e300", "render {run} --distance 0.001 1e300 --out new_render",
     "--distance 0.001, 1e+300 m must lie in [1e-06, 10] m"),
    ("render-distance-11-m", "render {run} --distance 11 --out new_render", "must lie in [1e-06, 10] m"),
    ("render-size-beyond-memory", "render {run} --size 60000 45000 --out new_render", "GiB are available"),
    ("render-size-100000", "render {run} --size 100000 75000 --out new_render", "a 100000×75000 render"),
    ("export-slm-beyond-memory", "export {run} --slm 100000 100000 --out new_export", "a 100000×100000 export"),
    ("export-levels-beyond-64-bits", "export {run} --levels 100000000000000000000 --out new_export",
     "--levels: 100000000000000000000 lies beyond the 64-bit integers"),
    ("view-distances-stop-1e300", "view {run} --distances 0.001 1e300 3 --quiet --out new.html",
     "must lie in [1e-06, 10] m"),
    ("view-distances-start-1e-9", "view {run} --distances 1e-9 0.002 3 --quiet --out new.html",
     "must lie in [1e-06, 10] m"),
    ("view-distances-count-1e300", "view {run} --distances 0.001 0.002 1e300 --quiet --out new.html",
     "COUNT must lie in [1, 4096]"),
    ("fit-time-1e307", "fit --size 32 24 --quiet --out new_run --time 1e307", "at most 525600 (a year)"),
    ("fit-checkpoint-every-beyond-64-bits", f"fit {FIT} --checkpoint-every 100000000000000000000000",
     "--checkpoint-every: 100000000000000000000000 lies beyond the 64-bit integers"),
    ("fit-steps-beyond-64-bits", "fit --size 32 24 --quiet --out new_run --steps 99999999999999999999", "--steps"),
    ("fit-size-beyond-64-bits", f"fit {FIT} --size 99999999999999999999 24", "--size"),
    ("fit-resume-huge-guard-band", "fit --resume {guarded} --quiet", "a 16384 px guard band needs about"),
    ("eval-huge-guard-band", "eval {guardedrun}", "a 16384 px guard band needs about"),
    ("compress-bpp-1e308", "compress {run} --bpp 1e308 --out new.cvq", "give a budget of at most 9007199254740992"),
    ("compress-max-bytes-beyond-2-53", "compress {run} --max-bytes 1152921504606846976 --out new.cvq",
     "at most 9007199254740992"),
    ("compress-max-bytes-beyond-64-bits", "compress {run} --max-bytes 100000000000000000000000 --out new.cvq",
     "beyond the 64-bit integers"),
    ("compress-prune-0.999", "compress {run} --finetune 2 --prune 0.999 --out new.cvq", "--prune 0.999 removes all"),
    ("encode-bpp-1e308", f"{ENCODE} --bpp 1e308 --out new.cvq", "give a budget of at most"),
    ("encode-max-bytes-beyond-64-bits", f"{ENCODE} --max-bytes 100000000000000000000 --out new.cvq",
     "beyond the 64-bit integers"),
    ("bench-threads-beyond-64-bits", f"bench {BENCH} --threads 100000000000000000000", "--threads"),
    ("bench-jobs-beyond-64-bits", f"bench {BENCH} --jobs 100000000000000000000", "--jobs"),
    ("render-distance-negative", "render {run} --distance -1 --out new_render", "--distance"),
    ("render-distance-inf", "render {run} --distance inf --out new_render", "--distance"),
    ("render-distance-nan", "render {run} --distance 0.001 nan --out new_render", "--distance"),
    ("render-size-0", "render {run} --size 0 0 --out new_render", "--size"),
    ("render-size-other-aspect", "render {run} --size 33 24 --out new_render", "aspect ratio"),
    ("render-size-square", "render {run} --size 80 80 --out new_render", "aspect ratio"),
    ("render-size-negative", "render {run} --size -32 -24 --out new_render", "--size"),
    ("render-size-16-12", "render {run} --size 16 12 --out new_render", "--size 16×12: each side needs at least 16 px"),
    ("render-size-finer-than-the-wavelengths", "render {run} --size 320 240 --out new_render",
     "--size 320×240: a wavelength of 6.39e-07 m needs a pixel pitch above"),
    ("fit-wavelength-beyond-the-pitch", f"fit {FIT} --wavelengths 639e-9 532e-9 6e-6",
     "which takes wavelengths below 5.28916e-06 m; keep every --wavelengths below it, or give a larger --pitch"),
    ("fit-pitch-below-the-wavelengths", f"fit {FIT} --pitch 4e-7", "a wavelength of 6.39e-07 m needs a pixel pitch"),
    ("export-aperture-1e300", "export {run} --aperture 1e300 --out new_export", "give a radius in [0, √2]"),
    ("export-aperture-2", "export {run} --aperture 2 --out new_export", "--aperture 2"),
    ("render-distance-twice", "render {run} --distance 0.001 0.001 --out new_render",
     "--distance 0.001 and 0.001 m would both be written to recon_1mm.png"),
    ("render-distance-alike-to-6-digits", "render {run} --distance 0.002 0.0010000001 0.001 --out new_render",
     "give distinct distances"),
    ("view-distances-start-0", "view {run} --distances 0 1 5 --quiet --out new.html", "--distances"),
    ("view-distances-count-0", "view {run} --distances 0.001 0.002 0 --quiet --out new.html", "--distances"),
    ("view-distances-nan", "view {run} --distances 0.001 nan 3 --quiet --out new.html", "--distances"),
    ("view-distances-inf", "view {run} --distances 0.001 inf 3 --quiet --out new.html", "--distances"),
    ("view-distances-negative", "view {run} --distances -0.001 0.002 3 --quiet --out new.html", "--distances"),
    ("view-distances-fractional-count", "view {run} --distances 0.001 0.002 2.5 --quiet --out new.html",
     "COUNT is a whole number"),
    ("view-distances-in-mm", "view {run} --distances 0.5 6 41 --quiet --out new.html", "distances are in m"),
    ("compress-max-drop-negative", "compress {run} --max-drop -1 --out new.cvq", "--max-drop"),
    ("compress-max-drop-nan", "compress {run} --max-drop nan --out new.cvq", "--max-drop"),
    ("compress-max-drop-inf", "compress {run} --max-drop inf --out new.cvq", "--max-drop"),
    ("compress-prune-1", "compress {run} --finetune 2 --prune 1 --out new.cvq", "--prune"),
    ("compress-prune-negative", "compress {run} --finetune 2 --prune -0.1 --out new.cvq", "--prune"),
    ("compress-prune-nan", "compress {run} --finetune 2 --prune nan --out new.cvq", "--prune"),
    ("compress-prune-without-finetune", "compress {run} --prune 0.5 --out new.cvq", "--prune"),
    ("compress-finetune-negative", "compress {run} --finetune -1 --out new.cvq", "--finetune"),
    ("compress-bits-99", "compress {run} --bits 99 --out new.cvq", "--bits"),
    ("compress-bits-position-negative", "compress {run} --bits position=-1 --out new.cvq", "--bits"),
    ("compress-bits-unknown-attribute", "compress {run} --bits nonsense=3 --out new.cvq", "--bits"),
    ("compress-bits-not-a-number", "compress {run} --bits phase=x --out new.cvq", "--bits"),
    ("compress-bits-an-attribute-twice", "compress {run} --bits phase=3 phase=5 --out new.cvq",
     "--bits phase=3 and phase=5: give each attribute once"),
    ("bench-jobs-0", f"bench {BENCH} --jobs 0", "--jobs"),
    ("bench-jobs-negative", f"bench {BENCH} --jobs -1", "--jobs"),
    ("bench-threads-0", f"bench {BENCH} --threads 0", "--threads"),
    ("bench-shard-0", f"bench {BENCH} --shard 0/2", "--shard"),
    ("bench-shard-beyond-count", f"bench {BENCH} --shard 3/2", "--shard"),
    ("bench-shard-not-a-fraction", f"bench {BENCH} --shard x", "--shard"),
    ("bench-shard-of-0", f"bench {BENCH} --shard 1/0", "--shard"),
    ("bench-steps-0", f"bench {BENCH} --steps 0", "--steps"),
    ("bench-steps-negative", f"bench {BENCH} --steps -1", "--steps"),
    ("bench-size-8", f"bench {BENCH} --size 8 8", "--size"),
    ("bench-size-0", f"bench {BENCH} --size 0 0", "--size"),
    ("bench-ratio-0", f"bench {BENCH} --ratios 0", "--ratio"),
    ("bench-ratio-nan", f"bench {BENCH} --ratios nan", "--ratio"),
    ("bench-ratio-inf", f"bench {BENCH} --ratios inf", "--ratio"),
    ("bench-warmup-negative", f"bench {BENCH} --curvature-warmup -1", "--curvature-warmup"),
    ("bench-warmup-beyond-steps", f"bench {BENCH} --curvature-warmup 99999", "--curvature-warmup"),
    ("bench-finetune-negative", f"bench {RD_BENCH} --finetune -1", "--finetune"),
    ("compress-bpp-0", "compress {run} --bpp 0 --out new.cvq", "--bpp"),
    ("compress-bpp-negative", "compress {run} --bpp -1 --out new.cvq", "--bpp"),
    ("compress-bpp-nan", "compress {run} --bpp nan --out new.cvq", "--bpp"),
    ("compress-bpp-inf", "compress {run} --bpp inf --out new.cvq", "--bpp"),
    ("compress-bpp-below-the-smallest-file", "compress {run} --bpp 1 --out new.cvq", "--bpp 1 (96 bytes"),
    ("compress-max-bytes-0", "compress {run} --max-bytes 0 --out new.cvq", "--max-bytes"),
    ("compress-max-bytes-below-the-smallest-file", "compress {run} --max-bytes 50 --out new.cvq", "smallest file"),
    ("encode-bpp-0", f"{ENCODE} --bpp 0 --out new.cvq", "--bpp"),
    ("encode-bpp-nan", f"{ENCODE} --bpp nan --out new.cvq", "--bpp"),
    ("encode-bpp-inf", f"{ENCODE} --bpp inf --out new.cvq", "--bpp"),
    ("encode-bpp-below-the-smallest-file", f"{ENCODE} --bpp 1 --out new.cvq", "smallest file"),
    ("encode-max-bytes-negative", f"{ENCODE} --max-bytes -5 --out new.cvq", "--max-bytes"),
    ("encode-finetune-negative", f"{ENCODE} --finetune -1 --bpp 8 --out new.cvq", "--finetune"),
    ("encode-steps-0", f"{ENCODE} --steps 0 --bpp 8 --out new.cvq", "--steps"),
    ("batch-steps-0", f"{BATCH} --steps 0 --out new_batch", "--steps"),
    ("batch-size-8", f"{BATCH} --size 8 8 --out new_batch", "--size"),
    ("batch-planes-0", f"{BATCH} --planes 0 --out new_batch", "--planes"),
    ("batch-ratio-nan", f"{BATCH} --ratio nan --out new_batch", "--ratio"),
    ("batch-bpp-0", f"{BATCH} --bpp 0 --out new_batch", "--bpp"),
    ("batch-bpp-below-the-smallest-file", f"{BATCH} --bpp 1 --out new_batch", "smallest file"),
    ("batch-finetune-negative", f"{BATCH} --finetune -1 --out new_batch", "--finetune"),
    ("batch-jobs-0", f"{BATCH} --jobs 0 --out new_batch", "--jobs"),
    ("batch-checkpoint-every-negative", f"{BATCH} --checkpoint-every -1 --out new_batch", "--checkpoint-every"),
    ("compress-finetune-beyond-a-fits-steps", "compress {run} --finetune 1000000000 --bits 8 --out new.cvq",
     "give at most 100000000 steps"),
)

# ---------------------------------------------------------------------------------------------------------------
# Unknown choices, typos and other usage errors (argparse's own included).
USAGE = cases(
    "usage",
    ("fit-color-RGB", f"fit {FIT} --color RGB", "--color"),
    ("fit-primitive-CVQPG", f"fit {FIT} --primitive CVQPG", "--primitive"),
    ("fit-qpf-Mahalanobis", f"fit {FIT} --qpf Mahalanobis", "--qpf"),
    ("fit-device-gpu", f"fit {FIT} --device gpu", "--device"),
    ("fit-backend-cuda", f"fit {FIT} --backend cuda", "--backend"),
    ("fit-bound-none", f"fit {FIT} --bound none", "--bound"),
    ("fit-curvature-rainbow", f"fit {FIT} --curvature rainbow", "invalid choice: 'rainbow'"),
    ("fit-scene-nope", f"fit {FIT} --scene nope", "--scene"),
    ("fit-device-cuda-without-gpu", f"fit {FIT} --device cuda", "no CUDA GPU"),
    ("fit-numba-on-cuda", f"fit {FIT} --device cuda --backend numba", "--backend numba runs on the CPU, not on cuda"),
    ("fit-triton-on-cpu", f"fit {FIT} --backend triton", "--backend triton runs on CUDA, not on cpu"),
    ("fit-recipe-unknown", f"fit {FIT} --recipe fastest", "--recipe"),
    ("fit-steps-not-whole", f"fit {FIT} --steps 2.5", "--steps"),
    ("fit-ratio-not-a-number", f"fit {FIT} --ratio abc", "--ratio"),
    ("fit-size-one-number", "fit --quiet --out new_run --size 32", "--size"),
    ("fit-ratio-and-num-gaussians", f"fit {FIT} --ratio 0.1 --num-gaussians 5", "--num-gaussians"),
    ("fit-unknown-flag", f"fit {FIT} --bogus-flag", "--bogus-flag"),
    ("fit-out-without-value", "fit --size 32 24 --steps 2 --quiet --out", "--out"),
    ("eval-no-target", "eval", "RUN_DIR"),
    ("eval-two-targets", "eval {run} {run2}", "run_b"),
    ("eval-device-gpu", "eval {run} --device gpu", "--device"),
    ("eval-device-cuda-without-gpu", "eval {run} --device cuda", "no CUDA GPU"),
    ("export-device-cuda-without-gpu", "export {run} --device cuda --out new_export", "--device cpu"),
    ("render-device-cuda-without-gpu", "render {run} --device cuda --out new_render", "--device cpu"),
    ("export-encoding-dpacc", "export {run} --encoding dpacc --out new_export", "--encoding"),
    ("export-device-gpu", "export {run} --device gpu --out new_export", "--device"),
    ("export-levels-not-whole", "export {run} --levels 2.5 --out new_export", "--levels"),
    ("export-slm-one-number", "export {run} --slm 64 --out new_export", "--slm"),
    ("info-no-target", "info", "RUN_DIR"),
    ("info-unknown-flag", "info {run} --bogus-flag", "--bogus-flag"),
    ("render-device-gpu", "render {run} --device gpu --out new_render", "--device"),
    ("render-distance-without-value", "render {run} --out new_render --distance", "--distance"),
    ("view-no-run", "view --quiet", "RUN_DIR"),
    ("view-distances-two-numbers", "view {run} --distances 0.001 0.002 --quiet --out new.html", "--distances"),
    ("compress-bits-and-max-drop", "compress {run} --bits 8 --max-drop 0.1 --out new.cvq", "--max-drop"),
    ("compress-finetune-not-whole", "compress {run} --finetune 1.5 --out new.cvq", "--finetune"),
    ("compress-bpp-and-max-drop", "compress {run} --bpp 8 --max-drop 0.1 --out new.cvq", "--max-drop"),
    ("compress-bpp-and-bits", "compress {run} --bpp 8 --bits 6 --out new.cvq", "--bits"),
    ("compress-bpp-and-max-bytes", "compress {run} --bpp 8 --max-bytes 900 --out new.cvq", "--max-bytes"),
    ("compress-bpp-and-prune", "compress {run} --bpp 8 --finetune 1 --prune 0.1 --out new.cvq", "--prune"),
    ("encode-no-budget", "encode {image} --depth {depth} --out new.cvq", "--bpp"),
    ("encode-no-out", "encode {image} --depth {depth} --bpp 8", "--out"),
    ("encode-max-drop", f"{ENCODE} --bpp 8 --max-drop 0.1 --out new.cvq", "--max-drop"),
    ("encode-image-and-scene", f"{ENCODE} --scene star --bpp 8 --out new.cvq", "--scene"),
    ("decompress-no-file", "decompress", "FILE"),
    ("decompress-unknown-flag", "decompress {cvq} --bits 8 --out new.safetensors", "--bits"),
    ("bench-preset-nope", f"bench {BENCH} --preset nope", "nope"),
    ("bench-colors-RGB", f"bench {BENCH} --colors RGB", "RGB"),
    ("bench-methods-typo", f"bench {BENCH} --methods cvqgp", "cvqgp"),
    ("bench-scene-names-unknown", "bench --preset star --size 32 24 --steps 2 --quiet --out new_bench "
     "--scene-names nosuchscene", "nosuchscene"),
    ("bench-device-gpu", f"bench {BENCH} --device gpu", "--device"),
    ("bench-backend-cuda", f"bench {BENCH} --backend cuda", "--backend"),
    ("bench-device-cuda-without-gpu", f"bench {BENCH} --device cuda", "cuda"),
    ("bench-seed-and-seeds", f"bench {BENCH} --seed 1 --seeds 2 3", "--seeds"),
    ("bench-jobs-not-whole", f"bench {BENCH} --jobs two", "--jobs"),
    ("bench-fits-outside-rate-distortion", f"bench {BENCH} --fits {{bench}}", "--fits"),
    ("bench-finetune-outside-rate-distortion", f"bench {BENCH} --finetune 5", "--finetune"),
    ("results-unknown-flag", "results --root {records} --out new.md --bogus-flag", "--bogus-flag"),
    ("results-root-without-value", "results --out new.md --root", "--root"),
    ("compile-unknown-flag", "compile --bogus-flag", "--bogus-flag"),
    ("compile-extra-argument", "compile extra_argument", "extra_argument"),
    ("compile-device", "compile --device gpu", "--device"),
    # An empty argument is no path: it would mean the default place, or the current folder.
    ("fit-out-empty", f"fit {FIT} --out ''", "--out is empty"),
    ("fit-resume-empty", "fit --resume '' --quiet", "--resume is empty"),
    ("fit-image-empty", f"fit '' {FIT}", "IMAGE is empty"),
    ("batch-inputs-empty", "batch '' --size 32 24 --steps 1 --quiet --out new_batch", "INPUTS is empty"),
    ("fit-depth-empty", f"fit {{image}} --depth '' {FIT}", "--depth is empty"),
    ("compress-out-empty", "compress {run} --bits 8 --out ''", "--out is empty"),
    ("render-target-empty", "render '' --out new_render", "RUN_DIR|MODEL is empty"),
    ("eval-target-empty", "eval ''", "RUN_DIR is empty"),
    ("view-out-empty", f"view {{run}} --quiet {SWEEP} --out ''", "--out is empty"),
    ("export-out-empty", "export {run} --out ''", "--out is empty"),
    ("decompress-file-empty", "decompress '' --out new.safetensors", "FILE is empty"),
    ("encode-resume-empty", "encode --resume '' --quiet", "--resume is empty"),
    ("results-root-empty-string", "results --root '' --out new.md", "--root is empty"),
    ("bench-out-empty", f"bench {BENCH} --out ''", "--out is empty"),
    ("compress-bits-empty", "compress {run} --bits '' --out new.cvq", "--bits is empty"),
    ("batch-no-out", "batch {scenes} --size 32 24 --steps 1 --quiet", "--out"),
    ("batch-depth", f"{BATCH} --depth {{depth}} --out new_batch", "--depth"),
    ("batch-gpus-per-fit-local", f"{BATCH} --gpus-per-fit 0.5 --out new_batch", "--gpus-per-fit"),
    # A check that can refuse runs before anything is written, and a cluster that does not answer is no wait.
    ("batch-ray-address-nothing-listens", f"{BATCH} --executor ray --ray-address 127.0.0.1:1 --out new_batch",
     "--ray-address 127.0.0.1:1"),
    ("batch-ray-address-unknown-host", f"{BATCH} --executor ray --ray-address nowhere.invalid:6379 --out new_batch",
     "not known"),
    ("batch-ray-address-malformed", f"{BATCH} --executor ray --ray-address 127.0.0.1:port --out new_batch",
     "HOST:PORT"),
    ("bench-ray-address-nothing-listens-with-cells-to-reuse",
     f"bench {BENCH} --ratios 0.1 0.2 --reuse {{bench}} --executor ray --ray-address 127.0.0.1:1",
     "--ray-address 127.0.0.1:1"),
    ("bench-ray-gpus-per-fit-beyond-the-cluster-with-cells-to-reuse",
     f"bench {BENCH} --ratios 0.1 0.2 --reuse {{bench}} --executor ray --gpus-per-fit 1e9", "--gpus-per-fit", SLOW),
    ("batch-ray-gpus-per-fit-beyond-the-cluster", f"{BATCH} --executor ray --gpus-per-fit 1e9 --out new_batch",
     "--gpus-per-fit", SLOW),
    ("batch-ray-gpus-per-fit-without-a-gpu", f"{BATCH} --executor ray --gpus-per-fit 0.5 --out new_batch",
     "--gpus-per-fit", SLOW),
)

# ---------------------------------------------------------------------------------------------------------------
# Missing, wrong, corrupt or mismatched inputs.
INPUTS = cases(
    "inputs",
    ("fit-image-missing", f"fit missing.png --planes 1 {FIT}", "no such file"),
    ("fit-image-is-a-folder", f"fit {{folder}} --planes 1 {FIT}", "folder"),
    ("fit-image-is-text", f"fit {{text}} --planes 1 {FIT}", "notes.txt"),
    ("fit-image-png-of-text", f"fit {{textpng}} --planes 1 {FIT}", "not an image file"),
    ("fit-image-corrupt-png", f"fit {{cut}} --planes 1 {FIT}", "corrupt or truncated"),
    ("fit-image-empty-file", f"fit {{empty}} --planes 1 {FIT}", "empty.png"),
    ("fit-depth-missing", f"fit {{image}} --depth nodepth.png {FIT}", "nodepth.png"),
    ("fit-depth-is-a-folder", f"fit {{image}} --depth {{folder}} {FIT}", "is a folder"),
    ("fit-depth-is-text", f"fit {{image}} --depth {{text}} {FIT}", "notes.txt"),
    ("fit-depth-corrupt", f"fit {{image}} --depth {{cut}} {FIT}", "cut.png"),
    ("fit-depth-with-nan", f"fit {{image}} --depth {{nandepth}} {FIT}", "nan_depth.tiff"),
    ("fit-depth-other-aspect", f"fit {{image}} --depth {{square}} {FIT}", "--resize-depth"),
    ("fit-depth-constant", f"fit {{image}} --depth {{flat}} {FIT}", "constant"),
    ("fit-more-planes-than-depth-separates", f"fit {{image}} --depth {{binary}} --planes 5 {FIT}", "separates only"),
    ("fit-depth-with-scene", f"fit --scene demo --depth {{depth}} {FIT}", "--depth applies to an IMAGE"),
    ("fit-image-and-scene", f"fit {{image}} --scene star {FIT}", "--scene"),
    ("fit-two-planes-without-depth", f"fit {{image}} --planes 2 {FIT}", "--planes"),
    ("fit-default-planes-without-depth", f"fit {{image}} {FIT}", "needs a depth map"),
    ("fit-resume-not-a-run", "fit --resume {notarun} --quiet", "notarun"),
    ("fit-resume-missing", "fit --resume missing_run --quiet", "missing_run"),
    ("fit-resume-a-file", "fit --resume {image} --quiet", "photo.png"),
    ("fit-resume-a-cuda-run-without-a-gpu", "fit --resume {gpurun} --quiet", "no CUDA GPU"),
    ("fit-resume-a-cuda-checkpoint", "fit --resume {gpucheckpoint} --quiet", "written on cuda"),
    ("eval-run-missing", "eval missing_run", "missing_run"),
    ("eval-not-a-run", "eval {notarun}", "notarun"),
    ("eval-run-without-model", "eval {unfinished}", "unfinished"),
    ("eval-model-outside-its-run", "eval {loose}", "loose"),
    ("eval-corrupt-cvq", "eval {badcvq}", "bad.cvq"),
    ("eval-model-of-another-run", "eval {mixed}/foreign.safetensors", "foreign.safetensors"),
    ("eval-model-of-a-twin-run", "eval {twin}/foreign.safetensors", "was fitted in another run"),
    ("eval-run-holding-a-twin-run-model", "eval {twin}", "was fitted in another run"),
    ("render-run-holding-a-twin-run-model", "render {twin} --out new_render", "was fitted in another run"),
    ("export-model-of-a-twin-run", "export {twin}/foreign.safetensors --out new_export", "was fitted in another run"),
    ("eval-damaged-model", "eval {damaged}", "not a readable safetensors file"),
    ("eval-model-a-folder", "eval {modelfolder}", "is a folder, not the run's model file"),
    ("render-model-a-folder", "render {modelfolder}/model.safetensors --out new_render", "is a folder"),
    ("eval-finished-run-without-its-model", "eval {modelless}", "finished run whose model.safetensors is gone"),
    ("eval-model-of-format-0", "eval {oldformat}", "format version"),
    ("eval-model-missing-a-tensor", "eval {lacking}", "missing tensors curvature_per_m"),
    ("eval-model-of-another-shape", "eval {misshapen}", "has shape"),
    ("eval-text-file", "eval {text}", "notes.txt"),
    ("eval-config-as-model", "eval {run}/config.json", "config.json"),
    ("export-run-missing", "export missing_run --out new_export", "not a run folder"),
    ("export-not-a-run", "export {notarun} --out new_export", "notarun"),
    ("export-run-without-model", "export {unfinished} --out new_export", "unfinished"),
    ("export-model-outside-its-run", "export {loose} --out new_export", "loose"),
    ("export-corrupt-cvq", "export {badcvq} --out new_export", "bad.cvq"),
    ("export-damaged-model", "export {damaged} --out new_export", "model.safetensors"),
    ("export-model-of-another-run", "export {mixed}/foreign.safetensors --out new_export", "foreign.safetensors"),
    ("info-missing", "info missing_run", "no such"),
    ("info-not-a-run", "info {notarun}", "notarun"),
    ("info-run-without-model", "info {unfinished}", "unfinished"),
    ("info-text-file", "info {text}", "notes.txt"),
    ("info-empty-file", "info {empty}", "empty.png"),
    ("info-corrupt-cvq", "info {badcvq}", "bad.cvq"),
    ("info-damaged-model", "info {damaged}", "model.safetensors"),
    ("info-half-of-a-loose-model", "info {loose} --half", "loose"),
    ("info-half-of-a-cvq", "info {cvq} --half", "--half"),
    ("render-missing", "render missing_run --out new_render", "missing_run"),
    ("render-not-a-run", "render {notarun} --out new_render", "notarun"),
    ("render-run-without-model", "render {unfinished} --out new_render", "unfinished"),
    ("render-text-file", "render {text} --out new_render", "notes.txt"),
    ("render-corrupt-cvq", "render {badcvq} --out new_render", "bad.cvq"),
    ("render-damaged-model", "render {damaged} --out new_render", "model.safetensors"),
    ("view-run-missing", "view missing_run --quiet --distances 0.001 0.002 2 --out new.html", "missing_run"),
    ("view-not-a-run", "view {notarun} --quiet --distances 0.001 0.002 2 --out new.html",
     "is not a run folder (no config.json)"),
    ("view-run-without-model", "view {unfinished} --quiet --distances 0.001 0.002 2 --out new.html", "unfinished"),
    ("view-damaged-model", "view {damaged} --quiet --distances 0.001 0.002 2 --out new.html", "model.safetensors"),
    ("view-runs-of-different-sizes", "view {run} {run2} --quiet --distances 0.001 0.002 2 --out new.html", "run_b"),
    ("view-three-runs", "view {run} {run} {run} --quiet --distances 0.001 0.002 2 --out new.html",
     "3 run folders: give one or two"),
    # the page's frames are computed before the run's records are read
    ("view-cut-target", "view {cuttarget} --quiet --distances 0.001 0.005 2 --out new.html",
     "delete it to view the run without the PSNR at its plane", SLOW),
    ("view-cut-metrics", f"view {{cutmetrics}} --quiet {SWEEP} --out new.html",
     "delete it, then `cvqpg eval` on the run writes it again", SLOW),
    ("view-cut-export-metrics", f"view {{cutexport}} --quiet {SWEEP} --out new.html",
     "run `cvqpg export` on the run again", SLOW),
    ("view-cut-display", f"view {{cutdisplay}} --quiet {SWEEP} --out new.html", "run `cvqpg export` on the run again",
     SLOW),
    ("compress-missing", "compress missing_run --out new.cvq", "missing_run"),
    ("compress-not-a-run", "compress {notarun} --out new.cvq", "notarun"),
    ("compress-run-without-model", "compress {unfinished} --out new.cvq", "unfinished"),
    ("compress-a-cvq", "compress {cvq} --out new.cvq", "model.cvq"),
    ("compress-damaged-model", "compress {damaged} --out new.cvq", "model.safetensors"),
    ("compress-text-file", "compress {text} --out new.cvq", "notes.txt"),
    ("compress-empty-file", "compress {empty} --out new.cvq", "empty.png"),
    ("compress-finetune-of-a-loose-model", "compress {loose} --finetune 2 --out new.cvq", "--finetune"),
    ("decompress-a-safetensors", "decompress {model} --out new.safetensors", "model.safetensors"),
    ("decompress-missing", "decompress missing.cvq --out new.safetensors", "missing.cvq"),
    ("decompress-corrupt", "decompress {brokencvq} --out new.safetensors", "broken.cvq"),
    ("decompress-empty", "decompress {emptycvq} --out new.safetensors", "empty.cvq"),
    ("decompress-text-file", "decompress {text} --out new.safetensors", "notes.txt"),
    ("decompress-a-folder", "decompress {folder} --out new.safetensors", "folder"),
    ("bench-scenes-missing", f"bench {BENCH} --scenes missing_scenes", "missing_scenes"),
    ("bench-scenes-a-file", f"bench {BENCH} --scenes {{text}}", "notes.txt"),
    ("bench-scenes-empty-folder", f"bench {BENCH} --scenes {{folder}}", "folder"),
    ("bench-scenes-needed", "bench --preset paper --size 32 24 --steps 2 --quiet --out new_bench", "--scenes"),
    ("bench-fits-not-a-bench", "bench --preset compression --scenes {scenes} --fits {notarun} --size 32 24 --steps 2 "
     "--quiet --out new_bench", "notarun"),
    ("bench-reuse-missing", f"bench {BENCH} --reuse missing_bench", "missing_bench"),
    ("bench-summary-of-nothing", "bench --preset star --summary-only --quiet --out missing_bench", "missing_bench"),
    ("results-root-missing", "results --root missing_root --out new.md", "missing_root"),
    ("results-root-a-file", "results --root {text} --out new.md", "notes.txt"),
    ("results-cell-of-other-settings", "results --root {badrecords} --out new.md", "badrecords"),
    ("results-root-empty", "results --root {folder} --out new.md", "nothing to summarise"),
    ("results-root-of-other-files", "results --root {notarun} --out new.md", "nothing to summarise"),
    ("batch-inputs-missing", "batch missing_scenes --size 32 24 --steps 1 --quiet --out new_batch",
     "missing_scenes"),
    ("batch-inputs-empty-folder", "batch {folder} --size 32 24 --steps 1 --quiet --out new_batch", "folder"),
    ("batch-manifest-of-text", "batch {text} --size 32 24 --steps 1 --quiet --out new_batch", "unknown column"),
    # Names are checked where the items are read: their length with what the batch adds, their characters.
    ("batch-name-of-240-bytes", "batch {longname} --size 32 24 --steps 1 --quiet --planes 1 --out new_batch",
     "240 bytes long"),
    ("batch-name-with-a-nul", "batch {nulname} --size 32 24 --steps 1 --quiet --planes 1 --out new_batch",
     "control character (U+0000)"),
    ("batch-name-with-a-tab", "batch {tabname} --size 32 24 --steps 1 --quiet --planes 1 --out new_batch",
     "control character (U+0009)"),
    ("batch-manifest-column-twice", "batch {twocolumns} --size 32 24 --steps 1 --quiet --planes 1 --out new_batch",
     "named twice"),
    # A .cvq file is exactly what the format says: nothing after its end, a format-5 header with its dictionary.
    ("eval-cvq-with-trailing-bytes", "eval {trailing}", "after its end"),
    ("decompress-cvq-with-trailing-bytes", "decompress {trailing} --out new.safetensors", "after its end"),
    ("info-cvq-header-without-its-dictionary", "info {nodict}", "preset dictionary"),
    # Numbers no measured table holds, records that cvqpg never writes.
    ("fit-lut-of-phases-beyond-two-turns", f"fit {{image}} --depth {{depth}} --display phase --lut {{hugelut}} {FIT}",
     "lies beyond ±4π"),
    ("export-lut-in-degrees", "export {run} --lut {degreelut} --out new_export", "give them in rad (not degrees)"),
    ("encode-resume-a-budget-beyond-the-floats", "encode --resume {infbudget} --quiet",
     "lacks the budget or the fine-tuning steps"),
    ("encode-resume-tuning-steps-not-whole", "encode --resume {floatsteps} --quiet", "lacks the budget"),
    ("view-metrics-not-what-cvqpg-writes", f"view {{badmetrics}} --quiet {SWEEP} --out new.html",
     "its 'mean' is not what cvqpg writes there"),
    ("bench-reuse-a-cell-whose-record-the-summary-refuses", f"bench {BENCH} --reuse {{benchbadrecord}}",
     "metrics.json lacks mean.psnr"),
    # An input's path longer than the file system takes, refused before it is looked up.
    ("fit-image-name-of-300-bytes", f"fit {'n' * 300}.png --planes 1 {FIT}", "IMAGE nnnn"),
    ("fit-lut-name-of-300-bytes", f"fit {{image}} --depth {{depth}} --display phase --lut {'n' * 300} {FIT}",
     "a name longer than the file system takes (255 bytes); give a shorter path"),
    ("eval-run-name-of-300-bytes", f"eval {'n' * 300}", "RUN_DIR nnnn"),
    ("decompress-file-path-of-5000-bytes", f"decompress {'/'.join(['n' * 200] * 25)} --out new.safetensors",
     "a path longer than the file system takes"),
    ("batch-inputs-name-of-300-bytes", f"batch {'n' * 300} --size 32 24 --steps 1 --quiet --out new_batch",
     "INPUTS nnnn"),
    ("bench-reuse-name-of-300-bytes", f"bench {BENCH} --reuse {'n' * 300}", "--reuse nnnn"),
    ("results-root-name-of-300-bytes", f"results --root {'n' * 300} --out new.md", "--root nnnn"),
)

# ---------------------------------------------------------------------------------------------------------------
# Outputs that cannot be written, or would write over something that existed.
OUTPUTS = cases(
    "outputs",
    ("fit-out-existing-run", "fit --size 32 24 --steps 2 --quiet --out {run}", "--overwrite"),
    ("fit-out-existing-file", "fit --size 32 24 --steps 2 --quiet --out {text}", "notes.txt"),
    ("fit-out-existing-folder", "fit --size 32 24 --steps 2 --quiet --out {notarun}", "notarun"),
    ("fit-out-under-a-file", "fit --size 32 24 --steps 2 --quiet --out {image}/run", "photo.png"),
    ("fit-out-under-a-model-file", "fit --size 32 24 --steps 2 --quiet --out {model}/run", "model.safetensors"),
    ("fit-out-unwritable", "fit --size 32 24 --steps 2 --quiet --out /proc/cvqpg-hostile-run",
     "/proc/cvqpg-hostile-run"),
    ("fit-out-readonly-folder", "fit --size 32 24 --steps 2 --quiet --out {readonly}/run", "readonly", PERMISSIONS),
    ("fit-bad-option-with-overwrite", "fit --size 32 24 --steps 0 --quiet --out {run} --overwrite", "--steps"),
    ("fit-failure-creates-no-parents", "fit --size 32 24 --steps 0 --quiet --out new_parent/deeper/run", "--steps"),
    ("export-out-the-run-itself", "export {run} --out {run}", "run_a"),
    ("export-out-the-run-itself-with-overwrite", "export {run} --out {run} --overwrite", "run_a"),
    ("export-default-out-exists", "export {run}", "overwrite"),
    ("export-out-existing-folder", "export {run} --out {notarun}", "overwrite"),
    ("export-out-a-file", "export {run} --out {text}", "notes.txt"),
    ("export-out-under-a-file", "export {run} --out {image}/export", "photo.png"),
    ("export-out-unwritable", "export {run} --out /proc/cvqpg-hostile-export", "/proc/cvqpg-hostile-export"),
    ("export-out-readonly-folder", "export {run} --out {readonly}/export", "readonly", PERMISSIONS),
    ("render-out-the-run-itself", "render {run} --out {run}", "run_a"),
    ("render-default-out-exists", "render {run}", "overwrite"),
    ("render-out-existing-folder", "render {run} --out {notarun}", "overwrite"),
    ("render-out-a-file", "render {run} --out {text}", "notes.txt"),
    ("render-out-under-a-file", "render {run} --out {image}/render", "photo.png"),
    ("render-out-unwritable", "render {run} --out /proc/cvqpg-hostile-render", "/proc/cvqpg-hostile-render"),
    ("view-out-its-own-run", f"view {{run}} --quiet {SWEEP} --out {{run}}", "is this command's own input"),
    ("view-out-another-run", f"view {{run}} --quiet {SWEEP} --out {{run2}}",
     "is a run folder; choose a path outside it"),
    ("view-out-a-plain-folder", f"view {{run}} --quiet {SWEEP} --out {{folder}}", "is a folder; give a file name"),
    ("view-out-existing-page", f"view {{run}} --quiet {SWEEP} --out {{page}}", "overwrite"),
    ("view-out-run-config", f"view {{run}} --quiet {SWEEP} --out {{run}}/config.json --overwrite", "config.json"),
    ("view-out-run-metrics", f"view {{run}} --quiet {SWEEP} --out {{run}}/metrics.json --overwrite", "metrics.json"),
    ("view-out-under-a-file", f"view {{run}} --quiet {SWEEP} --out {{image}}/page.html", "photo.png"),
    ("view-out-parent-missing", f"view {{run}} --quiet {SWEEP} --out nodir/page.html", "nodir"),
    ("info-half-exists", "info {run} --half", "overwrite"),
    ("compress-out-the-model", "compress {run} --bits 8 --out {model}", "model.safetensors"),
    ("compress-out-the-model-with-overwrite", "compress {run} --bits 8 --out {model} --overwrite",
     "model.safetensors"),
    ("compress-out-own-input-absolute", "compress {loose} --bits 8 --out {tmp}/loose/model.safetensors --overwrite",
     "model.safetensors"),
    ("compress-out-metrics", "compress {run} --bits 8 --out {run}/metrics.json --overwrite", "metrics.json"),
    ("compress-out-config", "compress {run} --bits 8 --out {run}/config.json --overwrite", "config.json"),
    ("compress-out-a-folder", "compress {run} --bits 8 --out {run}", "run_a"),
    ("compress-default-out-exists", "compress {run} --bits 8", "overwrite"),
    ("compress-out-existing-file", "compress {run} --bits 8 --out {text}", "overwrite"),
    ("compress-out-parent-missing", "compress {run} --bits 8 --out nodir/deeper/out.cvq", "nodir"),
    ("compress-out-under-a-file", "compress {run} --bits 8 --out {image}/out.cvq", "photo.png"),
    ("compress-out-unwritable", "compress {run} --bits 8 --out /proc/cvqpg-hostile.cvq", "/proc/cvqpg-hostile.cvq"),
    ("compress-out-readonly-folder", "compress {run} --bits 8 --out {readonly}/out.cvq", "readonly", PERMISSIONS),
    ("compress-bpp-out-the-model", "compress {run} --bpp 8 --out {model} --overwrite", "model.safetensors"),
    ("encode-out-the-image", f"{ENCODE} --bpp 8 --out {{image}} --overwrite", "photo.png"),
    ("encode-out-the-depth-map", f"{ENCODE} --bpp 8 --out {{depth}} --overwrite", "depth.png"),
    ("encode-out-existing-file", f"{ENCODE} --bpp 8 --out {{text}}", "overwrite"),
    ("encode-out-a-folder", f"{ENCODE} --bpp 8 --out {{folder}}", "folder"),
    ("encode-out-run-model", f"{ENCODE} --bpp 8 --out {{model}} --overwrite", "model.safetensors"),
    ("decompress-out-own-input", "decompress {cvq} --out {cvq}", "model.cvq"),
    ("decompress-out-own-input-with-overwrite", "decompress {cvq} --out {cvq} --overwrite", "model.cvq"),
    ("decompress-out-the-run-model", "decompress {cvq} --out {model} --overwrite", "model.safetensors"),
    ("decompress-out-run-config", "decompress {cvq} --out {run}/config.json --overwrite", "config.json"),
    ("decompress-default-out-exists", "decompress {cvq}", "overwrite"),
    ("decompress-out-existing-file", "decompress {cvq} --out {text}", "overwrite"),
    ("decompress-out-a-folder", "decompress {cvq} --out {folder}", "folder"),
    ("decompress-out-parent-missing", "decompress {cvq} --out nodir/model.safetensors", "nodir"),
    ("decompress-out-unwritable", "decompress {cvq} --out /proc/cvqpg-hostile.safetensors",
     "/proc/cvqpg-hostile.safetensors"),
    ("bench-out-a-file", f"bench {BENCH} --out {{text}}", "notes.txt"),
    ("bench-out-under-a-file", f"bench {BENCH} --out {{image}}/bench", "photo.png"),
    ("bench-out-a-run-folder", f"bench {BENCH} --out {{run}}", "run_a"),
    ("bench-out-unwritable", f"bench {BENCH} --out /proc/cvqpg-hostile-bench", "/proc/cvqpg-hostile-bench"),
    ("results-out-existing-file", "results --root {records} --out {text}", "overwrite"),
    ("results-default-out-exists", "results --root {records}", "overwrite"),
    ("results-out-under-a-file", "results --root {records} --out {image}/results.md", "photo.png"),
    ("results-out-parent-missing", "results --root {records} --out nodir/results.md", "nodir"),
    ("results-out-a-folder", "results --root {records} --out {folder}", "folder"),
    ("results-out-run-config", "results --root {records} --out {run}/config.json --overwrite", "config.json"),
    ("results-out-unwritable", "results --root {records} --out /proc/cvqpg-hostile.md", "/proc/cvqpg-hostile.md"),
    ("results-out-readonly-folder", "results --root {records} --out {readonly}/results.md", "readonly", PERMISSIONS),
    # --overwrite replaces only the command's own kind of output.
    ("render-overwrite-a-users-folder", "render {run} --out {notarun} --overwrite", "notarun"),
    ("batch-out-a-users-folder", f"{BATCH} --out {{notarun}} --overwrite", "notarun"),
    ("batch-out-a-bench-folder", f"{BATCH} --out {{bench}} --overwrite", "not a batch folder"),
    ("batch-out-a-run-folder", f"{BATCH} --out {{run}}", "run_a"),
    ("batch-out-a-file", f"{BATCH} --out {{text}}", "notes.txt"),
    ("batch-out-the-inputs", f"{BATCH} --out {{scenes}}", "scenes"),
    ("batch-out-unwritable", f"{BATCH} --out /proc/cvqpg-hostile-batch", "/proc/cvqpg-hostile-batch"),
    # A batch owns only what its records say it made, writes through no link, and checks each path's kind first.
    ("batch-a-users-run-at-a-finished-items-output", f"{BATCH} --out {{bforeign}}", "not a run folder this batch"),
    ("batch-overwrite-a-users-run-at-an-items-output", f"{BATCH} --out {{bforeign}} --overwrite",
     "not a run folder this batch"),
    ("batch-a-users-run-where-an-item-failed", f"{BATCH} --out {{bfailed}}", "not a run folder this batch"),
    ("batch-a-users-file-at-an-items-cvq", f"{BATCH} --bpp 8 --out {{bcvq}}", "not a .cvq file this batch"),
    ("batch-overwrite-a-users-file-at-an-items-cvq", f"{BATCH} --bpp 8 --out {{bcvq}} --overwrite",
     "not a .cvq file this batch"),
    ("batch-an-items-work-a-link", f"{BATCH} --out {{blink}}", "tiny.partial is a symbolic link"),
    ("batch-a-cvq-items-work-a-link", f"{BATCH} --bpp 8 --out {{blink}}", "tiny.cvq.partial is a symbolic link"),
    ("batch-an-items-work-a-users-folder", f"{BATCH} --out {{bwork}}", "not an unfinished fit's"),
    ("batch-records-a-file", f"{BATCH} --out {{bdotbatch}}", ".batch is a file"),
    ("batch-summary-a-folder", f"{BATCH} --out {{bsummary}} --overwrite", "summary.csv is a folder"),
    ("batch-summary-lock-a-folder", f"{BATCH} --out {{block}} --overwrite", "summary.lock is a folder"),
    ("batch-error-log-a-folder", f"{BATCH} --out {{blog}} --overwrite", "tiny.error.log is a folder"),
    ("batch-record-a-folder", f"{BATCH} --out {{brecord}} --overwrite", "tiny.json is a folder"),
    ("compress-lock-a-folder", "compress {run} --bits 8 --out {lockdir}", "is a folder, not a regular file"),
    ("render-overwrite-another-run", "render {run} --out {run2} --overwrite", "run_b"),
    ("render-overwrite-an-export-folder", "render {run} --out {run}/export --overwrite", "export"),
    ("export-overwrite-a-users-folder", "export {run} --out {notarun} --overwrite", "notarun"),
    ("export-overwrite-another-run", "export {run} --out {run2} --overwrite", "run_b"),
    ("export-overwrite-a-render-folder", "export {run} --out {run}/render --overwrite", "render"),
    ("fit-overwrite-a-users-folder", "fit --size 32 24 --steps 2 --quiet --out {notarun} --overwrite", "notarun"),
    ("view-overwrite-a-runs-target", f"view {{run}} --quiet {SWEEP} --out {{run2}}/target_plane0.png --overwrite",
     "target_plane0.png"),
    ("view-overwrite-a-runs-curve", f"view {{run}} --quiet {SWEEP} --out {{run}}/curve.png --overwrite", "curve.png"),
    ("view-overwrite-a-users-file", f"view {{run}} --quiet {SWEEP} --out {{text}} --overwrite", "notes.txt"),
    ("compress-overwrite-a-runs-target", "compress {run} --bits 8 --out {run}/target_plane0.png --overwrite",
     "target_plane0.png"),
    ("compress-overwrite-a-users-file", "compress {run} --bits 8 --out {text} --overwrite", "notes.txt"),
    ("compress-overwrite-an-image", "compress {run} --bits 8 --out {image} --overwrite", "photo.png"),
    ("compress-overwrite-a-page", "compress {run} --bits 8 --out {page} --overwrite", "page.html"),
    ("decompress-overwrite-a-users-file", "decompress {cvq} --out {text} --overwrite", "notes.txt"),
    ("decompress-overwrite-a-runs-recon", "decompress {cvq} --out {run2}/recon_plane0.png --overwrite",
     "recon_plane0.png"),
    ("encode-overwrite-a-users-file", f"{ENCODE} --bpp 8 --out {{text}} --overwrite", "notes.txt"),
    ("results-overwrite-a-users-file", "results --root {records} --out {text} --overwrite", "notes.txt"),
    ("results-overwrite-a-page", "results --root {records} --out {page} --overwrite", "page.html"),
    ("bench-out-a-users-folder", f"bench {BENCH} --out {{notarun}}", "notarun"),
    # A symbolic link is never followed to a place the user did not name.
    ("render-out-a-link-to-a-users-folder", "render {run} --out {linkdir} --overwrite", "linkdir"),
    ("render-out-a-link-to-a-render-folder", "render {run} --out {linkrender} --overwrite", "linkrender"),
    ("export-out-a-link-to-a-users-folder", "export {run} --out {linkdir} --overwrite", "linkdir"),
    ("fit-out-a-link-to-a-run", "fit --size 32 24 --steps 2 --quiet --out {linkrun} --overwrite", "linkrun"),
    ("compress-out-a-link-to-a-cvq", "compress {run} --bits 8 --out {linkcvq} --overwrite", "linkcvq.cvq"),
    ("view-out-a-link-to-a-page", f"view {{run}} --quiet {SWEEP} --out {{linkpage}} --overwrite", "linkpage.html"),
    ("decompress-out-a-dangling-link", "decompress {cvq} --out {dangling}", "dangling.safetensors"),
    ("bench-out-a-link", f"bench {BENCH} --out {{linkdir}}", "linkdir"),
    # The current folder, or one that holds it, is no output.
    ("render-out-the-current-folder", "render {run} --out . --overwrite", "current folder"),
    ("export-out-a-folder-holding-the-current-one", "export {run} --out {run}/.. --overwrite", "current folder"),
    ("fit-out-the-current-folder", "fit --size 32 24 --steps 2 --quiet --out . --overwrite", "current folder"),
    # A resume whose place is taken stops, naming it, and keeps the interrupted folder.
    ("fit-resume-into-a-users-folder", "fit --resume {held}.partial --quiet", "held"),
    ("fit-resume-into-a-users-folder-with-overwrite", "fit --resume {held}.partial --quiet --overwrite", "held"),
    ("fit-resume-into-a-file", "fit --resume {filed}.partial --quiet --overwrite", "filed"),
    ("fit-resume-into-a-link", "fit --resume {linked}.partial --quiet --overwrite", "linked"),
    ("fit-resume-an-encode", "fit --resume {encoded} --quiet", "encode"),
    ("fit-out-beside-a-finished-fit-never-moved", "fit --size 32 24 --steps 1 --quiet --out {stranded}",
     "never moved into place; rename it to stranded"),
    ("fit-out-beside-a-file-where-its-work-goes", "fit --size 32 24 --steps 1 --quiet --out {filedwork}",
     "filed_work.partial is in the way"),
    ("encode-resume-into-a-users-file", "encode --resume {foreigncvq}.partial --quiet --overwrite", "foreign.cvq"),
    ("encode-resume-a-changed-budget", "encode --resume {tampered} --quiet", "the budget of 1 bytes in"),
    ("encode-work-a-dangling-link", f"{ENCODE} --bpp 8 --out {{danglingwork}}",
     "is in the way of the encode's work folder (not a folder)"),
    ("eval-metrics-a-folder", "eval {metricsfolder}", "is a folder, where `cvqpg eval` writes a file"),
    ("bench-a-cells-folder-a-link", f"bench {BENCH} --out {{benchlink}}", "is a symbolic link, which the bench"),
    ("bench-its-cells-a-link", f"bench {BENCH} --out {{cellslink}}", "cells_link/cells is a symbolic link"),
    ("bench-a-cells-record-a-folder", f"bench {BENCH} --out {{benchrecord}}", "metrics.json is a folder"),
    # A path through a loop of symbolic links is no place to write.
    ("fit-out-through-a-loop-of-links", f"fit {FIT} --out {{loop}}/run", "lies through a loop of symbolic links"),
    ("compress-out-through-a-loop-of-links", "compress {run} --bits 8 --out {loop}/new.cvq", "a loop of symbolic"),
    ("batch-out-through-a-loop-of-links", f"{BATCH} --out {{loop}}/new_batch", "a loop of symbolic links"),
    ("bench-out-through-a-loop-of-links", f"bench {BENCH} --out {{loop}}/new_bench", "a loop of symbolic links"),
    ("eval-metrics-a-link", "eval {metricslink}", "is a symbolic link, which `cvqpg eval` does not write through"),
    # A failure writes nothing.
    ("info-half-of-a-run-whose-image-is-gone", "info {lost} --half", "lost_photo.png"),
    # Names and paths longer than the file system takes, with what cvqpg keeps beside an output.
    ("fit-out-name-of-250-bytes", f"fit {FIT} --out {'n' * 250}", "a name longer than the file system takes"),
    ("fit-out-name-of-300-bytes", f"fit {FIT} --out {'n' * 300}", "a name longer than the file system takes"),
    ("fit-out-folder-name-of-300-bytes", f"fit {FIT} --out {'n' * 300}/run", "a name longer than"),
    ("fit-out-path-of-5000-bytes", f"fit {FIT} --out {'/'.join(['n' * 200] * 25)}", "a path longer than"),
    ("render-out-name-of-250-bytes", f"render {{run}} --out {'n' * 250}", "a name longer than"),
    ("export-out-name-of-300-bytes", f"export {{run}} --out {'n' * 300}", "a name longer than"),
    ("compress-out-name-of-246-bytes", f"compress {{run}} --bits 8 --out {'n' * 246}.cvq", "a name longer than"),
    ("decompress-out-name-of-300-bytes", f"decompress {{cvq}} --out {'n' * 300}", "a name longer than"),
    ("view-out-name-of-250-bytes", f"view {{run}} --quiet {SWEEP} --out {'n' * 245}.html", "a name longer than"),
    ("encode-out-name-of-250-bytes", f"{ENCODE} --bpp 8 --out {'n' * 246}.cvq", "a name longer than"),
    ("results-out-name-of-250-bytes", f"results --root {{records}} --out {'n' * 247}.md", "a name longer than"),
    ("bench-out-name-of-300-bytes", f"bench {BENCH} --out {'n' * 300}", "a name longer than"),
    # A file's name that ends in a slash names a folder.
    ("view-out-ending-in-a-slash", f"view {{run}} --quiet {SWEEP} --out page/", "names a folder"),
    ("compress-out-ending-in-a-slash", "compress {run} --bits 8 --out new.cvq/", "names a folder"),
    ("decompress-out-ending-in-a-slash", "decompress {cvq} --out new.safetensors/", "names a folder"),
    ("results-out-ending-in-a-slash", "results --root {records} --out new.md/", "names a folder"),
)

CASES = NUMBERS + USAGE + INPUTS + OUTPUTS


# ---------------------------------------------------------------------------------------------------------------
# Helpers.

def cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """`main(argv)` as the console script runs it: argparse's exit is an exit code too."""
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else 1
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def tree_state(root: Path) -> dict[str, tuple[int, object]]:
    """Every path under `root` (not following links): its mode, and for a file its size and modification time (any
    write changes it), for a link its target. Strings, not `Path`s: it runs before and after every case."""
    state = {}
    start = len(str(root)) + 1
    for folder, folders, files in os.walk(root):
        for name in folders + files:
            path = os.path.join(folder, name)
            info = os.lstat(path)
            if stat.S_ISREG(info.st_mode):
                content = (info.st_size, info.st_mtime_ns)
            elif stat.S_ISLNK(info.st_mode):
                content = "-> " + os.readlink(path)
            else:
                content = None
            state[path[start:]] = (info.st_mode, content)
    return state


def tree_changes(before: dict, after: dict) -> list[str]:
    return ([f"created {p}" for p in sorted(after.keys() - before.keys())]
            + [f"removed {p}" for p in sorted(before.keys() - after.keys())]
            + [f"changed {p}" for p in sorted(before.keys() & after.keys()) if before[p] != after[p]])


def expand(argv: str, work: Path) -> list[str]:
    return [token.format(tmp=work, **PLACES) for token in shlex.split(argv)]


def command_of(argv: list[str]) -> str:
    return argv[0] if argv else ""


def flip_bytes(data: bytes) -> bytes:
    """Damage in the middle of a file: every byte of its middle third inverted."""
    start, stop = len(data) // 3, 2 * len(data) // 3
    return data[:start] + bytes(b ^ 0xFF for b in data[start:stop]) + data[stop:]


# ---------------------------------------------------------------------------------------------------------------
# The template: tiny assets, made once through the command line.

def truncated(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:path.stat().st_size // 2])


def damaged_copies(t: Path, run_a: Path) -> None:
    """Copies of the finished run_a (model.cvq, export/ and the other extras included), each damaged in one way."""
    def copy(name: str) -> Path:
        return Path(shutil.copytree(run_a, t / name))

    for name, damaged in (("cut_target", "target_plane1.png"), ("cut_metrics", "metrics.json"),
                          ("cut_export", "export/metrics.json"), ("cut_display", "export/display_plane0.png")):
        truncated(copy(name) / damaged)
    with safe_open(str(run_a / "model.safetensors"), framework="pt") as handle:
        metadata = handle.metadata()
    tensors = load_file(run_a / "model.safetensors")
    save_file(tensors, str(copy("old_format") / "model.safetensors"), metadata={**metadata, "format_version": "0"})
    save_file({k: v for k, v in tensors.items() if k != "curvature_per_m"}, str(copy("lacking") / "model.safetensors"),
              metadata=metadata)
    save_file({**tensors, "amplitude": tensors["amplitude"][:, :1].contiguous()},
              str(copy("misshapen") / "model.safetensors"), metadata=metadata)
    # Runs to resume (no metrics.json): one recorded on CUDA, one whose checkpoint was written there.
    gpu_run = copy("gpu_run")
    (gpu_run / "metrics.json").unlink()
    recorded = json.loads((run_a / "config.json").read_text())
    (gpu_run / "config.json").write_text(json.dumps({**recorded, "run": {**recorded["run"], "device": "cuda"}}))
    gpu_checkpoint = copy("gpu_checkpoint")
    (gpu_checkpoint / "metrics.json").unlink()
    payload = blank_state(read_run(run_a)[0]).to_payload()
    payload["device"], payload["generator"] = "cuda", torch.zeros(16, dtype=torch.uint8)  # a CUDA generator's state
    save_checkpoint(gpu_checkpoint / "checkpoint.pt", payload)

def output_traps(t: Path) -> None:
    """What an output or a resume must not destroy: a user's folder and file where an interrupted run would
    finish, interrupted encodes, a run whose image is gone, and symbolic links to places the user did not name."""
    (t / "held").mkdir()
    (t / "held" / "thesis.tex").write_text("years of work\n")
    (t / "filed").write_text("a user's file\n")
    for name in ("held", "filed", "linked"):
        (t / f"{name}.partial").mkdir()
        shutil.copy(t / "unfinished" / "config.json", t / f"{name}.partial" / "config.json")
    (t / "linked").symlink_to("notarun")
    for name, max_bytes in (("enc.cvq.partial", 900), ("foreign.cvq.partial", 900), ("tampered.cvq.partial", 1)):
        (t / name).mkdir()
        shutil.copy(t / "unfinished" / "config.json", t / name / "config.json")
        (t / name / "budget.json").write_text(json.dumps({"max_bytes": max_bytes, "given": "--bpp 8",
                                                           "finetune_steps": 1}))
    (t / "foreign.cvq").write_text("a user's notes, named .cvq\n")
    for name in ("model_folder", "modelless"):
        shutil.copytree(t / "run_b", t / name)
        (t / name / "model.safetensors").unlink()
    (t / "model_folder" / "model.safetensors").mkdir()
    shutil.copytree(t / "run_b", t / "stranded.partial")
    (t / "filed_work.partial").write_text("a user's file\n")
    lost_image = shutil.copy(t / "photo.png", t / "lost_photo.png")
    assert main(["fit", str(lost_image), "--depth", str(t / "depth.png"), "--size", "32", "24", "--num-gaussians", "20",
                 "--steps", "1", "--quiet", "--out", str(t / "lost")]) == 0
    Path(lost_image).unlink()
    for link, target in (("linkdir", "notarun"), ("linkrender", "run_a/render"), ("linkrun", "run_b"),
                         ("linkcvq.cvq", "run_a/model.cvq"), ("linkpage.html", "page.html"),
                         ("dangling.safetensors", "nowhere/model.safetensors")):
        (t / link).symlink_to(target)


def codec_traps(t: Path) -> None:
    """`.cvq` files whose checksum holds but whose bytes are not what the format says: bytes after the end, a
    format-5 header deflated without its preset dictionary."""
    data = (t / "run_a" / "model.cvq").read_bytes()
    (t / "run_a" / "trailing.cvq").write_bytes(with_checksum(data[:-4] + b"trailing bytes"))
    _magic, version, length = codec.PREFIX.unpack_from(data)
    start = codec.header_start(version)
    header = zlib.decompressobj(zdict=codec.HEADER_DICTIONARY).decompress(data[start:start + length])
    plain = zlib.compress(header, 9)
    body = codec.PREFIX.pack(codec.MAGIC, version, len(plain)) + data[codec.PREFIX.size:start] + plain \
        + data[start + length:-4]
    (t / "run_a" / "nodict.cvq").write_bytes(with_checksum(body))


def record_traps(t: Path) -> None:
    """Lookup tables whose numbers cannot be a measured table's; run folders and interrupted encodes whose records
    were changed by hand into something cvqpg never writes; a link where an encode's work folder goes; bench
    folders with a link or a folder where the bench writes."""
    (t / "huge_lut.csv").write_text("\n".join(str(1e300 * level) for level in range(256)))
    (t / "degree_lut.csv").write_text("\n".join(str(level * 360 / 256) for level in range(256)))
    (t / "dangling.cvq.partial").symlink_to("nowhere")
    for name in ("metrics_folder", "metrics_link", "bad_metrics"):
        shutil.copytree(t / "run_a", t / name)
        (t / name / "metrics.json").unlink()
    (t / "metrics_folder" / "metrics.json").mkdir()
    (t / "metrics_link" / "metrics.json").symlink_to("../photo.png")
    (t / "bad_metrics" / "metrics.json").write_text(json.dumps({"mean": 5, "per_plane": {}}))
    cell = "cells/star_gray-10_cvqpg_s100"
    for name in ("bench_link", "cells_link", "bench_record", "bench_bad_record"):
        shutil.copytree(t / "bench", t / name)
    (t / "bench_bad_record" / cell / "metrics.json").write_text(json.dumps({"mean": 5}))
    (t / "loop").symlink_to("loop")
    shutil.rmtree(t / "bench_link" / cell)
    (t / "bench_link" / cell).symlink_to("../../notarun")
    shutil.rmtree(t / "cells_link" / "cells")
    (t / "cells_link" / "cells").symlink_to("../notarun")
    (t / "bench_record" / cell / "metrics.json").unlink()
    (t / "bench_record" / cell / "metrics.json").mkdir()
    for name, budget in (("inf_budget.cvq.partial", '{"max_bytes": 1e400, "given": "--bpp 8", "finetune_steps": 1}'),
                         ("float_steps.cvq.partial",
                          '{"max_bytes": 900, "given": "--bpp 8", "finetune_steps": 1e30}')):
        (t / name).mkdir()
        shutil.copy(t / "unfinished" / "config.json", t / name / "config.json")
        (t / name / "budget.json").write_text(budget)


def with_checksum(body: bytes) -> bytes:
    return body + codec.CHECKSUM.pack(zlib.crc32(body))


def batch_traps(t: Path) -> None:
    """A finished batch folder of one item (`tiny`), copied with something in the way of the batch in each copy;
    manifests whose names or columns cannot work; a folder where a lock file goes."""
    batched = t / "b_done"
    assert main(["batch", str(t / "scenes"), "--size", "32", "24", "--steps", "1", "--quiet", "--out",
                 str(batched)]) == 0

    def copy(name: str) -> Path:
        return Path(shutil.copytree(batched, t / name))

    for name in ("b_foreign", "b_failed"):
        shutil.rmtree(copy(name) / "tiny")
        shutil.copytree(t / "run_b", t / name / "tiny")
    record = t / "b_failed" / ".batch" / "tiny.json"
    record.write_text(json.dumps({"name": "tiny", "status": "failed", "output": "tiny", "error": "bad",
                                  "kind": "input"}))
    (copy("b_cvq") / "tiny.cvq").write_text("a user's notes, named .cvq\n")
    link = copy("b_link")
    shutil.rmtree(link / "tiny")
    (link / ".batch" / "tiny.json").unlink()
    for name in ("tiny.partial", "tiny.cvq.partial"):
        (link / name).symlink_to("../notarun")
    work = copy("b_work")
    shutil.rmtree(work / "tiny")
    (work / ".batch" / "tiny.json").unlink()
    (work / "tiny.partial").mkdir()
    (work / "tiny.partial" / "thesis.tex").write_text("years of work\n")
    (t / "b_dot_batch").mkdir()
    (t / "b_dot_batch" / ".batch").write_text("a user's file named .batch\n")
    summary = copy("b_summary") / "summary.csv"
    summary.unlink()
    summary.mkdir()
    lock = copy("b_lock") / ".batch" / "summary.lock"
    lock.unlink(missing_ok=True)
    lock.mkdir()
    (copy("b_log") / "tiny.error.log").mkdir()
    record = copy("b_record") / ".batch" / "tiny.json"
    record.unlink()
    record.mkdir()
    for name, rows in (("long_name.csv", f"photo.png,{'n' * 240}"), ("nul_name.csv", "photo.png,a\x00b"),
                       ("tab_name.csv", "photo.png,a\tb")):
        (t / name).write_text(f"image,name\n{rows}\n")
    (t / "two_columns.csv").write_text("image,image\nphoto.png,notes.png\n")
    (t / ".locked.cvq.cvqpg-lock").mkdir()


class Template(NamedTuple):
    folder: Path
    fresh_run_files: frozenset[str]  # the files of run_a as `cvqpg fit` left it


@pytest.fixture(scope="module")
def template(finished_run, built_once) -> Template:
    """The hostile cases' folder (`build_template`), made once for the session."""
    fresh = frozenset(p.relative_to(finished_run).as_posix() for p in finished_run.rglob("*"))
    return Template(built_once("hostile_template", functools.partial(build_template, finished_run)), fresh)


def build_template(finished_run: Path, t: Path) -> None:
    """In `t`: runs of every kind, damaged copies, every command's outputs, images, scenes, traps."""
    t.mkdir()
    run_a, run_b = t / "run_a", t / "run_b"
    shutil.copytree(finished_run, run_a)
    assert main(["fit", "--size", "48", "36", "--color", "gray", "--planes", "1", "--num-gaussians", "20",
                 "--steps", "2", "--quiet", "--out", str(run_b)]) == 0

    # Copies of run_a, made before its extras: damaged, mixed, unfinished, a loose model.
    shutil.copytree(run_a, t / "damaged")
    (t / "damaged" / "model.safetensors").write_bytes(b"\x00garbage" * 32)
    shutil.copytree(run_a, t / "mixed")
    shutil.copy(run_b / "model.safetensors", t / "mixed" / "foreign.safetensors")
    (t / "unfinished").mkdir()
    shutil.copy(run_a / "config.json", t / "unfinished" / "config.json")
    (t / "loose").mkdir()
    shutil.copy(run_a / "model.safetensors", t / "loose" / "model.safetensors")
    twin = t / "twin_run"
    assert main(["fit", "--size", "32", "24", "--steps", "2", "--seed", "7", "--quiet", "--out", str(twin)]) == 0
    shutil.copytree(run_a, t / "twin")
    for name in ("model.safetensors", "foreign.safetensors"):
        shutil.copy(twin / "model.safetensors", t / "twin" / name)
    shutil.rmtree(twin)
    shutil.copytree(run_a, t / "guarded_run")
    (t / "guarded").mkdir()
    for folder in (t / "guarded_run", t / "guarded"):
        text = (run_a / "config.json").read_text()
        assert '"guard_band_px": 144' in text
        (folder / "config.json").write_text(text.replace('"guard_band_px": 144', '"guard_band_px": 16384'))

    # run_a's extras: every command's default output exists, so that rerunning it needs --overwrite.
    assert main(["compress", str(run_a), "--bits", "8"]) == 0                       # run_a/model.cvq
    assert main(["decompress", str(run_a / "model.cvq")]) == 0                      # run_a/model.decoded.safetensors
    assert main(["export", str(run_a)]) == 0                                        # run_a/export/
    assert main(["render", str(run_a)]) == 0                                        # run_a/render/
    assert main(["info", str(run_a), "--half"]) == 0                                # run_a/model.f16.safetensors
    damaged_copies(t, run_a)
    damaged = flip_bytes((run_a / "model.cvq").read_bytes())
    (run_a / "bad.cvq").write_bytes(damaged)
    (t / "broken.cvq").write_bytes(damaged)
    (t / "empty.cvq").write_bytes(b"")

    assert main(["bench", "--preset", "star", "--size", "32", "24", "--steps", "2", "--scene-names", "star",
                 "--out", str(t / "bench"), "--quiet"]) == 0

    cells = t / "records" / "paper" / "cells"
    cells.mkdir(parents=True)
    shutil.copytree(RECORDED_CELL, cells / RECORDED_CELL.name)
    other = t / "badrecords" / "paper" / "cells" / RECORDED_CELL.name
    other.mkdir(parents=True)
    for name in ("config.json", "metrics.json"):
        shutil.copy(run_a / name, other / name)
    (t / "docs").mkdir()
    (t / "docs" / "results.md").write_text("# Results written before\n")

    rng = np.random.default_rng(7)
    Image.fromarray(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(t / "photo.png")
    ramp = np.tile(np.linspace(0, 255, 32).astype(np.uint8), (24, 1))
    Image.fromarray(ramp).save(t / "depth.png")
    Image.fromarray(ramp[:, :24]).save(t / "square_depth.png")
    Image.new("L", (32, 24), 90).save(t / "flat_depth.png")
    binary = np.zeros((24, 32), np.uint8)
    binary[:, 16:] = 255
    Image.fromarray(binary).save(t / "binary_depth.png")
    values = np.tile(np.linspace(1.0, 4.0, 32, dtype=np.float32), (24, 1))
    values[5:9, 10:20] = np.nan
    Image.fromarray(values, "F").save(t / "nan_depth.tiff")
    png = (t / "photo.png").read_bytes()
    (t / "cut.png").write_bytes(png[: len(png) // 2])
    (t / "empty.png").write_bytes(b"")
    (t / "notes.txt").write_text("not an image, not a model\n")
    (t / "notes.png").write_text("this is text")
    (t / "folder").mkdir()
    (t / "notarun").mkdir()
    (t / "notarun" / "readme.txt").write_text("a folder of someone's files\n")
    (t / "page.html").write_text("<!doctype html><title>a page written before</title>\n")
    (t / "scenes" / "tiny").mkdir(parents=True)
    shutil.copy(t / "photo.png", t / "scenes" / "tiny" / "image.png")
    shutil.copy(t / "depth.png", t / "scenes" / "tiny" / "depth.png")
    (t / "readonly").mkdir()
    (t / "readonly").chmod(0o555)
    output_traps(t)
    codec_traps(t)
    batch_traps(t)
    record_traps(t)


def hostile_environment(monkeypatch, folder: Path) -> None:
    """The current folder `folder`; no GPU visible (nor Triton's interpreter, which runs its kernels on the CPU in
    the tests of them), no traceback requested."""
    monkeypatch.chdir(folder)
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    monkeypatch.delenv("CVQPG_TRACEBACK", raising=False)


class Shared(NamedTuple):
    root: Path  # holds `folder` and nothing else: a case that writes beside it is seen too
    folder: Path
    state: dict  # `tree_state(root)` as the template left it


@pytest.fixture(scope="module")
def shared(template, tmp_path_factory) -> Shared:
    """One copy of the template that every refusal runs in."""
    root = tmp_path_factory.mktemp("shared")
    folder = root / "w"
    shutil.copytree(template.folder, folder, symlinks=True)
    return Shared(root, folder, tree_state(root))


@pytest.fixture
def work(template, tmp_path, monkeypatch) -> Path:
    """A private copy of the template (for commands that succeed), the current folder."""
    folder = tmp_path / "w"
    shutil.copytree(template.folder, folder, symlinks=True)
    hostile_environment(monkeypatch, folder)
    return folder


# ---------------------------------------------------------------------------------------------------------------
# The tests.

def test_every_command_has_hostile_cases_and_every_case_an_id_of_its_own(capsys):
    code, out, _err = cli(["--help"], capsys)
    listed = set(re.search(r"\{([a-z,]+)\}", out).group(1).split(","))
    covered = {case.values[0].argv.split()[0] for case in CASES}
    assert code == 0 and listed - covered == set(), "commands without a hostile case"
    ids = [case.id for case in CASES]
    assert len(ids) == len(set(ids))


# A library parameter's name in backticks (`num_planes`) where the command line should name its flag.
PARAMETER_NAME = re.compile(r"`[a-z]+(?:_[a-z]+)+`")


def refusal_problems(argv: list[str], code: int, err: str, fragment: str, changes: list[str]) -> list[str]:
    """What keeps a command's outcome from being a refusal: exit code 2, one line `cvqpg <command>: error: …` that
    names `fragment` (by flag, not by parameter name), no traceback, and no change to the tree (`changes`)."""
    command = command_of(argv)
    lines = err.splitlines()
    problems = []
    if code != 2:
        problems.append(f"exit code {code}, not 2")
    if len(lines) != 1:
        problems.append(f"{len(lines)} lines on stderr, not 1")
    if "Traceback" in err:
        problems.append("a traceback")
    if not (lines and lines[-1].startswith(f"cvqpg {command}: error: ")):
        problems.append(f"no line starting 'cvqpg {command}: error: '")
    if fragment not in err:
        problems.append(f"{fragment!r} not named")
    if PARAMETER_NAME.search(err):
        problems.append(f"a parameter's name {PARAMETER_NAME.search(err).group()} where its flag belongs")
    if changes:
        problems.append("the tree changed: " + ", ".join(changes[:6]) + (" ..." if len(changes) > 6 else ""))
    return problems


@pytest.mark.parametrize("case", CASES)
def test_hostile_input_is_refused_in_one_line_and_changes_nothing(case: Case, shared, template, monkeypatch, capsys):
    if case.permissions and IS_ROOT:
        pytest.skip("running as root: file permissions do not apply (the /proc cases cover unwritable outputs)")
    hostile_environment(monkeypatch, shared.folder)
    argv = expand(case.argv, shared.folder)
    code, _out, err = cli(argv, capsys)
    changes = tree_changes(shared.state, tree_state(shared.root))
    if changes:  # the next case starts from the template again
        shutil.rmtree(shared.folder)
        shutil.copytree(template.folder, shared.folder, symlinks=True)
    problems = refusal_problems(argv, code, err, case.fragment, changes)
    assert not problems, "; ".join(problems) + f"\n  cvqpg {' '.join(argv)}\n  stderr: {err.strip()[-800:]}"


def test_every_command_that_writes_has_cases_of_outputs_it_must_not_write(capsys):
    """A command with `--overwrite` writes an output: each has rows in the outputs group."""
    _code, out, _err = cli(["--help"], capsys)
    writers = set()
    for command in re.search(r"\{([a-z,]+)\}", out).group(1).split(","):
        _code, help_text, _err = cli([command, "--help"], capsys)
        if "--overwrite" in help_text:
            writers.add(command)
    covered = {case.values[0].argv.split()[0] for case in OUTPUTS}
    assert writers and writers - covered == set()


@pytest.mark.slow
@pytest.mark.parametrize("argv, output, shared", [
    ("compress {run} --bits 6 --overwrite", "run_a/model.cvq", False),
    ("render {run} --overwrite", "run_a/render", False),
    ("decompress {cvq} --overwrite", "run_a/model.decoded.safetensors", False),
    ("fit --size 32 24 --steps 2 --quiet --out {run} --overwrite", "run_a", False),
    (f"view {{run}} --quiet {SWEEP} --out {{page}} --overwrite", "page.html", False),
    # A fit resuming or replacing the run holds it: nothing is written into it meanwhile.
    ("eval {run}", "run_a", False),
    ("eval {cvq}", "run_a", False),
    ("export {run} --overwrite", "run_a", False),
    ("info {run} --half --overwrite", "run_a", False),
    ("compress {run} --bits 6 --overwrite", "run_a", False),
    # Another eval rewrites the run's metrics; another command writes into the run (a shared hold).
    ("eval {run}", "run_a/metrics.json", False),
    ("fit --size 32 24 --steps 2 --quiet --out {run} --overwrite", "run_a", True),
    ("fit --resume {unfinished} --quiet", "unfinished", True),
])
def test_a_second_writer_of_one_output_is_refused_in_one_line(argv, output, shared, work, tmp_path, capsys):
    """Another command holds the output (its lock, as `claimed` takes it): this one stops, and changes nothing."""
    argv = expand(argv, work)
    locks = set(work.rglob("*.cvqpg-lock"))  # the template's own (a folder at a lock's path)
    with claimed(work / output, shared=shared):
        before = tree_state(tmp_path)
        code, _out, err = cli(argv, capsys)
        changes = tree_changes(before, tree_state(tmp_path))
    problems = refusal_problems(argv, code, err, "being written by another cvqpg command", changes)
    assert not problems, "; ".join(problems) + f"\n  stderr: {err.strip()[-800:]}"
    assert set(work.rglob("*.cvqpg-lock")) == locks


@pytest.mark.parametrize("argv", [
    f"view {{run}} --quiet {SWEEP} --out {{pipe}} --overwrite",
    "compress {run} --bits 8 --out {pipe} --overwrite",
    "decompress {cvq} --out {pipe} --overwrite",
    "results --root {records} --out {pipe} --overwrite",
    "render {run} --out {pipe} --overwrite",
    f"fit {FIT} --out {{pipe}} --overwrite",
])
def test_a_pipe_or_a_device_is_never_an_output(argv, shared, template, tmp_path, monkeypatch, capsys):
    """A named pipe (as a device node, /dev/null, would be, which root could otherwise replace): refused, left."""
    pipe = tmp_path / "pipe.md"
    os.mkfifo(pipe)
    hostile_environment(monkeypatch, shared.folder)
    argv = [token.format(tmp=shared.folder, pipe=pipe, **PLACES) for token in shlex.split(argv)]
    code, _out, err = cli(argv, capsys)
    problems = refusal_problems(argv, code, err, "is neither a file nor a folder",
                                tree_changes(shared.state, tree_state(shared.root)))
    assert not problems and stat.S_ISFIFO(os.lstat(pipe).st_mode), problems


@pytest.mark.parametrize("argv", [
    f"fit {{pipe}} --planes 1 {FIT}",
    f"fit {{image}} --depth {{pipe}} {FIT}",
    f"fit {{image}} --depth {{depth}} --display phase --lut {{pipe}} {FIT}",
    "export {run} --lut {pipe} --out new_export",
    f"fit {{image}} --depth {{depth}} --display dpac --lut /dev/zero {FIT}",
])
def test_a_pipe_or_a_device_given_as_an_input_is_refused_not_read(argv, shared, template, tmp_path, monkeypatch,
                                                                   capsys):
    """A named pipe's read waits for a writer for ever, /dev/zero's never ends: refused before it is opened."""
    pipe = tmp_path / "pipe.png"
    os.mkfifo(pipe)
    hostile_environment(monkeypatch, shared.folder)
    argv = [token.format(tmp=shared.folder, pipe=pipe, **PLACES) for token in shlex.split(argv)]
    faulthandler.dump_traceback_later(120, exit=True, file=sys.__stderr__)
    code, _out, err = cli(argv, capsys)
    faulthandler.cancel_dump_traceback_later()
    problems = refusal_problems(argv, code, err, "is neither a file nor a folder",
                                tree_changes(shared.state, tree_state(shared.root)))
    assert not problems, "; ".join(problems) + f"\n  stderr: {err.strip()[-800:]}"


@pytest.mark.parametrize("argv, lock", [
    ("compress {run} --bits 8 --out new.cvq", ".new.cvq.cvqpg-lock"),
    ("decompress {cvq} --out new.safetensors", ".new.safetensors.cvqpg-lock"),
    (f"{BATCH} --out new_batch", ".new_batch.cvqpg-lock"),
    (f"{BATCH} --out {{bdone}}", "b_done/.batch/summary.lock"),
    (f"{BATCH} --out {{bdone}}", "b_done/tiny.error.log"),
])
def test_a_lock_or_a_file_that_is_a_pipe_is_refused_not_waited_on(argv, lock, shared, template, tmp_path,
                                                                   monkeypatch, capsys):
    """A named pipe where a command keeps its lock or writes a file: one line, no wait (a guard ends a hang)."""
    hostile_environment(monkeypatch, shared.folder)
    pipe = shared.folder / lock
    kept = (pipe.read_bytes(), os.lstat(pipe)) if pipe.exists() else None  # a lock file the batch left
    pipe.unlink(missing_ok=True)
    os.mkfifo(pipe)
    try:
        state = tree_state(shared.root)
        faulthandler.dump_traceback_later(120, exit=True, file=sys.__stderr__)
        argv = expand(argv, shared.folder)
        code, _out, err = cli(argv, capsys)
        faulthandler.cancel_dump_traceback_later()
        problems = refusal_problems(argv, code, err, pipe.name, tree_changes(state, tree_state(shared.root)))
    finally:
        pipe.unlink()
        if kept is not None:
            pipe.write_bytes(kept[0])
            pipe.chmod(stat.S_IMODE(kept[1].st_mode))
            os.utime(pipe, ns=(kept[1].st_atime_ns, kept[1].st_mtime_ns))
    assert not problems, "; ".join(problems) + f"\n  stderr: {err.strip()[-800:]}"


@pytest.mark.parametrize("variable, value", [("NUMBA_NUM_THREADS", "0"), ("NUMBA_NUM_THREADS", "abc"),
                                             ("OMP_NUM_THREADS", "0"), ("OMP_NUM_THREADS", "-3"),
                                             ("OMP_NUM_THREADS", "4,x"), ("MKL_NUM_THREADS", "1.5")])
def test_a_thread_count_in_the_environment_that_is_none_is_refused(variable, value, shared, monkeypatch, capsys):
    """Numba reads its count as it loads, and fails (0) or warns in several lines (garbage): refused first."""
    hostile_environment(monkeypatch, shared.folder)
    monkeypatch.setenv(variable, value)
    argv = expand(f"fit {FIT}", shared.folder)
    code, _out, err = cli(argv, capsys)
    problems = refusal_problems(argv, code, err, f"{variable}={value!r} is not a thread count",
                                tree_changes(shared.state, tree_state(shared.root)))
    assert not problems, problems


def test_a_thread_count_in_the_environment_beyond_the_cores_is_lowered_with_a_note(monkeypatch, capsys):
    monkeypatch.setenv("NUMBA_NUM_THREADS", "9999")
    code, _out, err = cli(["fit", "--size", "32", "24", "--steps", "0"], capsys)  # refused after the environment
    cores = len(os.sched_getaffinity(0))
    assert code == 2 and os.environ["NUMBA_NUM_THREADS"] == str(cores)
    assert f"cvqpg: note: NUMBA_NUM_THREADS=9999 lowered to {cores}" in err


def test_a_resume_whose_checkpoint_is_a_folder_is_refused_and_changes_nothing(template, tmp_path, monkeypatch,
                                                                              capsys):
    run = Path(shutil.copytree(template.folder / "run_a", tmp_path / "w" / "cut.partial"))
    (run / "metrics.json").unlink()
    (run / "checkpoint.pt").mkdir()
    hostile_environment(monkeypatch, tmp_path / "w")
    before = tree_state(tmp_path)
    argv = ["fit", "--resume", "cut.partial", "--quiet"]
    code, _out, err = cli(argv, capsys)
    problems = refusal_problems(argv, code, err, "checkpoint.pt is not a file",
                                tree_changes(before, tree_state(tmp_path)))
    assert not problems, problems


@pytest.mark.slow
def test_sigterm_midway_leaves_nothing_half_written(work):
    """SIGTERM while `render` fills its staged folder: exit 143, one line, and neither the folder nor the lock
    stays (the default SIGTERM would kill the command where it stands)."""
    distances = [f"{0.001 + 0.00001 * k:.5f}" for k in range(400)]
    process = subprocess.Popen([sys.executable, "-m", "cvqpg.cli", "render", "run_a", "--out", "late", "--distance",
                                *distances], cwd=work, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        deadline = time.monotonic() + 300
        # a first frame in the staged folder: the kernels are compiled (Numba's compiler ignores an exception raised
        # in its callbacks), and the render is under way
        while (not list(work.glob(".late.partial-*/*")) and process.poll() is None
               and time.monotonic() < deadline):
            time.sleep(0.05)
        process.send_signal(signal.SIGTERM)
        _out, err = process.communicate(timeout=300)
    finally:
        process.kill()
    assert process.returncode == 128 + signal.SIGTERM and err.strip() == "cvqpg render: terminated", err
    assert not [path.name for path in work.iterdir() if "late" in path.name]


@pytest.mark.slow
def test_the_resumes_refused_keep_their_interrupted_folders(work, capsys):
    for name in ("held", "filed"):
        code, _out, err = cli(["fit", "--resume", f"{name}.partial", "--quiet", "--overwrite"], capsys)
        assert code == 2 and name in err
        assert (work / f"{name}.partial" / "config.json").is_file()
    assert (work / "held" / "thesis.tex").read_text() == "years of work\n"
    assert (work / "filed").read_text() == "a user's file\n"
    assert not [p for p in os.listdir(work) if ".replaced-" in p]


@pytest.mark.slow
def test_a_command_writes_into_an_empty_folder_it_is_given(work, tmp_path, capsys):
    before = tree_state(tmp_path)
    code, _out, err = cli(expand("render {run} --out {folder}", work), capsys)
    assert code == 0, err
    changes = tree_changes(before, tree_state(tmp_path))
    assert changes and all(change.split()[1].startswith("w/folder/") for change in changes), changes


# Nothing lost on success: a command given --overwrite replaces its own output as a whole and nothing else. Each
# command works (fits, searches) before it writes: slow.

class Success(NamedTuple):
    argv: str
    replaced: str  # the one path (file or folder) that may change; everything else stays byte for byte


SUCCESSES = {
    # run_a holds model.cvq, export/, render/, model.f16.safetensors ... that a fresh run does not: all must go.
    "fit-overwrite-replaces-the-whole-run": Success(
        "fit --size 32 24 --num-gaussians 20 --steps 2 --quiet --seed 5 --out {run} --overwrite", "run_a"),
    "compress-overwrite-replaces-only-its-file": Success("compress {run} --bits 6 --overwrite", "run_a/model.cvq"),
    "compress-bpp-overwrite-replaces-only-its-file": Success("compress {run} --bpp 8 --finetune 1 --overwrite",
                                                             "run_a/model.cvq"),
    "encode-overwrite-replaces-only-its-file": Success(f"{ENCODE} --bpp 8 --out {{cvq}} --overwrite",
                                                       "run_a/model.cvq"),
    "decompress-overwrite-replaces-only-its-file": Success("decompress {cvq} --overwrite",
                                                           "run_a/model.decoded.safetensors"),
    "export-overwrite-replaces-the-whole-folder": Success("export {run} --levels 16 --overwrite", "run_a/export"),
    "render-overwrite-replaces-the-whole-folder": Success("render {run} --distance 0.002 --overwrite",
                                                          "run_a/render"),
    "info-half-overwrite-replaces-only-its-file": Success("info {run} --half --overwrite",
                                                          "run_a/model.f16.safetensors"),
    "results-overwrite-replaces-only-its-file": Success("results --root {records} --overwrite", "docs/results.md"),
    "view-overwrite-replaces-only-its-page": Success(f"view {{run}} --quiet {SWEEP} --out {{page}} --overwrite",
                                                     "page.html"),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SUCCESSES))
def test_overwrite_replaces_the_output_as_a_whole_and_nothing_else(name, template, work, tmp_path, capsys):
    success = SUCCESSES[name]
    output = work / success.replaced
    if output.is_dir():
        (output / "stray.txt").write_text("left by an earlier run\n")  # must be gone: the folder is replaced
    else:
        output.write_bytes(output.read_bytes() + b"an older output\n")  # of its kind still; must be rewritten
    before = tree_state(tmp_path)
    code, _out, err = cli(expand(success.argv, work), capsys)
    assert code == 0, err
    after = tree_state(tmp_path)
    replaced = f"w/{success.replaced}"

    def outside(state):
        return {p: v for p, v in state.items() if p != replaced and not p.startswith(replaced + "/")}

    assert tree_changes(outside(before), outside(after)) == [], "paths other than the output changed"
    if name.startswith("fit"):
        files = {p.relative_to(output).as_posix() for p in output.rglob("*")}
        assert files == template.fresh_run_files, (
            f"the replaced run holds other files than a fresh run: {sorted(files ^ template.fresh_run_files)}")
    if output.is_dir():
        assert not (output / "stray.txt").exists(), f"{success.replaced}/stray.txt survived the overwrite"
    else:
        assert after[replaced][1] != before[replaced][1], f"{success.replaced} was not rewritten"


@pytest.mark.slow
def test_a_fit_refused_with_overwrite_leaves_the_old_run_byte_for_byte(work, tmp_path, capsys):
    """The failure comes after the options pass (the depth map separates 2 planes, not 5): the run that was there
    stays, with its model.cvq, export/ and every other file."""
    argv = expand("fit {image} --depth {binary} --planes 5 --size 32 24 --steps 2 --quiet --out {run} --overwrite",
                  work)
    before = tree_state(tmp_path)
    code, _out, err = cli(argv, capsys)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert tree_changes(before, tree_state(tmp_path)) == []


# ---------------------------------------------------------------------------------------------------------------
# Many planes: the propagation's kernels take them in groups, so that a fit of any plane count compiles a few
# short kernels and starts at once.

def test_the_compile_probe_has_the_group_lengths_of_any_plane_count_with_few_planes():
    for planes in range(1, 257):
        probe = probe_planes(planes)
        assert group_lengths(probe) == group_lengths(planes) and probe < 2 * FUSED_PLANES_AT_ONCE


def group_lengths(planes: int) -> set[int]:
    return {group.stop - group.start for group in plane_groups(planes)}


@pytest.mark.slow
def test_a_fit_of_more_planes_than_the_kernels_once_took_finishes():
    config = FitConfig.create(width=32, height=24, color="gray", num_planes=101, num_gaussians=24, steps=1,
                              curvature_warmup=0, guard_band_px=8)
    depth = torch.linspace(0, 1, 32 * 24).reshape(24, 32)  # some pixels on every plane
    image = torch.rand(1, 24, 32, generator=torch.Generator().manual_seed(3))
    result = fit(image, depth, config, RunOptions(backend="numba"))
    assert len(result.metrics.per_plane["psnr"]) == 101 and math.isfinite(result.metrics.mean["psnr"])


@pytest.mark.slow
def test_a_render_at_more_distances_than_the_kernels_once_took_finishes(work, capsys):
    distances = [f"{0.001 + 0.00004 * k:.5f}" for k in range(101)]
    code, _out, err = cli(expand("render {run} --out many --distance", work) + distances, capsys)
    assert code == 0, err
    assert len(list((work / "many").glob("recon_*.png"))) == 101


@pytest.mark.parametrize("make, message", [
    (lambda: prepare_image(Image.new("RGB", (1, 1), (200, 10, 10)), 32, 24, "rgb"), "1×1 px, upscaled to 32×24"),
    (lambda: prepare_depth(Image.new("RGBA", (32, 24), (90, 90, 90, 0)), 32, 24), "depth map has an alpha channel"),
    (lambda: check_depth_geometry(Image.new("RGB", (32, 24)), Image.new("L", (24, 24)), resize_depth=True),
     "stretched to the image (another aspect ratio)"),
])
def test_what_is_done_to_an_input_beyond_resizing_it_is_noted(make, message, caplog):
    with caplog.at_level("WARNING", logger="cvqpg"):
        make()
    assert message in caplog.text


def test_a_batch_notes_a_depth_map_it_stretches_in_the_items_summary_row(template):
    item = BatchInput("tiny", template.folder / "photo.png", template.folder / "square_depth.png")
    planned = plan_item(item, template.folder / "new_batch", BatchSettings(resize_depth=True))
    assert "stretched to the image" in planned.note
    assert plan_item(item, template.folder / "new_batch", BatchSettings()).note is None


def test_a_batch_item_whose_depth_map_is_a_pipe_is_planned_without_waiting_on_it(template, tmp_path):
    """The stretched depth map's note reads the files' headers: a pipe is not opened (its fit refuses it)."""
    pipe = tmp_path / "depth.png"
    os.mkfifo(pipe)
    item = BatchInput("tiny", template.folder / "photo.png", pipe)
    faulthandler.dump_traceback_later(60, exit=True, file=sys.__stderr__)
    planned = plan_item(item, tmp_path / "new_batch", BatchSettings(resize_depth=True))
    faulthandler.cancel_dump_traceback_later()
    assert not planned.note
