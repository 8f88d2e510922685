"""Rate–distortion points of one fitted model: the `.cvq` codec at several bit budgets, the float32 and
float16 model files, and the still-image anchors of hologram compression (JPEG 2000 and JPEG XL via
`imagecodecs`, the `compression` extra) on the real and imaginary parts of the model's float32 field.

Rate is bits per hologram pixel (8·bytes / (W·H), all channels together); distortion is the mean
multi-plane PSNR (dB) and SSIM of the reconstructions against the run's targets.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from ..codec import BitDepths, decode, encode, file_bits
from ..config import FitConfig, RunOptions
from ..control import SILENT, RunControl
from ..defaults import ENCODE_FINETUNE_STEPS
from ..errors import ConfigError
from ..finetune import finetune
from ..fitting import hologram, render
from ..metrics import mean_psnr, mean_ssim
from ..optics import reconstruct
from ..primitives import Primitives
from ..app.provenance import machine_record
from ..app.encoding import encode_budget, encode_config, encode_in_folder, start_encode
from ..runs import CONFIG_FILE
from ..search import (LADDER, Budget, CompressionSettings, MaxDrop, Reference, prune, rate_control, search,
                      smallest_file)
from ..storage import load_model, save_model
from ..targets import Scene

JPEG2K_PSNRS = (30, 35, 40, 43, 46, 50, 55, 60, 70)  # OpenJPEG's quality layer, the planes' own PSNR in dB
JPEGXL_DISTANCES = (16.0, 12.0, 8.0, 4.0, 3.0, 2.0, 1.5, 1.0, 0.7, 0.5, 0.25)  # butteraugli distances, smaller is finer
RANGE_BYTES = 8  # float32 low and high per plane
# A cell's ladder points: the search's rungs from 3 bits coarser than the defaults to 6 finer, those every recorded
# cell holds (finer ones render as the float model does).
CELL_LADDER = LADDER[:LADDER.index(BitDepths().shifted(6)) + 1]
MAX_DROPS_DB = (0.1, 0.5)  # the `--max-drop` budgets of a benchmark cell (each search takes tens of renders)
# The rungs of `CELL_LADDER` that a cell fine-tunes: those whose drop without it lies in this range (dB). Rungs
# already within 0.1 dB gain nothing; rungs below 4 dB cannot be brought back within the fit's last decibel.
FINETUNED_DROPS_DB = (0.1, 4.0)
# The fractions of primitives that a cell prunes (least field energy first) before fine-tuning at the
# finest of those rungs: fewer primitives, each at the same bits.
PRUNE_FRACTIONS = (0.05, 0.1, 0.2)
# The wide BD-rate range: from 3 dB to 0.1 dB below the fit.
WIDE_RANGE_DB = (3.0, 0.1)
CODEC, FLOAT32, FLOAT16 = "cvqpg", "model float32", "model float16"
ENCODER = "cvqpg encode"  # `.cvq` files of a fit at the budget's primitive count, not of the cell's fit
ENCODER_RATE = "cvqpg encode --rate-loss"  # the same with the rate in the fit's loss (`ratefit`)
ENCODERS = (ENCODER, ENCODER_RATE)
ANCHORS = ("JPEG 2000", "JPEG XL")


@dataclass
class Point:
    """One rate–distortion point; times in s (encode, and decode + render of the planes); a `cvqpg encode` point
    also has the process's CPU seconds (all threads) over its encode time, which show how shared the cores were."""

    codec: str
    setting: str
    bytes: int
    bpp: float
    psnr: float
    ssim: float
    encode_s: float
    decode_s: float
    primitives: int | None = None  # in the file (None for the anchors, which code a field)
    budget_bpp: float | None = None  # the `--bpp` budget that rate control was given
    encode_cpu_s: float | None = None


def _score(recon: Tensor, targets: Tensor) -> tuple[float, float]:
    return mean_psnr(recon, targets), mean_ssim(recon, targets)


def _point(codec: str, setting: str, size: int, config: FitConfig, recon: Tensor, targets: Tensor,
           encode_s: float, decode_s: float, primitives: int | None = None) -> Point:
    pixels = config.targets.width * config.targets.height
    return Point(codec, setting, size, 8 * size / pixels, *_score(recon, targets),
                 encode_s, decode_s, primitives)


def _decoded_point(codec: str, setting: str, data: bytes, config: FitConfig, targets: Tensor,
                   encode_s: float) -> Point:
    """The point of a `.cvq` file's bytes, decoded and rendered as a reader would (timed)."""
    started = time.perf_counter()
    decoded = decode(data).primitives
    recon = render(decoded, config)[1]
    return _point(codec, setting, len(data), config, recon, targets, encode_s, time.perf_counter() - started,
                  decoded.count)


def _describe(bits: BitDepths, config: FitConfig) -> str:
    """The depths a file of `config` codes, as `--bits` takes them."""
    return " ".join(f"{k}={v}" for k, v in file_bits(bits, config).items())


def codec_points(primitives: Primitives, config: FitConfig, targets: Tensor,
                 ladder: Sequence[BitDepths] = CELL_LADDER) -> list[Point]:
    """The `.cvq` codec at each budget of `ladder`."""
    points = []
    for bits in ladder:
        started = time.perf_counter()
        data = encode(primitives, config, bits)
        points.append(_decoded_point(CODEC, _describe(bits, config), data, config, targets,
                                     time.perf_counter() - started))
    return points


def searched_points(primitives: Primitives, config: FitConfig, targets: Tensor, fit_psnr: float,
                    max_drops: Sequence[float] = MAX_DROPS_DB) -> list[Point]:
    """The `.cvq` codec at the budgets that `cvqpg compress --max-drop D` picks (per-attribute search,
    no fine-tuning), one point per distinct budget; the search counts as encoding time."""
    reference = Reference(targets, "the run's targets", fit_psnr)
    points, seen = [], set()
    for max_drop in max_drops:
        started = time.perf_counter()
        choice = search(primitives, config, reference, MaxDrop(max_drop))
        searched = time.perf_counter() - started
        if choice.bits not in seen:
            seen.add(choice.bits)
            points.append(_decoded_point(CODEC, f"--max-drop {max_drop:g}: {_describe(choice.bits, config)}",
                                         choice.data, config, targets, searched))
    return points


def finetuned_points(primitives: Primitives, config: FitConfig, scene: Scene, fit_psnr: float, steps: int,
                     ladder: Sequence[BitDepths], untuned: Sequence[Point],
                     prune_fractions: Sequence[float] = PRUNE_FRACTIONS) -> list[Point]:
    """The `.cvq` codec after `steps` steps of quantisation-aware fine-tuning on the run's own targets, at
    each rung of `ladder` whose drop without it (`untuned`, the points of `codec_points` in ladder
    order) lies within `FINETUNED_DROPS_DB`, and at the finest of those rungs after pruning each of
    `prune_fractions` of the primitives (`search.prune`). Fine-tuning counts as encoding time."""
    low, high = FINETUNED_DROPS_DB
    rungs = [bits for bits, point in zip(ladder, untuned) if low < fit_psnr - point.psnr <= high]
    settings = [(bits, 0.0) for bits in rungs] + [(rungs[-1], fraction) for fraction in prune_fractions if rungs]
    points = []
    for bits, fraction in settings:
        started = time.perf_counter()
        data = encode(finetune(prune(primitives, fraction), config, scene, bits, steps), config, bits)
        label = (f"--prune {fraction:g} " if fraction else "") + f"--finetune {steps}: {_describe(bits, config)}"
        points.append(_decoded_point(CODEC, label, data, config, scene.targets, time.perf_counter() - started))
    return points


def budget_points(primitives: Primitives, config: FitConfig, scene: Scene, fit_psnr: float,
                  budgets_bpp: Sequence[float], steps: int) -> list[Point]:
    """The `.cvq` codec at each budget of `budgets_bpp` (bits per hologram pixel) as `cvqpg compress --bpp`
    writes it (`search.rate_control`: primitives and bit depths chosen for the budget, then `steps` of
    quantisation-aware fine-tuning on the scene's targets), the whole rate control counted as encoding time.
    Budgets below the smallest file the format can write of the model get no point."""
    reference = Reference(scene.targets, "the run's targets", fit_psnr)
    smallest = smallest_file(primitives, config)
    points = []
    for bpp in budgets_bpp:
        budget = Budget.of(config, bpp=bpp)
        if budget.max_bytes < smallest:
            continue
        started = time.perf_counter()
        chosen = rate_control(primitives, config, reference, budget, scene, steps).choice
        point = _decoded_point(CODEC, f"--bpp {bpp:.3f}: {_describe(chosen.bits, config)}", chosen.data, config,
                               scene.targets, time.perf_counter() - started)
        point.budget_bpp = bpp
        points.append(point)
    return points


def encode_point(scene: Scene, config: FitConfig, source: dict[str, Any], bpp: float, work: Path,
                 finetune_steps: int = ENCODE_FINETUNE_STEPS, run: RunOptions = RunOptions(),
                 control: RunControl = SILENT, rate_loss: bool = False) -> Point | None:
    """The file `cvqpg encode --bpp` (with `rate_loss`, `--rate-loss`: labelled `ENCODER_RATE`) writes of `scene`
    (its inputs `source`) with `config`'s settings: a fit at the
    budget's primitive count in the folder `work` (`app.encoding.encode_in_folder`), rate control and
    `finetune_steps` of fine-tuning; None where the budget is below the smallest file of a model of the fit's
    shape. The fit (on `run`), or its rate control, raises `fitting.FitInterrupted` once `control` asks to stop, with
    a checkpoint saved, from which the same call resumes; `work` is removed once the point is made. Its encode time is
    the fit's, over every segment, and the rate control's (`app.encoding.Encoding.seconds`), wall and CPU."""
    settings = CompressionSettings(bpp=bpp, rate_loss=rate_loss)
    try:
        budget = encode_budget(config, settings)
    except ConfigError:
        return None
    fit_config, fit = encode_config(config, budget), settings.rate_fit(budget)
    if not (work / CONFIG_FILE).is_file():
        start_encode(work, fit_config, source, budget, finetune_steps, run, fit)
    encoded = encode_in_folder(work, scene, fit_config, budget, finetune_steps, run, control.quiet(), fit=fit)
    chosen = encoded.rate.choice
    point = _decoded_point(ENCODER_RATE if rate_loss else ENCODER,
                           f"--bpp {bpp:.3f}: {fit_config.primitive_count} fitted, {_describe(chosen.bits, config)}",
                           chosen.data, config, scene.targets, encoded.seconds)
    point.budget_bpp, point.encode_cpu_s = bpp, encoded.cpu_seconds
    shutil.rmtree(work)
    return point


def rate_base(record: dict[str, Any]) -> float:
    """The rate (bpp) that a rate grid cell's `--bpp` budgets are fractions of (`budgets_for`), read back from
    its record: its first budget, that of the largest fraction, which no model's smallest file exceeds."""
    first = next((point for point in record["points"] if point.get("budget_bpp") is not None), None)
    if first is None or not record.get("budget_fractions"):
        raise ValueError("the record holds no `--bpp` budget points (not a rate grid cell)")
    return first["budget_bpp"] / record["budget_fractions"][0]


def budgets_for(ladder_points: Sequence[Point], fit_psnr: float, fractions: Sequence[float]) -> list[float]:
    """`fractions` of the rate (bpp) of the smallest ladder file within 0.1 dB of the fit (the finest rung's
    where none is)."""
    held = [point for point in ladder_points if point.psnr >= fit_psnr - 0.1]
    base = min(held, key=lambda point: point.bytes) if held else max(ladder_points, key=lambda point: point.bytes)
    return [fraction * base.bpp for fraction in fractions]


def model_file_points(primitives: Primitives, config: FitConfig, targets: Tensor) -> list[Point]:
    """The float32 and float16 `model.safetensors` files."""
    points = []
    with tempfile.TemporaryDirectory(prefix="cvqpg-rd-") as scratch:
        for dtype in ("float32", "float16"):
            path = Path(scratch) / f"model.{dtype}.safetensors"
            started = time.perf_counter()
            save_model(path, primitives, config, dtype)
            encoded = time.perf_counter()
            loaded, _ = load_model(path)
            recon = render(loaded, config)[1]
            points.append(_point(FLOAT32 if dtype == "float32" else FLOAT16, "safetensors", path.stat().st_size,
                                 config, recon, targets, encoded - started, time.perf_counter() - encoded,
                                 loaded.count))
    return points


def _planes(field: Tensor) -> list[np.ndarray]:
    """Real and imaginary parts of each channel, float64 [H, W]."""
    array = field.detach().cpu().numpy()
    return [part.astype(np.float64) for channel in array for part in (channel.real, channel.imag)]


def _field(planes: list[np.ndarray], channels: int) -> Tensor:
    return torch.from_numpy(np.stack([planes[2 * c] + 1j * planes[2 * c + 1] for c in range(channels)])
                            .astype(np.complex64))


def anchor_points(primitives: Primitives, config: FitConfig, targets: Tensor,
                  settings: dict[str, Sequence[Any]] | None = None) -> list[Point]:
    """JPEG 2000 and JPEG XL on the model's float32 field: each real and imaginary plane mapped from
    its own [min, max] to 16 bits (the range, two float32, counted as side information)."""
    import imagecodecs

    codecs: dict[str, tuple[Callable[[np.ndarray, Any], bytes], Callable[[bytes], np.ndarray]]] = {
        "JPEG 2000": (lambda plane, psnr: imagecodecs.jpeg2k_encode(plane, level=psnr, codecformat="j2k"),
                      imagecodecs.jpeg2k_decode),
        "JPEG XL": (lambda plane, distance: imagecodecs.jpegxl_encode(plane, distance=distance),
                    imagecodecs.jpegxl_decode)}
    settings = settings or {"JPEG 2000": JPEG2K_PSNRS, "JPEG XL": JPEGXL_DISTANCES}
    with torch.no_grad():
        planes = _planes(hologram(primitives, config))
    ranges = [(plane.min(), plane.max()) for plane in planes]
    quantised = [np.rint((plane - low) / max(high - low, 1e-30) * 65535).astype(np.uint16)
                 for plane, (low, high) in zip(planes, ranges)]
    points = []
    for codec, values in settings.items():
        encoder, decoder = codecs[codec]
        for value in values:
            started = time.perf_counter()
            streams = [encoder(plane, value) for plane in quantised]
            encoded = time.perf_counter()
            decoded = [low + decoder(stream).astype(np.float64) / 65535 * (high - low)
                       for stream, (low, high) in zip(streams, ranges)]
            with torch.no_grad():
                recon = reconstruct(_field(decoded, config.channels), config)
            size = sum(len(s) for s in streams) + RANGE_BYTES * len(streams)
            points.append(_point(codec, str(value), size, config, recon, targets, encoded - started,
                                 time.perf_counter() - encoded))
    return points


def rd_points(primitives: Primitives, config: FitConfig, targets: Tensor, ladder: Sequence[BitDepths] = CELL_LADDER,
              anchors: bool = True) -> list[dict[str, Any]]:
    """All R-D points of one model against `targets` [M, C, H, W], as plain dicts (for JSON and tables)."""
    points = [*model_file_points(primitives, config, targets), *codec_points(primitives, config, targets, ladder)]
    if anchors:
        points += anchor_points(primitives, config, targets)
    return [asdict(p) for p in points]


def cell_record(model_file: Path, scene: Scene, ladder: Sequence[BitDepths] = CELL_LADDER,
                max_drops: Sequence[float] = MAX_DROPS_DB, finetune_steps: int = 0,
                budget_fractions: Sequence[float] = (), budget_finetune_steps: int = 0) -> dict[str, Any]:
    """A benchmark cell's R-D record (`rd.json`) for the model in `model_file` against the scene's
    targets: the float32 and float16 model files, the codec at each rung of `ladder`, the anchors, the
    codec at the `--max-drop` budgets, and with `finetune_steps` > 0 the codec fine-tuned, and pruned
    and fine-tuned, at some rungs (`finetuned_points`); with `budget_fractions`, the codec at those fractions of
    the rate of its smallest ladder file within 0.1 dB (`budgets_for`), rate-controlled and fine-tuned for
    `budget_finetune_steps` (`budget_points`); the fit's own PSNR; and how long it all took
    on which machine at which load (wall and process CPU seconds: their ratio shows how shared the
    cores were)."""
    primitives, config = load_model(model_file)
    targets = scene.targets
    started, cpu_started = time.perf_counter(), time.process_time()
    render(primitives, config)  # compiles the kernels, so that no point's decode time includes it
    fit_psnr = mean_psnr(render(primitives, config)[1], targets)
    ladder_points = codec_points(primitives, config, targets, ladder)
    points = [*model_file_points(primitives, config, targets), *ladder_points,
              *anchor_points(primitives, config, targets),
              *searched_points(primitives, config, targets, fit_psnr, max_drops)]
    if finetune_steps:
        points += finetuned_points(primitives, config, scene, fit_psnr, finetune_steps, ladder, ladder_points)
    if budget_fractions:
        points += budget_points(primitives, config, scene, fit_psnr,
                                budgets_for(ladder_points, fit_psnr, budget_fractions), budget_finetune_steps)
    return {"model_file": str(model_file), "model_bytes": model_file.stat().st_size, "fit_psnr": fit_psnr,
            "finetune_steps": finetune_steps, "prune_fractions": list(PRUNE_FRACTIONS) if finetune_steps else [],
            "budget_fractions": list(budget_fractions), "budget_finetune_steps": budget_finetune_steps,
            "points": [asdict(p) for p in points],
            "seconds": time.perf_counter() - started, "cpu_seconds": time.process_time() - cpu_started,
            "run": machine_record(primitives.position_px.device)}


def pareto(points: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The points that no cheaper point matches in PSNR, by increasing rate (and so increasing PSNR)."""
    front: list[dict[str, Any]] = []
    for point in sorted(points, key=lambda p: (p["bpp"], -p["psnr"])):
        if not front or point["psnr"] > front[-1]["psnr"]:
            front.append(point)
    return front


@dataclass
class BdRate:
    """BD-rate (%) of a test codec against an anchor over PSNR `low`..`high` (dB); negative: fewer bits."""

    percent: float
    low: float
    high: float


def bd_rate(anchor: Sequence[dict[str, Any]], test: Sequence[dict[str, Any]], top_psnr: float,
            span_db: float = 1.0) -> BdRate | None:
    """BD-rate of `test` against `anchor` (points as `rd_points` gives them) over PSNR from
    `top_psnr` − `span_db` to `top_psnr`, narrowed to where both Pareto fronts have points; None
    where they share no such range or a front has fewer than two points.

    log10(bpp) is interpolated over PSNR with `bjontegaard`'s PCHIP interpolators (its own default
    integrates over the curves' whole overlap; here the range is ours), then averaged over the range.
    """
    import bjontegaard

    fronts = [pareto(anchor), pareto(test)]
    if min(len(front) for front in fronts) < 2:
        return None
    low = max(top_psnr - span_db, *(front[0]["psnr"] for front in fronts))
    high = min(top_psnr, *(front[-1]["psnr"] for front in fronts))
    if high <= low:
        return None
    (rate_a, psnr_a), (rate_t, psnr_t) = ([[p[k] for p in front] for k in ("bpp", "psnr")] for front in fronts)
    _, f_anchor, f_test = bjontegaard.bd_rate(rate_a, psnr_a, rate_t, psnr_t, method="pchip",
                                              require_matching_points=False, interpolators=True, min_overlap=0)
    mean_log_ratio = (f_test.integrate(low, high) - f_anchor.integrate(low, high)) / (high - low)
    return BdRate(float((10**mean_log_ratio - 1) * 100), low, high)


def smallest_within(points: Sequence[dict[str, Any]], top_psnr: float, drop_db: float) -> dict[str, Any] | None:
    """The smallest point at most `drop_db` below `top_psnr`, or None."""
    held = [p for p in points if p["psnr"] >= top_psnr - drop_db]
    return min(held, key=lambda p: p["bytes"]) if held else None


def _by_codec(record: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    by_codec: dict[str, list[dict[str, Any]]] = {}
    for point in record["points"]:
        by_codec.setdefault(point["codec"], []).append(point)
    return by_codec


def _against_anchors(by_codec: dict[str, list[dict[str, Any]]], top_psnr: float, span_db: float,
                     codecs: Sequence[str] = (CODEC,)) -> tuple[dict[str, BdRate | None], str | None]:
    """The BD-rate of the points of `codecs` together against each anchor over `span_db` below `top_psnr`
    (`bd_rate`), and the better anchor: the one against which they save least (None where no BD-rate could be
    taken)."""
    tested = [point for codec in codecs for point in by_codec.get(codec, [])]
    rates = {anchor: bd_rate(by_codec.get(anchor, []), tested, top_psnr, span_db) for anchor in ANCHORS}
    known = {anchor: rate for anchor, rate in rates.items() if rate is not None}
    return rates, max(known, key=lambda anchor: known[anchor].percent) if known else None


def cell_summary(record: dict[str, Any], span_db: float = 1.0, drop_db: float = 0.1) -> dict[str, Any]:
    """What the tables show of one cell's record: the codec's BD-rate against each anchor and against
    the better one (the anchor against which the codec saves least), and the smallest files within
    `drop_db` of the fit, the codec's as a fraction of the fit's `model.safetensors`, with its times."""
    by_codec = _by_codec(record)
    top = record["fit_psnr"]
    rates, better = _against_anchors(by_codec, top, span_db)
    float32 = by_codec[FLOAT32][0]
    held = {codec: smallest_within(by_codec.get(codec, []), top, drop_db) for codec in (CODEC, *ANCHORS)}
    codec_point = held[CODEC]
    return {"fit_psnr": top, "bd_rate": rates, "better_anchor": better,
            "held": held, "float32_decode_s": float32["decode_s"],
            "fraction": None if codec_point is None else codec_point["bytes"] / record["model_bytes"]}


def _interpolated(xs: Sequence[float], ys: Sequence[float], x: float) -> float | None:
    """y at `x` on the polyline through (xs, ys), xs increasing; None outside it."""
    if not xs or not xs[0] <= x <= xs[-1]:
        return None
    return float(np.interp(x, xs, ys))


def psnr_at_rate(points: Sequence[dict[str, Any]], bpp: float) -> float | None:
    """PSNR (dB) of the Pareto front of `points` at `bpp`, linear in log(bpp) between its points."""
    front = pareto(points)
    return _interpolated([math.log(p["bpp"]) for p in front], [p["psnr"] for p in front], math.log(bpp))


def rate_at_psnr(points: Sequence[dict[str, Any]], psnr: float) -> float | None:
    """bpp of the Pareto front of `points` at `psnr` (dB), linear in log(bpp) between its points."""
    front = pareto(points)
    log_rate = _interpolated([p["psnr"] for p in front], [math.log(p["bpp"]) for p in front], psnr)
    return None if log_rate is None else math.exp(log_rate)


@dataclass
class EqualRate:
    """At the rate `bpp` where the anchor's front is `drop_db` below the fit, the codec's PSNR and its gain."""

    bpp: float
    drop_db: float
    codec_psnr: float
    gain_db: float


def equal_rate_gain(anchor: Sequence[dict[str, Any]], codec: Sequence[dict[str, Any]], top_psnr: float,
                    drop_db: float = 2.0) -> EqualRate | None:
    """The codec's PSNR above the anchor's at the rate where the anchor reaches `top_psnr` − `drop_db`; None
    where either front does not reach there."""
    rate = rate_at_psnr(anchor, top_psnr - drop_db)
    psnr = None if rate is None else psnr_at_rate(codec, rate)
    return None if psnr is None else EqualRate(rate, drop_db, psnr, psnr - (top_psnr - drop_db))


def budget_fill(point: dict[str, Any]) -> float:
    """A rate-controlled point's bytes as a share of its budget's ⌊bpp·W·H/8⌋ bytes (1 at most, honestly)."""
    pixels = round(8 * point["bytes"] / point["bpp"])
    return point["bytes"] / math.floor(point["budget_bpp"] * pixels / 8)


def wide_summary(record: dict[str, Any], drop_db: float = 2.0) -> dict[str, Any]:
    """What the rate grid's tables show of one cell (`--preset rate`): the codec's BD-rate over
    `WIDE_RANGE_DB` below the fit against each anchor and the better one, its gain over JPEG XL at JPEG XL's
    rate `drop_db` below the fit, and its rate-controlled points: their budget fill, primitive counts and
    encode seconds. Where the cell has `cvqpg encode` points (`--preset encode`), also the BD-rate against the
    better anchor and the gain of the codec's points and those together; the budget fills, primitive counts,
    point count and deepest point then count those points as well."""
    by_codec = _by_codec(record)
    top, (deepest, shallowest) = record["fit_psnr"], WIDE_RANGE_DB
    codec = by_codec.get(CODEC, [])
    rates, better = _against_anchors(by_codec, top - shallowest, deepest - shallowest)
    budgeted = [point for point in codec if point.get("budget_bpp") is not None]
    encoded = by_codec.get(ENCODER, [])
    bd_with_encoder = equal_with_encoder = None
    if encoded:
        both, better_of_both = _against_anchors(by_codec, top - shallowest, deepest - shallowest, (CODEC, ENCODER))
        bd_with_encoder = both[better_of_both] if better_of_both else None
        equal_with_encoder = equal_rate_gain(by_codec.get("JPEG XL", []), codec + encoded, top, drop_db)
    return {"fit_psnr": top, "bd_rate": rates, "better_anchor": better,
            "equal_rate": equal_rate_gain(by_codec.get("JPEG XL", []), codec, top, drop_db),
            "encoded": encoded, "bd_rate_with_encoder": bd_with_encoder, "equal_rate_with_encoder": equal_with_encoder,
            "fills": [budget_fill(point) for point in budgeted + encoded],
            "counts": sorted({point["primitives"] for point in codec + encoded if point.get("primitives") is not None}),
            "points": len(codec + encoded),
            "deepest_db": top - min((point["psnr"] for point in codec + encoded), default=top),
            "budgeted": budgeted}
