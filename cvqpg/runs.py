"""Run folders: everything a fit leaves behind, and re-evaluation of a saved run."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from . import __version__
from .config import MIN_SIZE_PX, SECTIONS, FitConfig, RunOptions, check_sampling
from .control import SILENT, RunControl
from .errors import ConfigError, CvqpgError, InputError, ModelFileError
from .files import write_atomic
from .display import Display, Encoding
from .patterns import PhasePattern, phase_pattern
from .fitting import FitResult, render
from .metrics import MetricReport, evaluate, mean_psnr
from .ops.field import slm_field
from .optics import reconstruct
from .primitives import Primitives
from .representation import require_gaussians
from .scenes import builtin_scene
from .storage import load_model, model_info, model_run, save_model
from .targets import Scene, load_scene

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"
MODEL_FILE = "model.safetensors"
CHECKPOINT_FILE = "checkpoint.pt"
HISTORY_FILE = "history.csv"
HISTORY_ROWS = 1000  # at most about this many steps per history.csv: a bench cell keeps it in git
PLANE_IMAGES = ("target_plane*.png", "recon_plane*.png")
# What every config.json of the flat layout (before `config_schema`) has held since the first version, and what
# every later one holds: without them a run would take the defaults.
RUN_KEYS = ("source", "width", "height", "color", "primitive", "pixel_pitch", "num_planes", "plane_center",
            "plane_span")
SCHEMA_RUN_KEYS = ("source", *SECTIONS)
RESTORE_RUN = "restore the file or fit the run again"
REEVALUATE_RUN = "delete it, then `cvqpg eval` on the run writes it again"
# The schema of a fit's fingerprint (`fit_fingerprint`) in checkpoints and models.
FINGERPRINT_SCHEMA = 2


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (see `write_atomic`)."""
    write_atomic(path, json.dumps(data, indent=2) + "\n")


def to_8bit(image: Tensor) -> Image.Image:
    """[C, H, W] in [0, 1] → 8-bit RGB or L image."""
    array = np.clip(np.round(image.detach().cpu().float().numpy() * 255), 0, 255).astype(np.uint8)
    return Image.fromarray(array[0], "L") if array.shape[0] == 1 else Image.fromarray(
        array.transpose(1, 2, 0), "RGB")


def colormapped(values: np.ndarray, cmap: str, low: float, high: float) -> Image.Image:
    """Channels [C, H, W] side by side through a matplotlib colour map."""
    import matplotlib

    tiled = np.concatenate(list(values), axis=1)
    rgba = matplotlib.colormaps[cmap]((tiled - low) / (high - low))
    return Image.fromarray((rgba[..., :3] * 255).astype(np.uint8), "RGB")


def hologram_images(hologram: Tensor) -> dict[str, Image.Image]:
    """`amplitude` (viridis, 0..max) and `phase` (twilight, 0..2π) of a hologram [C, H, W], one panel
    per channel."""
    amplitude = hologram.abs().cpu().numpy()
    phase = np.mod(hologram.angle().cpu().numpy(), 2 * math.pi)
    return {"amplitude": colormapped(amplitude, "viridis", 0.0, max(float(amplitude.max()), 1e-12)),
            "phase": colormapped(phase, "twilight", 0.0, 2 * math.pi)}


def save_hologram_images(hologram: Tensor, folder: Path) -> None:
    """`amplitude.png` and `phase.png` (see `hologram_images`)."""
    for name, image in hologram_images(hologram).items():
        image.save(folder / f"{name}.png")


def save_curve(history: dict[str, list[float]], path: Path) -> None:
    """Loss (log scale) and PSNR per step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, loss_axis = plt.subplots(figsize=(7, 3.5), dpi=110)
    steps = np.arange(len(history["loss"]))
    loss_axis.semilogy(steps, history["loss"], color="tab:blue")
    loss_axis.set_xlabel("step")
    loss_axis.set_ylabel("loss", color="tab:blue")
    psnr_axis = loss_axis.twinx()
    psnr_axis.plot(steps, history["psnr"], color="tab:orange")
    psnr_axis.set_ylabel("PSNR vs targets (dB)", color="tab:orange")
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def save_history(history: dict[str, list[float]], seconds: float, path: Path) -> None:
    """`step,seconds,loss,psnr` at every k-th update and the last, k chosen for at most `HISTORY_ROWS` + 1 rows.

    `seconds` is the step's share of the loop's `seconds` (its updates cost alike), so that runs of
    different lengths and speeds can share a PSNR-against-seconds plot."""
    updates = len(history["psnr"])
    stride = max(1, math.ceil(updates / HISTORY_ROWS))
    rows = ["step,seconds,loss,psnr"]
    for step in sorted({*range(0, updates, stride), updates - 1} if updates else ()):
        rows.append(f"{step},{seconds * (step + 1) / updates:.3f},{history['loss'][step]:.6g},{history['psnr'][step]:.4f}")
    write_atomic(path, "\n".join(rows) + "\n")


def read_history(path: Path) -> dict[str, np.ndarray]:
    """A `history.csv` (see `save_history`) as arrays `step`, `seconds`, `loss` and `psnr`."""
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return dict(zip(("step", "seconds", "loss", "psnr"), table.T))


def metrics_record(report: MetricReport, config: FitConfig, seconds: float,
                   extra: dict[str, Any] | None = None) -> dict[str, Any]:
    return {**report.to_dict(), "steps": config.optimisation.steps, "num_gaussians": config.primitive_count,
            "num_params": config.primitive_count * config.params_per_primitive,
            "seconds": seconds, **(extra or {})}


def complex_field_metrics(primitives: Primitives, config: FitConfig, scene: Scene, backend: str = "auto"
                          ) -> dict[str, Any]:
    """For a model fitted through a display other than the complex one: the display (`display`, its label) and
    `complex_field`, the metrics of its complex field as method.md §3 reconstructs it, beside those of what the
    display shows; else nothing."""
    if config.display.ideal:
        return {}
    _, recon = render(primitives, config.replace(display=Display()), backend=backend)
    return {"display": config.display.label(), "complex_field": evaluate(recon, scene.targets).to_dict()}


def start_run(folder: str | Path, config: FitConfig, source: dict[str, Any], run: RunOptions = RunOptions(),
              keep_checkpoint: bool = False) -> Path:
    """Create the run folder with its `config.json` (enough to resume: the settings, the inputs and where it runs);
    clear a previous run's outputs (and its checkpoint, unless `keep_checkpoint`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for pattern in (METRICS_FILE, MODEL_FILE, HISTORY_FILE, *PLANE_IMAGES, *(() if keep_checkpoint else (CHECKPOINT_FILE,))):
        for stale in folder.glob(pattern):
            stale.unlink()
    write_json(folder / CONFIG_FILE, {"cvqpg_version": __version__, "source": source, **config.to_dict(),
                                      "run": run.to_dict()})
    return folder


def read_record(path: Path, remedy: str) -> dict[str, Any]:
    """The JSON object in the file `path`; `InputError` naming it and `remedy` where it is unreadable, not JSON
    or not an object."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise InputError(f"{path} is not a readable JSON file ({error}); {remedy}") from None
    if not isinstance(record, dict):
        raise InputError(f"{path} holds a JSON {type(record).__name__}, not an object; {remedy}")
    return record


def read_metrics(path: Path, remedy: str = REEVALUATE_RUN, within: Sequence[str] = ()) -> dict[str, Any]:
    """A metrics record (`read_record`) whose fields are of the kinds `metrics_record` writes: `mean` an object of
    numbers, `per_plane` one of lists of numbers, `seconds` a number, `run` an object (each where present; None
    for a metric that was not available), and so is each of its sections named in `within` (an export's
    `phase_only_display`, ...); `InputError` naming the first that is not, with `remedy`."""
    record = read_record(path, remedy)
    for section, fields in [("", record), *((name, record.get(name, {})) for name in within)]:
        wrong = _metrics_problem(fields)
        if wrong is not None:
            raise InputError(f"{path}: its {'.'.join(filter(None, (section, wrong)))!r} is not what cvqpg writes "
                             f"there; {remedy}")
    return record


def _metrics_problem(record: Any) -> str | None:
    """The first field of a metrics record (`read_metrics`) that is not of its kind, "" for a record that is no
    object, or None."""
    def number(value: Any) -> bool:
        return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))

    if not isinstance(record, dict):
        return ""
    kinds = {"mean": lambda v: isinstance(v, dict) and all(number(x) for x in v.values()),
             "per_plane": lambda v: isinstance(v, dict) and all(
                 isinstance(x, list) and all(number(y) for y in x) for x in v.values()),
             "seconds": number, "run": lambda v: v is None or isinstance(v, dict)}
    return next((key for key, fits in kinds.items() if key in record and not fits(record[key])), None)


def read_run(folder: str | Path) -> tuple[FitConfig, dict[str, Any]]:
    """The configuration and input description of a run folder; `InputError` naming the folder or file where
    its `config.json` is missing, unreadable, incomplete or holds settings that cannot work. Inputs the run
    keeps itself (an estimated depth map) are recorded relative to the run folder and returned resolved."""
    folder = Path(folder)
    path = folder / CONFIG_FILE
    if not path.is_file():
        raise InputError(f"{folder} is not a run folder (no {CONFIG_FILE}); give a folder written by `cvqpg fit`")
    recorded = read_record(path, RESTORE_RUN)
    missing = [key for key in (SCHEMA_RUN_KEYS if "config_schema" in recorded else RUN_KEYS) if key not in recorded]
    if missing:
        raise InputError(f"{path} lacks {', '.join(missing)}; {RESTORE_RUN}")
    source = recorded["source"]
    if not isinstance(source, dict) or not ("scene" in source or "image" in source):
        raise InputError(f"{path}: its source names neither a scene nor an image; {RESTORE_RUN}")
    source = {key: str(folder / value) if key in ("image", "depth") and not Path(value).is_absolute() else value
              for key, value in source.items()}
    try:
        return FitConfig.from_dict(recorded).validate(), source
    except (ConfigError, TypeError, ValueError, AttributeError) as error:
        raise InputError(f"{path}: its settings cannot work ({error}); {RESTORE_RUN}") from None


def read_run_options(folder: str | Path) -> RunOptions:
    """Where the run in `folder` ran, as its `config.json` records it (device and backend): what a resume runs
    on, and the kernels a render of it takes where they run (`RunOptions.on_device`)."""
    path = Path(folder) / CONFIG_FILE
    try:
        return RunOptions.from_dict(read_record(path, RESTORE_RUN))
    except ConfigError as error:
        raise InputError(f"{path}: {error}; {RESTORE_RUN}") from None


def write_run(folder: str | Path, result: FitResult, scene: Scene, source: dict[str, Any],
              run: dict[str, Any] | None = None, extra: dict[str, Any] | None = None) -> Path:
    """Save config, metrics, model, per-plane targets and reconstructions, hologram, curve and history; `run`
    is what `metrics.json` records about the code and machine (`cvqpg.app.provenance.run_record`), `extra` what
    else it records (a bench cell's own numbers).

    The checkpoint goes only once `metrics.json`, the mark of a finished run, is written: a run
    killed while its files are written resumes from the checkpoint instead of starting over."""
    folder = start_run(folder, result.config, source, result.run, keep_checkpoint=True)
    config = result.config
    save_model(folder / MODEL_FILE, result.primitives, config, run=run_fit(folder))
    for plane, (target, image) in enumerate(zip(scene.targets, result.reconstructions)):
        to_8bit(target).save(folder / f"target_plane{plane}.png")
        to_8bit(image).save(folder / f"recon_plane{plane}.png")
    save_hologram_images(result.hologram, folder)
    save_curve(result.history, folder / "curve.png")
    save_history(result.history, result.seconds, folder / HISTORY_FILE)
    history = result.history["psnr"]
    write_json(folder / METRICS_FILE, metrics_record(
        result.metrics, config, result.seconds,
        {**complex_field_metrics(result.primitives, config, scene, result.run.backend),
         "updates": len(history), "initial_psnr": history[0] if history else None,
         "skipped_steps": result.skipped_steps, "sanitised_steps": result.sanitised_steps,
         **(extra or {}), **({} if run is None else {"run": run})}))
    (folder / CHECKPOINT_FILE).unlink(missing_ok=True)
    return folder


def scene_from_source(source: dict[str, Any], config: FitConfig) -> Scene:
    """Rebuild a run's scene from what `config.json` recorded about its inputs."""
    if "scene" in source:
        return builtin_scene(source["scene"], config)
    return load_scene(source["image"], source.get("depth"), config, source.get("resize_depth", False))


def optics_label(config: FitConfig) -> str:
    """E.g. `640×480 px, 3.74 µm pitch, 639/532/473 nm`."""
    return (f"{config.targets.width}×{config.targets.height} px, {config.optics.pixel_pitch * 1e6:g} µm pitch, "
            + "/".join(f"{w * 1e9:g}" for w in config.wavelengths) + " nm")


def _targets(config: FitConfig) -> tuple[Any, ...]:
    """What a run's targets, and a render compared with them, depend on: size and colour first."""
    return (config.targets.width, config.targets.height, config.targets.color, config.optics.pixel_pitch,
            config.wavelengths,
            config.plane_distances)


def targets_label(config: FitConfig, brief: bool) -> str:
    """The targets `config` fits: size and colour (`brief`: `64×48 rgb`), or the optics and planes."""
    if brief:
        return f"{config.targets.width}×{config.targets.height} {config.targets.color}"
    return f"{optics_label(config)}, planes at {', '.join(f'{d * 1e3:g}' for d in config.plane_distances)} mm"


def load_run_model(folder: str | Path, model: str | Path | None = None, device: str | None = None
                   ) -> tuple[Primitives, FitConfig, dict[str, Any]]:
    """The model of the run in `folder` (its own, or the model file `model`) with its settings, on `device`
    (None: the CPU), and the run's `source`. `ModelFileError` where the model was
    fitted for other targets than the run's: another size, colour, pixel pitch, wavelengths or planes."""
    folder = Path(folder)
    run_config, source = read_run(folder)
    path = folder / MODEL_FILE if model is None else Path(model)
    primitives, config = load_model(path, device or "cpu")
    if _targets(config) != _targets(run_config):
        brief = _targets(config)[:3] != _targets(run_config)[:3]
        raise ModelFileError(f"{path} was fitted for {targets_label(config, brief)}, the run folder {folder} is "
                             f"{targets_label(run_config, brief)}: use it with its own run folder")
    recorded = model_run(path)
    if recorded is not None and not same_fit(recorded, run_fit(folder)):
        raise ModelFileError(f"{path} was fitted in another run (other settings or inputs than "
                             f"{folder / CONFIG_FILE} records): use it with its own run folder")
    fitted = _fitted_count(folder) if model is None else None
    if fitted is not None and fitted != primitives.count:
        raise ModelFileError(f"{path} holds {primitives.count} primitives, the run's {METRICS_FILE} records a fit of "
                             f"{fitted}: use the model with its own run folder")
    return primitives, config, source


def run_fit(folder: str | Path) -> dict[str, Any]:
    """The fingerprint (`fit_fingerprint`) of the fit that the run folder's `config.json` records."""
    folder = Path(folder)
    return fit_fingerprint(read_run(folder)[0], read_record(folder / CONFIG_FILE, RESTORE_RUN)["source"])


def fit_fingerprint(config: FitConfig, source: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint or a model records of the fit it belongs to: the settings and the inputs (`source`, as
    `config.json` records it), with the record's schema (`FINGERPRINT_SCHEMA`). Where it ran is no part."""
    return {"schema": FINGERPRINT_SCHEMA, "config": config.to_dict(), "source": source}


# The settings that `config_schema` 2 (cvqpg 0.3.0) recorded, section by section. A fit that the settings added
# since leave as they were (their defaults) hashes that record, as 0.3.0 did, so that the `.cvq` files written
# before them keep binding to their runs.
PRE_DISPLAY_SCHEMA = 2
PRE_DISPLAY_LAYOUT: dict[str, Any] = {
    "targets": ("width", "height", "color", "num_planes", "plane_center", "plane_span", "defocus_sigma_px",
                "depth_exponent"),
    "optics": ("pixel_pitch", "wavelengths_m", "guard_band_px", "pad_multiple_px"),
    "primitives": ("kind", "ratio", "count", "bound", "global_bound", "eta", "qpf", "curvature"),
    "optimisation": {"steps": None, "curvature_warmup": None, "seed": None, "betas": None, "adan_eps": None,
                     "grad_clip_norm": None, "init": None,
                     "lr": ("position", "position_final", "scale", "amplitude", "phase", "opacity", "rotation",
                            "curvature")},
    "loss": ("ssim_weight", "focus_weight", "product_weight", "target_noise"),
    "recipe": None,
}


def _within(record: dict[str, Any], layout: dict[str, Any] | tuple[str, ...]) -> dict[str, Any]:
    """The part of `record` that `layout` names (nested sections as dicts, plain fields as names or None)."""
    if isinstance(layout, tuple):
        return {name: record[name] for name in layout}
    return {name: record[name] if inner is None else _within(record[name], inner) for name, inner in layout.items()}


def canonical_config(config: FitConfig) -> dict[str, Any]:
    """The record of `config` that fingerprints hash: `to_dict`'s, or, where every setting added since
    `PRE_DISPLAY_SCHEMA` keeps its default, the record that schema kept (`PRE_DISPLAY_LAYOUT`)."""
    record = config.to_dict()
    earlier = {"config_schema": PRE_DISPLAY_SCHEMA, **_within(record, PRE_DISPLAY_LAYOUT)}
    try:
        return earlier if FitConfig.from_dict(earlier) == config else record
    except CvqpgError:  # a setting of the earlier layout that only a later one allows (a per-pixel init)
        return record


def fingerprint_digest(fingerprint: object) -> bytes | None:
    """The 16 bytes a `.cvq` file (format 5 on) keeps of a `fit_fingerprint` record: the first half of the SHA-256
    of its canonical JSON (keys sorted, no spaces), the settings as this version reads them; None where the
    record is not one of `FINGERPRINT_SCHEMA`."""
    if not (isinstance(fingerprint, dict) and fingerprint.get("schema") == FINGERPRINT_SCHEMA):
        return None
    try:
        canonical = {**fingerprint, "config": canonical_config(FitConfig.from_dict(fingerprint["config"]))}
        text = json.dumps(canonical, sort_keys=True, separators=(",", ":"))
    except (KeyError, TypeError, ValueError, CvqpgError):
        return None
    return hashlib.sha256(text.encode()).digest()[:16]


def same_fit(recorded: object, fingerprint: dict[str, Any]) -> bool:
    """Whether a `fit_fingerprint` record read back from a file is `fingerprint`: the settings it recorded read
    as the same configuration (a setting added later takes the value the fit had) and the same inputs. A `.cvq`
    file records its `fingerprint_digest` (bytes)."""
    if isinstance(recorded, bytes):
        return recorded == fingerprint_digest(fingerprint)
    if not (isinstance(recorded, dict) and recorded.get("schema") == FINGERPRINT_SCHEMA):
        return False
    try:
        return (FitConfig.from_dict(recorded["config"]) == FitConfig.from_dict(fingerprint["config"])
                and recorded["source"] == fingerprint["source"])
    except (KeyError, TypeError, ValueError, CvqpgError):
        return False


def _fitted_count(folder: Path) -> int | None:
    """The primitive count N that the run's `metrics.json` records, or None where it records none."""
    path = folder / METRICS_FILE
    if not path.is_file():
        return None
    count = read_record(path, REEVALUATE_RUN).get("num_gaussians")
    return count if isinstance(count, int) and not isinstance(count, bool) else None


def evaluation_file(folder: str | Path, model: str | Path | None = None) -> Path:
    """Where `evaluate_run` writes: the run's `metrics.json`, or `<model stem>.metrics.json` for `model`."""
    return Path(folder) / (METRICS_FILE if model is None else f"{Path(model).stem}.{METRICS_FILE}")


def evaluate_run(folder: str | Path, model: str | Path | None = None, device: str = "cpu") -> dict[str, Any]:
    """Recompute a saved run's metrics from its model (or `model`, e.g. a compressed file in the
    run folder) and inputs, rendered on `device` with the run's kernels where they run there
    (`RunOptions.on_device`); rewrites `metrics.json`, or writes `<model stem>.metrics.json` for `model`."""
    folder = Path(folder)
    primitives, config, source = load_run_model(folder, model, device)
    scene = scene_from_source(source, config)
    backend = read_run_options(folder).on_device(device).backend
    _, recon = render(primitives, config, backend=backend)
    metrics_file = evaluation_file(folder, model)
    previous = {}
    if (folder / METRICS_FILE).is_file():
        previous = read_record(folder / METRICS_FILE, "delete it and evaluate again (the fit's time and run "
                               "record go with it)")
    kept = {k: v for k, v in previous.items()
            if k not in ("mean", "per_plane", "unavailable", "display", "complex_field")}
    record = {**metrics_record(evaluate(recon, scene.targets), config, previous.get("seconds", 0.0),
                               complex_field_metrics(primitives, config, scene, backend)), **kept}
    write_json(metrics_file, record)
    return record


EXPORT_FOLDER = "export"
RENDER_FOLDER = "render"
HALF_MODEL_FILE = "model.f16.safetensors"


def channel_labels(config: FitConfig) -> list[str]:
    """File-name label per channel: colour and wavelength, e.g. `red_639nm`."""
    names = ("red", "green", "blue") if config.channels == 3 else ("gray",)
    return [f"{name}_{round(w * 1e9)}nm" for name, w in zip(names, config.wavelengths)]


def save_phase_pattern(pattern: PhasePattern, display: Display, labels: list[str], folder: Path) -> list[str]:
    """Per channel: the gray levels as PNG (8-bit up to 256 levels, else 16-bit) and the
    unquantised phase (rad) as float32 `.npy`. Returns the file names."""
    written = []
    for label, gray, phase in zip(labels, pattern.gray, pattern.phase_rad):
        depth = np.uint8 if display.levels <= 256 else np.uint16
        Image.fromarray(gray.cpu().numpy().astype(depth)).save(folder / f"phase_{label}.png")
        np.save(folder / f"phase_{label}.npy", phase.cpu().numpy().astype(np.float32))
        written += [f"phase_{label}.png", f"phase_{label}.npy"]
    return written


def export_display(config: FitConfig, encoding: Encoding | None = None, levels: int | None = None,
                   lut: tuple[float, ...] | None = None, aperture: float | None | str = "auto",
                   canvas: tuple[int, int] | None = None) -> Display:
    """The phase-only display that `export_run` writes for: the run's own where it was fitted through one, else
    DPAC with its default aperture; each setting given replaces its own (None, `auto`: not given; `aperture`
    None: no filter). A new encoding takes its own default aperture, and given `levels` uniform levels."""
    base = config.display if config.display.phase_only else Display.create("dpac")
    encoding = encoding or base.encoding
    if lut is None and levels is None:
        lut = base.lut
    if aperture == "auto" and encoding == base.encoding:
        aperture = base.aperture
    return Display.create(encoding, levels if levels is not None or lut is not None else base.levels, lut,
                          aperture, canvas or base.canvas)


def export_run(folder: str | Path, encoding: Encoding | None = None, levels: int | None = None,
               slm: tuple[int, int] | None = None, aperture: float | None | str = "auto",
               out: str | Path | None = None, model: str | Path | None = None, device: str = "cpu",
               lut: tuple[float, ...] | None = None, control: RunControl = SILENT) -> dict[str, Any]:
    """Write a run's phase-only SLM patterns and simulate showing them (method.md §8), rendered on `device`;
    `model` replaces the run's own model (e.g. a compressed file in the run folder).

    The display is `export_display`'s (the run's own, for a run fitted through one: the very patterns the fit
    optimised, and the display the fit's metrics measured); `slm` is the SLM's (W, H) in px (default: the
    hologram's own size). Writes the patterns, the simulated display's planes and `metrics.json` (phase-only
    display, the complex field on the same canvas behind the same 4f aperture, and the complex field as method.md
    §3 reconstructs it, all against the targets). `control` is asked between the stages (`RunControl.check`).
    """
    folder = Path(folder)
    out = Path(out) if out is not None else folder / EXPORT_FOLDER
    primitives, config, source = load_run_model(folder, model, device)
    display = export_display(config, encoding, levels, lut, aperture, None if slm is None else (slm[1], slm[0]))
    shown_config = config.replace(display=display)
    shown_config.validate()
    out.mkdir(parents=True, exist_ok=True)
    scene = scene_from_source(source, config)
    complex_config = config.replace(display=Display())
    control.check()
    hologram, complex_recon = render(primitives, complex_config)
    with torch.no_grad():
        pattern = phase_pattern(slm_field(hologram), display)
        control.check()
        shown = reconstruct(hologram, shown_config)
        control.check()
        complex_shown = reconstruct(hologram, config.replace(display=Display(aperture=display.aperture,
                                                                             canvas=display.canvas)))
    control.check()
    files = save_phase_pattern(pattern, display, channel_labels(config), out)
    for plane, image in enumerate(shown):
        to_8bit(image).save(out / f"display_plane{plane}.png")
        files.append(f"display_plane{plane}.png")
    record = {"display": display.to_dict(), "encoding": display.encoding, "levels": display.levels,
              "slm_px": list(slm) if slm else None,
              "hologram_px": [config.targets.width, config.targets.height], "aperture_of_nyquist": display.aperture,
              "files": files,
              "phase_only_display": evaluate(shown, scene.targets).to_dict(),
              "complex_display": evaluate(complex_shown, scene.targets).to_dict(),
              "complex_field": evaluate(complex_recon, scene.targets).to_dict()}
    write_json(out / METRICS_FILE, record)
    return record


def model_path(target: str | Path) -> Path:
    """A model file, or the model of a run folder."""
    target = Path(target)
    return target / MODEL_FILE if target.is_dir() else target


def half_precision_model(folder: str | Path) -> dict[str, Any]:
    """Store a run's model in float16 next to it and measure what that costs in PSNR (dB). The run's inputs are
    read first, so that a run whose targets cannot be rebuilt gets no copy."""
    folder = Path(folder)
    primitives, config, source = load_run_model(folder)
    scene = scene_from_source(source, config)
    psnr_full = mean_psnr(render(primitives, config)[1], scene.targets)
    save_model(folder / HALF_MODEL_FILE, primitives, config, dtype="float16", run=model_run(folder / MODEL_FILE))
    half, _ = load_model(folder / HALF_MODEL_FILE)
    psnr_half = mean_psnr(render(half, config)[1], scene.targets)
    return {**model_info(folder / HALF_MODEL_FILE), "psnr_float32": psnr_full, "psnr_float16": psnr_half,
            "psnr_change": psnr_half - psnr_full}


def rescaled(primitives: Primitives, config: FitConfig, width: int, height: int) -> tuple[Primitives, FitConfig]:
    """The same physical hologram sampled on a W×H grid: positions and scales scale with the grid,
    the pixel pitch shrinks by as much, curvature (1/m) stays. Refuses another aspect ratio."""
    require_gaussians(config, "`size` (a render at another sampling)", "render it at its own "
                      f"{config.targets.width}×{config.targets.height} px")
    if min(width, height) < MIN_SIZE_PX:
        raise ConfigError(f"`size` {width}×{height}: each side needs at least {MIN_SIZE_PX} px")
    factor = width / config.targets.width
    if abs(height / config.targets.height - factor) > 0.01 * factor:
        raise ConfigError(f"size {width}×{height} changes the aspect ratio of the {config.targets.width}×"
                          f"{config.targets.height} model; keep W/H = "
                          f"{config.targets.width / config.targets.height:.4f} (`size`)")
    check_sampling(config.wavelengths, config.optics.pixel_pitch / factor, f"`size` {width}×{height}",
                   f"give a smaller `size` (the model's pitch is {config.optics.pixel_pitch:g} m at "
                   f"{config.targets.width}×{config.targets.height})")
    values = primitives.tensors()
    values["position_px"] = (values["position_px"] + 0.5) * factor - 0.5
    values["scale_px"] = values["scale_px"] * factor
    return Primitives.from_tensors(values), config.replace(
        width=width, height=height, pixel_pitch=config.optics.pixel_pitch / factor, num_gaussians=primitives.count)


def reconstruction_file(distance_m: float) -> str:
    """The file `render_model` writes the reconstruction at `distance_m` (m) to, named in mm to 6 digits."""
    return f"recon_{distance_m * 1e3:g}mm.png"


def check_distinct_files(distances_m: Sequence[float]) -> None:
    """Refuse distances (m) that `render_model` would write to one file (`reconstruction_file`)."""
    seen: dict[str, float] = {}
    for distance in distances_m:
        name = reconstruction_file(distance)
        if name in seen:
            raise InputError(f"`distance` {seen[name]:.12g} and {distance:.12g} m would both be written to {name}; "
                             "give distinct distances (they are named in mm to 6 digits)")
        seen[name] = distance


def render_model(target: str | Path, out: str | Path, size: tuple[int, int] | None = None,
                 distances_m: Sequence[float] | None = None, device: str = "cpu",
                 control: RunControl = SILENT) -> dict[str, Any]:
    """Render a saved model on `device` without fitting: hologram images and the reconstruction at each
    plane (the model's own, or `distances_m`), optionally resampled to `size` (W, H) px. A run folder's
    model must belong to it (`load_run_model`). `control` is asked between the stages and the frames
    (`RunControl.check`)."""
    if Path(target).is_dir():
        primitives, config, _ = load_run_model(target, device=device)
    else:
        primitives, config = load_model(target, device)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if size is not None:
        primitives, config = rescaled(primitives, config, *size)
    distances = config.plane_distances if distances_m is None else tuple(distances_m)
    control.check()
    field, recon = render(primitives, config, distances)
    control.check()
    save_hologram_images(field, out)
    files = ["amplitude.png", "phase.png"]
    for distance, image in zip(distances, recon):
        control.check()
        name = reconstruction_file(distance)
        to_8bit(image).save(out / name)
        files.append(name)
    return {"hologram_px": [config.targets.width, config.targets.height], "pixel_pitch_m": config.optics.pixel_pitch,
            "distances_m": list(distances), "files": files}
