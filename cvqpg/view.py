"""The view page (`cvqpg view`): one self-contained HTML file to refocus a run's hologram through a focal
sweep, compare it side by side with a second run, and see the hologram, its phase-only display, and the
run's settings and metrics. Images are embedded as data URIs: the page needs no server and no network."""

from __future__ import annotations

import base64
import html
import io
import json
import logging
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch
from PIL import Image
from torch import Tensor
from tqdm.auto import tqdm

from .config import FitConfig, check_distances
from .control import SILENT, RunControl
from .defaults import DEFAULT_SWEEP, VIEW_FILE
from .errors import InputError
from .fitting import hologram
from .metrics import METRIC_NAMES, psnr
from .ops.propagation import release_transfer_functions
from .optics import reconstruct
from .runs import (EXPORT_FOLDER, METRICS_FILE, hologram_images, load_run_model, optics_label, read_metrics,
                   read_run, read_run_options, to_8bit, write_atomic)
from .targets import load_picture

MAX_DISTANCE_M = 0.1  # farther, a few-mm hologram's band limit leaves almost nothing: a mm/m mix-up
FRAME_QUALITY = 90  # JPEG quality of every embedded image, colour at full resolution (4:4:4)
MAX_SWEEP_COUNT = 4096  # frames of one page: more than a slider's pixels
SWEEP_BATCH = 8  # distances per propagation: they share each channel's forward transform
SAME_DISTANCE_M = 1e-9
TEMPLATE = "view_page.html"
EXPORT_AGAIN = "run `cvqpg export` on the run again"

log = logging.getLogger("cvqpg")


@dataclass
class ViewRecord:
    """What `write_view` wrote: the page, its size, its frame count per run and the seconds it took."""

    path: Path
    bytes: int
    frames: int
    seconds: float


@dataclass
class Run:
    """A finished run folder, loaded on the device it is rendered on."""

    folder: Path
    config: FitConfig
    source: dict[str, Any]
    field: Tensor  # complex hologram [C, H, W]
    metrics: dict[str, Any] | None

    @property
    def name(self) -> str:
        return self.folder.resolve().name

    @property
    def planes(self) -> tuple[float, ...]:
        """Distances (m) of the training planes."""
        return self.config.plane_distances


def check_sweep(start_m: float, stop_m: float, count: int) -> None:
    """Raise `InputError` unless 1 ≤ COUNT ≤ `MAX_SWEEP_COUNT` and START ≤ STOP are distances in m below
    `MAX_DISTANCE_M`; `ConfigError` where they leave the configuration's range (`check_distances`)."""
    given = f"`distances` {start_m:g} {stop_m:g} {count:g}"
    if not 1 <= count <= MAX_SWEEP_COUNT:
        raise InputError(f"{given}: COUNT must lie in [1, {MAX_SWEEP_COUNT}]")
    if not 0 < start_m <= stop_m:
        raise InputError(f"{given}: give 0 < START ≤ STOP in m (e.g. 0.0005 0.006 41 for 0.5–6 mm)")
    check_distances((start_m, stop_m), given + ": START and STOP")
    if stop_m > MAX_DISTANCE_M:
        raise InputError(f"{given}: distances are in m and STOP is over {MAX_DISTANCE_M:g} m; for 0.5–6 mm give "
                        "0.0005 0.006 41")


def sweep_distances(start_m: float, stop_m: float, count: int, planes_m: Sequence[float]) -> list[float]:
    """COUNT distances (m) from START to STOP, plus the training planes inside that range, sorted: a
    target exists at every plane, so its PSNR is shown there exactly."""
    sweep = list(np.linspace(start_m, stop_m, count)) if count > 1 else [start_m]
    inside = [p for p in planes_m if start_m - SAME_DISTANCE_M <= p <= stop_m + SAME_DISTANCE_M]
    kept = [d for d in sweep if all(abs(d - p) > SAME_DISTANCE_M for p in inside)]
    return sorted(float(d) for d in kept + inside)


def check_comparable(folders: Sequence[Path], configs: Sequence[FitConfig]) -> None:
    """Raise `InputError` unless the runs share size, pixel pitch and wavelengths (side by side and the zoom
    need the same pixels)."""
    for folder, config in zip(folders[1:], configs[1:]):
        if optics_label(config) != optics_label(configs[0]):
            raise InputError(f"{folder} is {optics_label(config)} but {folders[0]} is {optics_label(configs[0])}; "
                            "compare runs of the same size and optics (e.g. the baseline and the CVQPG fit of one "
                            "scene)")


def run_device(folder: Path) -> str:
    """The device the run in `folder` was fitted on, or the CPU (with a note) where that GPU is absent."""
    device = read_run_options(folder).device
    if device.startswith("cuda") and not torch.cuda.is_available():
        log.warning(f"the run was fitted on {device}, which is not available; rendering on the CPU")
        return "cpu"
    return device


def load_run(folder: Path) -> Run:
    """Read a finished run folder and render its hologram; its model must belong to it (`load_run_model`)."""
    primitives, config, source = load_run_model(folder, device=run_device(folder))
    metrics_file = folder / METRICS_FILE
    metrics = read_metrics(metrics_file) if metrics_file.is_file() else None
    with torch.no_grad():
        field = hologram(primitives, config)
    return Run(folder, config, source, field, metrics)


def focal_sweep(run: Run, distances_m: Sequence[float], progress: bool = True, control: RunControl = SILENT
                ) -> Iterator[Tensor]:
    """Clamped reconstructions [C, H, W] (on the CPU) of a run at each distance (m), propagated
    `SWEEP_BATCH` distances at a time on the run's device; `control` asked before each batch
    (`RunControl.check`)."""
    with torch.no_grad(), tqdm(total=len(distances_m), disable=not progress, desc=f"view {run.name}",
                               unit="plane", dynamic_ncols=True) as bar:
        for start in range(0, len(distances_m), SWEEP_BATCH):
            control.check()
            batch = list(distances_m[start:start + SWEEP_BATCH])
            # Filled up with its last distance: Numba compiles the propagation's kernels once per plane count.
            filled = batch + batch[-1:] * (SWEEP_BATCH - len(batch))
            frames = reconstruct(run.field, run.config, filled)[:len(batch)].cpu()
            release_transfer_functions()
            bar.update(len(batch))
            yield from frames


def data_uri(image: Image.Image) -> str:
    """The image as an embeddable JPEG (`FRAME_QUALITY`, 4:4:4)."""
    buffer = io.BytesIO()
    image.save(buffer, "JPEG", quality=FRAME_QUALITY, subsampling=0)
    return "data:image/jpeg;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def read_target(path: Path, frame: Tensor) -> np.ndarray | None:
    """An 8-bit target PNG as [C, H, W] in [0, 1], or None where it is missing or does not match the frame;
    `InputError` where it is damaged."""
    if not path.is_file():
        return None
    picture = load_picture(path, "target", "delete it to view the run without the PSNR at its plane, or fit the "
                           "run again")
    pixels = np.asarray(picture, dtype=np.float32) / 255
    pixels = pixels[None] if pixels.ndim == 2 else pixels.transpose(2, 0, 1)
    return pixels if pixels.shape == tuple(frame.shape) else None


def plane_index(distance_m: float, planes_m: Sequence[float]) -> int | None:
    """The training plane at `distance_m`, if any."""
    return next((m for m, p in enumerate(planes_m) if abs(p - distance_m) <= SAME_DISTANCE_M), None)


def sweep_frames(run: Run, distances_m: Sequence[float], progress: bool, control: RunControl = SILENT
                 ) -> dict[str, list]:
    """Embedded frames and, where a training plane's target exists, their PSNR (dB) against it (`control`:
    `focal_sweep`)."""
    frames, psnrs = [], []
    for distance, frame in zip(distances_m, focal_sweep(run, distances_m, progress, control)):
        frames.append(data_uri(to_8bit(frame)))
        plane = plane_index(distance, run.planes)
        target = None if plane is None else read_target(run.folder / f"target_plane{plane}.png", frame)
        psnrs.append(None if target is None else round(psnr(frame.numpy(), target), 3))
    return {"frames": frames, "psnr": psnrs}


def plane_label(plane: int, distance_m: float) -> str:
    return f"plane {plane} · {distance_m * 1e3:g} mm"


def display_images(run: Run) -> list[dict[str, str]]:
    """The simulated phase-only display of `cvqpg export` at each plane, with its PSNR; none without an export."""
    folder = run.folder / EXPORT_FOLDER
    record_file = folder / METRICS_FILE
    record = (read_metrics(record_file, EXPORT_AGAIN, within=("phase_only_display", "complex_field"))
              if record_file.is_file() else {})
    shown = record.get("phase_only_display", {}).get("per_plane", {}).get("psnr", [])
    fitted = record.get("complex_field", {}).get("per_plane", {}).get("psnr", [])
    images = []
    for plane, distance in enumerate(run.planes):
        path = folder / f"display_plane{plane}.png"
        if path.is_file():
            scores = (f"PSNR {shown[plane]:.2f} dB (complex field: {fitted[plane]:.2f} dB)"
                      if plane < min(len(shown), len(fitted)) else "")
            images.append({"label": f"{plane_label(plane, distance)} {scores}".strip(),
                           "uri": data_uri(load_picture(path, "display image", EXPORT_AGAIN))})
    return images


def _value(value: Any, decimals: int) -> str:
    return "–" if value is None else f"{value:.{decimals}f}"


def settings_rows(run: Run) -> dict[str, str]:
    """The run's settings and metrics as (label → text), in the order the table shows them."""
    config, metrics = run.config, run.metrics or {}
    mean, per_plane = metrics.get("mean", {}), metrics.get("per_plane", {})
    record = metrics.get("run", {})
    rows = {"input": input_label(run.source), "primitive": config.primitives.kind, "colour": config.targets.color,
            "optics": optics_label(config),
            "planes": ", ".join(f"{d * 1e3:g} mm" for d in run.planes),
            "N primitives": f"{config.primitive_count:,}",
            "parameters": f"{config.primitive_count * config.params_per_primitive:,}",
            "steps (warm-up)": f"{config.optimisation.steps} ({config.optimisation.curvature_warmup})",
            "curvature": f"{config.primitives.curvature}, {config.primitives.bound} bound, {config.primitives.qpf} QPF"
            if config.primitives.kind == "cvqpg" else "–",
            "seed": str(config.optimisation.seed), "display": config.display.label()}
    rows.update({name.upper(): _value(mean.get(name), 4 if name in ("ssim", "flip", "lpips") else 3)
                 for name in METRIC_NAMES})
    rows["PSNR per plane (dB)"] = " / ".join(_value(v, 3) for v in per_plane.get("psnr", [])) or "–"
    rows["fit time"] = f"{metrics['seconds']:.0f} s" if "seconds" in metrics else "–"
    rows["device"] = record.get("device", run.field.device.type)
    rows["commit"] = str(record.get("commit") or "–")[:12]
    return rows


def input_label(source: dict[str, Any]) -> str:
    """The run's input: the built-in scene's name, or the image file's name."""
    return f"scene {source['scene']}" if "scene" in source else Path(source.get("image", "?")).name


def settings_table(runs: Sequence[Run]) -> str:
    """One column per run."""
    columns = [settings_rows(run) for run in runs]
    head = "<tr><th></th>" + "".join(f"<th>{html.escape(run.name)}</th>" for run in runs) + "</tr>"
    body = "".join(f"<tr><th>{html.escape(label)}</th>"
                   + "".join(f"<td>{html.escape(column[label])}</td>" for column in columns) + "</tr>"
                   for label in columns[0])
    return f"<table id='settings'>{head}{body}</table>"


def page_data(runs: Sequence[Run], distances_m: Sequence[float], progress: bool, control: RunControl = SILENT
              ) -> dict[str, Any]:
    """Everything the page's script reads: distances, training plane marks and each run's images (`control`:
    `sweep_frames`)."""
    planes = sorted({p for run in runs for p in run.planes})
    marks = [{"index": index, "label": f"{distance * 1e3:g} mm"}
             for index, distance in enumerate(distances_m) if plane_index(distance, planes) is not None]
    shown = []
    for run in runs:
        images = {name: data_uri(image) for name, image in hologram_images(run.field).items()}
        shown.append({"name": run.name, **sweep_frames(run, distances_m, progress, control), **images,
                      "display": display_images(run)})
    return {"width": runs[0].config.targets.width, "height": runs[0].config.targets.height,
            "distances_mm": [round(d * 1e3, 6) for d in distances_m], "marks": marks, "runs": shown}


def page_html(runs: Sequence[Run], data: dict[str, Any]) -> str:
    """The page: the template with the title, the settings table and the data (JSON) filled in."""
    title = "cvqpg view: " + " vs ".join(run.name for run in runs)
    notes = (f"Frames are JPEG at quality {FRAME_QUALITY} (4:4:4) of the clamped intensity. PSNR is against "
             "the run's 8-bit target_plane{m}.png, shown at the training planes (marked on the slider).")
    # JSON inside <script> must not close it: "</" is escaped, which JSON reads back unchanged.
    embedded = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    template = resources.files("cvqpg").joinpath(TEMPLATE).read_text(encoding="utf-8")
    return (template.replace("__TITLE__", html.escape(title)).replace("__NOTES__", html.escape(notes))
            .replace("__SETTINGS__", settings_table(runs)).replace("__DATA__", embedded))


def default_page(folders: Sequence[str | Path]) -> Path:
    """`RUN_DIR/view.html`, or `RUN_DIR/view_vs_<RUN_DIR_2's name>.html` for two runs."""
    first = Path(folders[0])
    return first / (VIEW_FILE if len(folders) == 1 else f"view_vs_{Path(folders[1]).resolve().name}.html")


def write_view(folders: Sequence[str | Path], out: str | Path | None = None,
               sweep: tuple[float, float, int] = DEFAULT_SWEEP, progress: bool = True,
               control: RunControl = SILENT) -> ViewRecord:
    """Write the view page of one or two finished run folders (sweep: START m, STOP m, COUNT); nothing is
    written when the input is refused, or `control` stops it (`RunControl.check`, asked before each batch of
    frames and before the page is written)."""
    clock = time.perf_counter()
    if not 1 <= len(folders) <= 2:
        raise InputError(f"give one or two run folders, not {len(folders)}")
    check_sweep(*sweep)
    out = Path(out) if out is not None else default_page(folders)
    if out.is_dir():
        raise InputError(f"`out` {out} is a folder; give a file name such as {out / VIEW_FILE}")
    folders = [Path(folder) for folder in folders]
    check_comparable(folders, [read_run(folder)[0] for folder in folders])
    runs = [load_run(folder) for folder in folders]
    distances = sweep_distances(*sweep, sorted({p for run in runs for p in run.planes}))
    page = page_html(runs, page_data(runs, distances, progress, control))
    control.check()
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, page)
    return ViewRecord(out, out.stat().st_size, len(distances), time.perf_counter() - clock)
