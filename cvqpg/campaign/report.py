"""Tables, CSVs, figures and `report.html` of a bench folder, from whatever cells are finished.

Our numbers are means over finished seeds, then over scenes. Next to them, in parentheses, are the
paper's per-scene values (supplementary table) averaged over the same scenes, shown only where our
fits use the paper's setup (640×480, 2 planes, 2000 steps). The ablation table's paper values are
its own five-scene means (the paper does not name those scenes). Unavailable metrics read "n/a".
"""

from __future__ import annotations

import csv
import functools
import html
import io
import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from . import figures
from .bench import (CELLS_DIR, DONE, ENCODE_FILE, EXPORTED_KEY, METHODS, METRICS_FILE, PRESETS, RD_FILE, SPECTRUM_FILE, BenchPlan,
                    Cell, setting_label)
from ..errors import InputError
from ..runs import read_record, write_atomic
from ..defaults import VIEW_FILE

TABLE_METRICS = ("psnr", "ssim", "lpips", "flip", "cvvdp")
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False, "flip": False, "cvvdp": True}
DECIMALS = {"psnr": 3, "ssim": 4, "lpips": 4, "flip": 4, "cvvdp": 3}
HEADINGS = {m: f"{m.upper()}{'↑' if up else '↓'}" for m, up in HIGHER_IS_BETTER.items()}
PAPER_SETUP = {"width": 640, "height": 480, "num_planes": 2, "steps": 2000}
ABLATION_VARIANTS = ("no-bound", "no-mahalanobis", "vanilla")
TABLE1_METHODS = ("baseline", "baseline+", "cvqpg")
CHANNEL_NAMES = ("red", "green", "blue")
NA, MISSING = "n/a", "–"

Metrics = dict[str, float | None]

# What the tables read of each cell record; `a.b` is required where `a` is present (listed, `a` is required).
RUN_RECORD_KEYS = ("commit", "device", "torch_threads", "numba_threads", "loop_seconds", "peak_memory_bytes")
RECORD_KEYS = {METRICS_FILE: ("mean", *(f"mean.{m}" for m in TABLE_METRICS), *(f"run.{k}" for k in RUN_RECORD_KEYS)),
               SPECTRUM_FILE: ("edges", "power"),
               RD_FILE: ("points", "fit_psnr", "model_bytes", "run", "run.load_average"),
               ENCODE_FILE: ("points", "run")}
RESTORE_CELL = "restore it, or delete the cell folder to fit the cell again"


@dataclass
class CellResult:
    """A cell of the plan with what its folder holds."""

    cell: Cell
    status: str
    metrics: dict[str, Any] | None
    spectrum: dict[str, Any] | None
    rd: dict[str, Any] | None = None


@dataclass
class Table:
    """A table rendered alike as Markdown and HTML; `bold` holds (row, column) positions, `links` their
    targets (paths relative to the bench folder)."""

    title: str
    header: list[str]
    rows: list[list[str]] = field(default_factory=list)
    bold: set[tuple[int, int]] = field(default_factory=set)
    links: dict[tuple[int, int], str] = field(default_factory=dict)
    note: str = ""

    def _cell(self, row: int, column: int, text: str, strong: str) -> str:
        text = f"{strong}{text}{strong.replace('<', '</')}" if (row, column) in self.bold else text
        link = self.links.get((row, column))
        if link is None:
            return text
        return f"<a href='{html.escape(link)}'>{text}</a>" if strong.startswith("<") else f"[{text}]({link})"

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(self.header) + " |",
                 "|" + "---|" * len(self.header)]
        lines += ["| " + " | ".join(self._cell(r, c, text, "**") for c, text in enumerate(row)) + " |"
                  for r, row in enumerate(self.rows)]
        return "\n".join(lines + ([f"\n{self.note}"] if self.note else [])) + "\n"

    def html(self) -> str:
        head = "".join(f"<th>{html.escape(h)}</th>" for h in self.header)
        body = "".join("<tr>" + "".join(f"<td>{self._cell(r, c, html.escape(text), '<b>')}</td>"
                                        for c, text in enumerate(row)) + "</tr>" for r, row in enumerate(self.rows))
        note = f"<p class='note'>{html.escape(self.note)}</p>" if self.note else ""
        return f"<h3>{html.escape(self.title)}</h3><table><tr>{head}</tr>{body}</table>{note}"


@functools.lru_cache(maxsize=1)
def paper_numbers() -> dict[str, Any]:
    """The paper's published numbers (`cvqpg/campaign/paper_numbers.json`)."""
    return json.loads(resources.files("cvqpg.campaign").joinpath("paper_numbers.json").read_text())


def read_cell_record(path: Path) -> dict[str, Any] | None:
    """A cell's `metrics.json`, `spectrum.json` or `rd.json`, or None where there is none; `InputError` naming
    it where it is not JSON or lacks what the tables read (`RECORD_KEYS`)."""
    if not path.is_file():
        return None
    record = read_record(path, RESTORE_CELL)
    missing = []
    for key in RECORD_KEYS[path.name]:
        parent, _, name = key.rpartition(".")
        holder = record.get(parent) if parent else record
        if (holder is not None or not parent) and (not isinstance(holder, dict) or name not in holder):
            missing.append(key)
    if missing:
        raise InputError(f"{path} lacks {', '.join(missing)}; {RESTORE_CELL}")
    return record


def rate_distortion_record(folder: Path) -> dict[str, Any] | None:
    """A rate–distortion cell's `rd.json`, with the points of its `encode.json` where the encode grid finished it."""
    record = read_cell_record(folder / RD_FILE)
    encoded = read_cell_record(folder / ENCODE_FILE)
    if record is None or encoded is None:
        return record
    return {**record, "points": record["points"] + encoded["points"]}


def collect(plan: BenchPlan) -> list[CellResult]:
    """Every cell of the plan with its status, and its metrics and spectrum once done. A cell whose method shows
    its model on a display after the fit (`Method.exported`) has that display's metrics as its own."""
    results = []
    for cell in plan.cells:
        folder = plan.cell_dir(cell)
        status = plan.status(folder)
        fitted = (folder / METRICS_FILE).is_file()
        metrics = read_cell_record(folder / METRICS_FILE) if fitted else None
        if metrics is not None and METHODS[cell.method].exported is not None:
            metrics = {**metrics, **{key: metrics.get(EXPORTED_KEY, {}).get(key)
                                     for key in ("mean", "per_plane", "unavailable")}}
        results.append(CellResult(cell, status, metrics, read_cell_record(folder / SPECTRUM_FILE) if fitted else None,
                                  rate_distortion_record(folder) if status == DONE else None))
    return results


def _mean(values: list[float | None]) -> float | None:
    """Mean, or None when there is nothing or any value is unavailable (never a zero)."""
    return None if not values or any(v is None for v in values) else float(np.mean(values))


def scene_values(results: list[CellResult], setting: str, method: str) -> dict[str, Metrics]:
    """Per scene, the metrics of its finished cells in `setting` and `method`, averaged over seeds."""
    by_scene: dict[str, list[Metrics]] = {}
    for r in results:
        if r.metrics is not None and r.cell.setting == setting and r.cell.method == method:
            by_scene.setdefault(r.cell.scene.name, []).append(r.metrics["mean"])
    return {scene: {m: _mean([v.get(m) for v in values]) for m in TABLE_METRICS} for scene, values in by_scene.items()}


def over_scenes(values: dict[str, Metrics], scenes: list[str]) -> Metrics | None:
    """Mean over `scenes`; None (shown as –, not n/a) when no scene has finished."""
    return {m: _mean([values[s][m] for s in scenes]) for m in TABLE_METRICS} if scenes else None


def _difference(a: Metrics, b: Metrics) -> Metrics:
    return {m: None if a[m] is None or b[m] is None else a[m] - b[m] for m in TABLE_METRICS}


def paper_setup(plan: BenchPlan, setting: str) -> bool:
    """Whether every cell of the setting is fitted the way the paper's numbers were."""
    return all(c.config.setting(k) == v for c in plan.cells if c.setting == setting for k, v in PAPER_SETUP.items())


def paper_scene_mean(scenes: list[str], setting: str, method: str) -> Metrics | None:
    """The paper's per-scene values averaged over `scenes`; None unless it lists all of them."""
    table = paper_numbers()["per_scene"]
    if not scenes or any(method not in table.get(s, {}).get(setting, {}) for s in scenes):
        return None
    return {m: float(np.mean([table[s][setting][method][m] for s in scenes])) for m in TABLE_METRICS}


def fmt(value: float | None, metric: str, signed: bool = False) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return NA
    return f"{value:{'+' if signed else ''}.{DECIMALS[metric]}f}"


def _with_paper(ours: Metrics | None, paper: Metrics | None, metric: str, signed: bool = False) -> str:
    if ours is None:
        return MISSING
    text = fmt(ours[metric], metric, signed)
    return text if paper is None else f"{text} ({fmt(paper[metric], metric, signed)})"


def _bold_best(table: Table, first_row: int, values: list[Metrics | None], first_column: int) -> None:
    """Bold the best value of each metric among `values` (rows from `first_row`), ties included."""
    for k, metric in enumerate(TABLE_METRICS):
        available = [(i, v[metric]) for i, v in enumerate(values) if v is not None and v[metric] is not None]
        if len(available) < 2:
            continue
        best = (max if HIGHER_IS_BETTER[metric] else min)(v for _, v in available)
        table.bold |= {(first_row + i, first_column + k) for i, v in available if v == best}


def primitive_count(plan: BenchPlan, setting: str, method: str) -> int:
    return next(c.config.primitive_count for c in plan.cells if c.setting == setting and c.method == method)


def setting_methods(plan: BenchPlan, setting: str) -> list[str]:
    """The plan's methods that have cells in `setting` (a grid need not fit every method everywhere)."""
    present = {c.method for c in plan.cells if c.setting == setting}
    return [m for m in plan.methods if m in present]


def shared_means(results: list[CellResult], setting: str, methods: list[str]
                 ) -> tuple[list[str], dict[str, Metrics | None]]:
    """The scenes finished in `setting` by every method of `methods` that has finished any, and each
    method's mean over them (None for a method with no finished cell): a table's rows are means over the
    same scenes, so that one row can be read against another."""
    finished = {m: scene_values(results, setting, m) for m in methods}
    started = [set(values) for values in finished.values() if values]
    scenes = sorted(set.intersection(*started)) if started else []
    return scenes, {m: over_scenes(values, scenes) if values else None for m, values in finished.items()}


def baseline_gain(means: dict[str, Metrics | None], method: str) -> Metrics | None:
    """`means[method]` − `means["baseline"]` per metric; None where either is missing."""
    ours, base = means.get(method), means.get("baseline")
    return None if ours is None or base is None else _difference(ours, base)


def waiting_note(results: list[CellResult], setting: str, methods: list[str], scenes: list[str]) -> str:
    """Says which finished cells a table's means leave out, until the other methods reach their scenes."""
    waiting = sum(len(set(scene_values(results, setting, m)) - set(scenes)) for m in methods)
    if not waiting:
        return ""
    return (f"{setting_label(setting)}: means over the scenes every method has finished ({', '.join(scenes)}); "
            f"{waiting} more finished cell{'s' * (waiting != 1)} join{'s' * (waiting == 1)} them once the other "
            "methods finish their scenes.")


def main_table(plan: BenchPlan, results: list[CellResult]) -> tuple[Table, list[dict[str, Any]]]:
    """Table 1's layout: per setting and method N and the mean metrics over the scenes every method has
    finished, and Δ of CVQPG over the baseline on them. Also the same rows for `summary.csv`."""
    table = Table("Mean over scenes (Table 1 layout); in parentheses: the paper, same scenes",
                  ["Setting", "Method", "N", "scenes", *(HEADINGS[m] for m in TABLE_METRICS)])
    rows: list[dict[str, Any]] = []
    notes = []
    for setting in plan.settings:
        comparable = paper_setup(plan, setting)
        methods = setting_methods(plan, setting)
        scenes, means = shared_means(results, setting, methods)
        papers = {}
        for method in methods:
            ours = means[method]
            paper = papers[method] = paper_scene_mean(scenes, setting, method) if comparable and ours else None
            used = len(scenes) if ours else 0
            table.rows.append([setting_label(setting), METHODS[method].label,
                               f"{primitive_count(plan, setting, method):,}", f"{used}/{len(plan.scenes)}",
                               *(_with_paper(ours, paper, m) for m in TABLE_METRICS)])
            rows.append(_csv_row(setting, method, primitive_count(plan, setting, method), used, ours, paper))
        _bold_best(table, len(table.rows) - len(methods), list(means.values()), 4)
        notes.append(waiting_note(results, setting, methods, scenes))
        if {"baseline", "cvqpg"} <= set(methods):
            delta, paper_delta = baseline_gain(means, "cvqpg"), baseline_gain(papers, "cvqpg")
            used = len(scenes) if delta else 0
            table.rows.append([setting_label(setting), "Δ (CVQPG − Baseline)", "", f"{used}/{len(plan.scenes)}",
                               *(_with_paper(delta, paper_delta, m, signed=True) for m in TABLE_METRICS)])
            rows.append(_csv_row(setting, "delta cvqpg-baseline", None, used, delta, paper_delta))
    table.note = " ".join(note for note in notes if note)
    return table, rows


def paired_delta(results: list[CellResult], setting: str, method: str, comparable: bool
                 ) -> tuple[Metrics | None, Metrics | None, list[str]]:
    """Mean over the scenes finished for both of (method − baseline), ours and the paper's, and those scenes."""
    ours, base = scene_values(results, setting, method), scene_values(results, setting, "baseline")
    scenes = sorted(set(ours) & set(base))
    delta = over_scenes({s: _difference(ours[s], base[s]) for s in scenes}, scenes)
    paper_method, paper_base = (paper_scene_mean(scenes, setting, m) for m in (method, "baseline"))
    paper = _difference(paper_method, paper_base) if comparable and paper_method and paper_base else None
    return delta, paper, scenes


def _csv_row(setting: str, method: str, n: int | None, scenes: int, ours: Metrics | None,
             paper: Metrics | None) -> dict[str, Any]:
    """A row of summary.csv: n/a for an unavailable metric; empty where no cell has finished or the paper has
    no comparable value."""
    row: dict[str, Any] = {"setting": setting, "method": method, "n": "" if n is None else n, "scenes": scenes}
    row |= {m: "" if ours is None else NA if ours[m] is None else ours[m] for m in TABLE_METRICS}
    row |= {f"paper_{m}": "" if paper is None else paper[m] for m in TABLE_METRICS}
    return row


def per_scene_table(plan: BenchPlan, results: list[CellResult]) -> Table:
    """The supplementary table's layout: per scene and setting, each metric for every method in turn."""
    order = " / ".join(METHODS[m].label for m in plan.methods)
    table = Table(f"Per scene (each cell: {order})", ["Scene", "Setting", "", *(HEADINGS[m] for m in TABLE_METRICS)])
    per_scene = paper_numbers()["per_scene"]
    for scene in plan.scenes:
        for setting in plan.settings:
            ours = [scene_values(results, setting, m).get(scene.name) for m in plan.methods]
            table.rows.append([scene.name, setting_label(setting), "ours", *_slashed(ours)])
            paper = per_scene.get(scene.name, {}).get(setting)
            if paper and paper_setup(plan, setting):
                table.rows.append(["", "", "paper", *_slashed([paper.get(m) for m in plan.methods])])
    if any(s.name == "star" for s in plan.scenes):
        base, ours = (paper_numbers()["star"]["methods"][m]["psnr"] for m in ("baseline", "cvqpg"))
        table.note = (f"Paper, Siemens star (single plane, grayscale, equal N): Baseline {base} dB, CVQPG {ours} dB, "
                      f"Δ {ours - base:+.2f} dB.")
    return table


def _slashed(values: list[Metrics | None]) -> list[str]:
    """Per metric, the methods' values joined by " / " (– for a method without a finished cell)."""
    return [" / ".join(MISSING if v is None else fmt(v[metric], metric) for v in values) for metric in TABLE_METRICS]


def variant_tables(plan: BenchPlan, results: list[CellResult]) -> list[Table]:
    """For grids beyond Table 1's methods (ablation, chromatic), per setting: Δ PSNR of every method over
    the baseline and the metrics, all over the scenes every method has finished; the paper's ablation values
    where they apply."""
    if set(plan.methods) <= set(TABLE1_METHODS):
        return []
    ablation = paper_numbers()["ablation"]
    comparable_methods = bool(set(ABLATION_VARIANTS) & set(plan.methods))
    tables = []
    for setting in plan.settings:
        comparable = comparable_methods and paper_setup(plan, setting) and setting == ablation["setting"]
        table = Table(f"Variants against the baseline, {setting_label(setting)}",
                      ["Variant", "N", "Δ PSNR", "scenes", *(HEADINGS[m] for m in TABLE_METRICS)])
        methods = setting_methods(plan, setting)
        scenes, means = shared_means(results, setting, methods)
        for method in methods:
            ours = means[method]
            paper = ablation["methods"].get(method) if comparable else None
            delta_text = MISSING
            if method != "baseline" and "baseline" in methods:
                delta = baseline_gain(means, method)
                paper_delta = None if paper is None else {
                    "psnr": paper["psnr"] - ablation["methods"]["baseline"]["psnr"]}
                delta_text = _with_paper(delta, paper_delta, "psnr", signed=True)
            table.rows.append([METHODS[method].label, f"{primitive_count(plan, setting, method):,}", delta_text,
                               f"{len(scenes) if ours else 0}/{len(plan.scenes)}",
                               *(_with_paper(ours, paper, m) for m in TABLE_METRICS)])
        _bold_best(table, 0, list(means.values()), 4)
        table.note = " ".join(note for note in (waiting_note(results, setting, methods, scenes),
                                                 "In parentheses: the paper's ablation, five-scene means."
                                                 if comparable else "") if note)
        tables.append(table)
    return tables


def seed_tables(plan: BenchPlan, results: list[CellResult]) -> list[Table]:
    """With several seeds: per setting and method the PSNR mean over scenes of each seed, and its spread."""
    if len(plan.seeds) < 2:
        return []
    header = ["Setting", "Method", *(f"seed {seed}" for seed in plan.seeds), "sd"]
    table = Table("Seed spread: PSNR mean over scenes per seed", header)
    for setting in plan.settings:
        per_seed = {seed: [r for r in results if r.cell.config.optimisation.seed == seed] for seed in plan.seeds}
        rows = {METHODS[m].label: [over_scenes(v, list(v)) for v in
                                   (scene_values(per_seed[seed], setting, m) for seed in plan.seeds)]
                for m in plan.methods}
        if {"baseline", "cvqpg"} <= set(plan.methods):
            rows["Δ (CVQPG − Baseline)"] = [paired_delta(per_seed[seed], setting, "cvqpg", False)[0]
                                            for seed in plan.seeds]
        for label, values in rows.items():
            psnr = [None if v is None else v["psnr"] for v in values]
            known = [v for v in psnr if v is not None]
            spread = float(np.std(known, ddof=1)) if len(known) > 1 else None
            signed = label.startswith("Δ")
            table.rows.append([setting_label(setting), label, *(MISSING if v is None else fmt(v, "psnr", signed)
                                                                for v in psnr), fmt(spread, "psnr")])
    return [table]


def cells_table(plan: BenchPlan, results: list[CellResult]) -> tuple[Table, list[dict[str, Any]]]:
    """Every cell: status, N, steps, updates, seconds and PSNR; a finished cell's name links to its view page
    (`cvqpg view`) where it has one."""
    table = Table("Cells", ["Cell", "Status", "N", "Steps", "Updates", "Seconds", "Device", "PSNR"])
    rows = []
    for r in results:
        m = r.metrics or {}
        row = {"cell": r.cell.name, "scene": r.cell.scene.name, "setting": r.cell.setting, "method": r.cell.method,
               "seed": r.cell.config.optimisation.seed, "status": r.status, "n": r.cell.config.primitive_count,
               "steps": m.get("steps", r.cell.config.optimisation.steps), "updates": m.get("updates", ""),
               "seconds": "" if "seconds" not in m else round(m["seconds"], 1), "device": fitted_on(r),
               **{k: "" if not m else NA if m["mean"][k] is None else m["mean"][k] for k in TABLE_METRICS}}
        rows.append(row)
        if r.status == DONE and (plan.cell_dir(r.cell) / VIEW_FILE).is_file():
            table.links[(len(table.rows), 0)] = f"{CELLS_DIR}/{r.cell.name}/{VIEW_FILE}"
        table.rows.append([row["cell"], r.status, f"{row['n']:,}", str(row["steps"]), str(row["updates"]),
                           str(row["seconds"]), row["device"], fmt(m["mean"]["psnr"], "psnr") if m else MISSING])
    return table, rows


def _bd_text(rate: Any, top: float, with_range: bool = False) -> str:
    if rate is None:
        return NA
    span = f" ({rate.low - top:+.2f}…{rate.high - top:+.2f} dB)" if with_range else ""
    return f"{rate.percent:+.1f}%{span}"


def _held_text(point: dict[str, Any] | None, top: float) -> str:
    return MISSING if point is None else f"{point['bpp']:.3f} ({point['psnr'] - top:+.3f} dB)"


def rate_distortion_table(plan: BenchPlan, results: list[CellResult]) -> tuple[list[Table], list[dict[str, Any]]]:
    """In a rate–distortion grid, per setting and scene (`rd.json`): the codec's BD-rate against each anchor
    and the better one, over the fit's own PSNR down to 1 dB below it; the smallest file within 0.1 dB of
    the fit as bpp and as a share of the float32 model file, beside the anchors'; its encode and decode +
    render seconds, beside loading and rendering the float32 model. Also the rows for `rd.csv`."""
    from .ratedistortion import ANCHORS, cell_summary

    if not PRESETS[plan.preset].rate_distortion:
        return [], []
    table = Table("Rate–distortion: the .cvq codec against JPEG 2000 and JPEG XL on the same field",
                  ["Scene", "Setting", "fit PSNR", "fine-tuning", *(f"BD-rate vs {a}" for a in ANCHORS),
                   "BD-rate vs the better",
                   "cvqpg ≤ 0.1 dB: bpp", "÷ model.safetensors", *(f"{a} ≤ 0.1 dB: bpp" for a in ANCHORS),
                   "encode s", "decode+render s", "float32 load+render s", "load"],
                  note="BD-rate: bits of the codec's Pareto front against the anchor's at equal PSNR, log-rate "
                  "interpolated with bjontegaard's PCHIP, averaged over the range shown (the fit's PSNR down to 1 dB "
                  "below it, narrowed to where both curves have points); negative means fewer bits. Fine-tuning: the "
                  "steps of the codec's fine-tuned and pruned points (`--finetune`), none where the cell has only the "
                  "ladder and the searched budgets. ≤ 0.1 dB: the "
                  "smallest file within 0.1 dB of the float32 fit, with its drop; encode s of a `--max-drop` point "
                  "includes its budget search. Seconds are wall time on the machine and load (15-minute load "
                  "average) of the cell's run record.")
    rows: list[dict[str, Any]] = []
    for setting in plan.settings:
        per_scene = [(r, cell_summary(r.rd)) for r in results if r.rd is not None and r.cell.setting == setting]
        for r, summary in per_scene:
            top, held, rates = summary["fit_psnr"], summary["held"], summary["bd_rate"]
            better = rates[summary["better_anchor"]] if summary["better_anchor"] else None
            codec = held["cvqpg"]
            steps = r.rd.get("finetune_steps", 0)
            table.rows.append([r.cell.scene.name, setting_label(setting), f"{top:.3f}",
                               f"{steps} steps" if steps else "none", *(_bd_text(rates[a], top) for a in ANCHORS),
                               _bd_text(better, top, True),
                               _held_text(codec, top),
                               MISSING if summary["fraction"] is None else f"1/{1 / summary['fraction']:.1f}",
                               *(_held_text(held[a], top) for a in ANCHORS),
                               MISSING if codec is None else f"{codec['encode_s']:.2f}",
                               MISSING if codec is None else f"{codec['decode_s']:.2f}",
                               f"{summary['float32_decode_s']:.2f}", f"{r.rd['run']['load_average']}"])
            rows.append({"cell": r.cell.name, "scene": r.cell.scene.name, "setting": setting, "fit_psnr": top,
                         "finetune_steps": steps,
                         **{f"bd_rate_{a.replace(' ', '').lower()}": "" if rates[a] is None else rates[a].percent
                            for a in ANCHORS},
                         "better_anchor": summary["better_anchor"] or "",
                         "bd_rate_better": "" if better is None else better.percent,
                         "bd_low_db": "" if better is None else better.low - top,
                         "bd_high_db": "" if better is None else better.high - top,
                         "bytes_within_0.1db": "" if codec is None else codec["bytes"],
                         "fraction_of_model": "" if summary["fraction"] is None else summary["fraction"],
                         "encode_s": "" if codec is None else codec["encode_s"],
                         "decode_render_s": "" if codec is None else codec["decode_s"],
                         "load_average": r.rd["run"]["load_average"]})
        betters = [float(row["bd_rate_better"]) for row in rows if row["setting"] == setting
                   and row["bd_rate_better"] != ""]
        fractions = [float(row["fraction_of_model"]) for row in rows if row["setting"] == setting
                     and row["fraction_of_model"] != ""]
        table.rows.append([f"mean ({len(per_scene)}/{len(plan.scenes)} scenes)", setting_label(setting), "", "", "",
                           "", f"{np.mean(betters):+.1f}%" if betters else MISSING, "",
                           f"1/{1 / np.mean(fractions):.1f}" if fractions else MISSING, "", "", "", "", "", ""])
        table.bold.add((len(table.rows) - 1, 6))
    if not PRESETS[plan.preset].budget_fractions:
        return [table], rows
    wide, wide_rows = wide_range_table(plan, results)
    by_cell = {row["cell"]: row for row in wide_rows}
    encoded, encoders = encode_points_table(plan, results), encoder_bd_table(plan, results)
    return [table, wide, *([encoded] if encoded.rows else []), *([encoders] if encoders.rows else [])], \
        [{**row, **by_cell.get(row["cell"], {})}
                                                                 for row in rows]


def encode_points_table(plan: BenchPlan, results: list[CellResult]) -> Table:
    """In a rate grid with the encode grid's points (`--preset encode`), one row per `cvqpg encode` file: its budget,
    primitives, rate and PSNR, beside the PSNR of the codec's front from the cell's fit (pruned and fine-tuned by
    `--bpp`) and of JPEG XL's front at the file's rate."""
    from .ratedistortion import CODEC, ENCODERS, psnr_at_rate

    table = Table("cvqpg encode's files against the Table 1 fit's codec front and JPEG XL at the same rate",
                  ["Scene", "Setting", "encoder", "budget bpp", "file bpp", "primitives", "PSNR", "below the fit",
                   "from the Table 1 fit", "JPEG XL", "above JPEG XL", "encode s", "CPU s"],
                  note="PSNR in dB, mean over the planes against the targets. From the Table 1 fit and JPEG XL: "
                  "the Pareto front of the cell's `.cvq` files of its own fit (ladder, searched, `--bpp`) and "
                  "JPEG XL's at the file's rate, linear in log bpp between their points (– outside them). "
                  "Primitives: those in the file; encode s: the fit and its rate control, wall time; CPU s: the "
                  "process's CPU time over it, all threads (below encode s × threads where other work shared the "
                  "cores; – for points recorded without it). Encoder: `cvqpg encode` as it fits by default, or with "
                  "the rate in the fit (`--rate-loss`).")
    for setting in plan.settings:
        for r in results:
            if r.rd is None or r.cell.setting != setting:
                continue
            top = r.rd["fit_psnr"]
            fitted = [p for p in r.rd["points"] if p["codec"] == CODEC]
            jpeg_xl = [p for p in r.rd["points"] if p["codec"] == "JPEG XL"]
            for point in sorted((p for p in r.rd["points"] if p["codec"] in ENCODERS),
                                key=lambda p: (ENCODERS.index(p["codec"]), -p["bpp"])):
                own, anchor = psnr_at_rate(fitted, point["bpp"]), psnr_at_rate(jpeg_xl, point["bpp"])
                table.rows.append([r.cell.scene.name, setting_label(setting), point["codec"],
                                   f"{point['budget_bpp']:.3f}",
                                   f"{point['bpp']:.3f}", f"{point['primitives']:,}", f"{point['psnr']:.3f}",
                                   f"{point['psnr'] - top:+.2f}", MISSING if own is None else f"{own:.2f}",
                                   MISSING if anchor is None else f"{anchor:.2f}",
                                   MISSING if anchor is None else f"{point['psnr'] - anchor:+.2f}",
                                   f"{point['encode_s']:.0f}",
                                   MISSING if point.get("encode_cpu_s") is None else f"{point['encode_cpu_s']:.0f}"])
    return table


def encoder_bd_table(plan: BenchPlan, results: list[CellResult]) -> Table:
    """In a grid with points of both encoders (`--preset rate-fit`), per cell: the BD-rate of each encoder's files
    against JPEG XL and JPEG 2000 over [fit − 3, fit − 0.1] dB, and the PSNR of the rate in the fit above
    today's encode at each budget (equal bytes, within rate control's 5%)."""
    from .ratedistortion import ANCHORS, ENCODER, ENCODER_RATE, WIDE_RANGE_DB, _against_anchors, _by_codec

    deepest, shallowest = WIDE_RANGE_DB
    table = Table(f"The rate in the fit against today's encode: BD-rate over [fit − {deepest:g}, fit − "
                  f"{shallowest:g}] dB and the PSNR gain at each budget",
                  ["Scene", "Setting", *(f"{encoder} vs {anchor}" for encoder in (ENCODER, ENCODER_RATE)
                                         for anchor in ANCHORS), "gain at each budget (dB)"],
                  note="BD-rate: negative where the encoder's files take fewer bytes than the anchor's at equal "
                  "PSNR; gain: the `--rate-loss` file's PSNR less today's at the same budget, largest budget first.")
    for setting in plan.settings:
        for r in results:
            if r.rd is None or r.cell.setting != setting:
                continue
            by_codec = _by_codec(r.rd)
            if not by_codec.get(ENCODER_RATE):
                continue
            top = r.rd["fit_psnr"]
            cells = []
            for encoder in (ENCODER, ENCODER_RATE):
                rates, _ = _against_anchors(by_codec, top - shallowest, deepest - shallowest, (encoder,))
                cells += [MISSING if rates[anchor] is None else f"{rates[anchor].percent:+.1f}%" for anchor in ANCHORS]
            today = {round(p["budget_bpp"], 6): p["psnr"] for p in by_codec.get(ENCODER, [])}
            gains = [f"{p['psnr'] - today[round(p['budget_bpp'], 6)]:+.2f}"
                     for p in sorted(by_codec[ENCODER_RATE], key=lambda p: -p["budget_bpp"])
                     if round(p["budget_bpp"], 6) in today]
            table.rows.append([r.cell.scene.name, setting_label(setting), *cells, ", ".join(gains) or MISSING])
    return table


def _range_text(values: list[float], digits: int = 3) -> str:
    return MISSING if not values else f"{min(values):.{digits}f}–{max(values):.{digits}f}"


def _mean_bd_text(values: list[float], cells: int | None = None) -> str:
    """The mean of BD-rates (%) with how many lie above 0%, and over how many cells where not all of `cells`."""
    if not values:
        return MISSING
    share = "" if cells is None or len(values) == cells else f" over {len(values)}"
    return f"{np.mean(values):+.1f}%{share} ({sum(value > 0 for value in values)} above 0%)"


def wide_range_table(plan: BenchPlan, results: list[CellResult]) -> tuple[Table, list[dict[str, Any]]]:
    """In a rate grid (`--preset rate`), per setting and scene: the codec's BD-rate against each anchor and
    the better one over [fit − 3, fit − 0.1] dB; its PSNR above JPEG XL at the rate where JPEG XL is 2 dB
    below the fit; and its `--bpp` points: how full each file is of its budget, how many primitives the
    codec's points hold, how deep they reach, and their encode seconds. Also the columns it adds to `rd.csv`."""
    from .ratedistortion import ANCHORS, WIDE_RANGE_DB, wide_summary

    deepest, shallowest = WIDE_RANGE_DB
    table = Table(f"Rate–distortion below the fit: BD-rate over [fit − {deepest:g}, fit − {shallowest:g}] dB and "
                  "the `--bpp` budgets",
                  ["Scene", "Setting", "fit PSNR", *(f"BD-rate vs {a}" for a in ANCHORS), "BD-rate vs the better",
                   "JPEG XL at fit − 2 dB: bpp", "cvqpg there: dB above", "with cvqpg encode: BD-rate vs the better",
                   "with cvqpg encode: dB above", "--bpp files: bytes ÷ budget",
                   "codec points", "primitive counts", "deepest point", "--bpp encode s", "cvqpg encode s"],
                  note=f"BD-rate as in the table above, over the fit's PSNR − {deepest:g} dB to − {shallowest:g} dB "
                  "(narrowed to where both fronts have points). cvqpg there: the codec's Pareto front at the rate "
                  "where JPEG XL's front is 2 dB below the fit (both interpolated linearly in log bpp), minus "
                  "that PSNR. --bpp files: each rate-controlled file's bytes over its budget's ⌊bpp·W·H/8⌋ "
                  "(within 0.95–1 is honest); codec points: all of the codec's points (ladder, searched, "
                  "budgets and cvqpg encode), with the distinct primitive counts among them and the deepest one's "
                  "drop below the fit. Encode s: the rate control of one budget (search, fine-tuning, last search), "
                  "smallest–largest. With cvqpg encode: the same figures for the codec's points together with "
                  "those of `cvqpg encode --bpp` at the budgets of `--preset encode` (a fit at each budget's "
                  "primitive count, rate-controlled into it), whose whole time is cvqpg encode s.")
    rows: list[dict[str, Any]] = []
    for setting in plan.settings:
        summaries = [(r, wide_summary(r.rd)) for r in results if r.rd is not None and r.cell.setting == setting]
        betters, gains, encoder_betters, encoder_gains = [], [], [], []
        for r, summary in summaries:
            top, rates = summary["fit_psnr"], summary["bd_rate"]
            better = rates[summary["better_anchor"]] if summary["better_anchor"] else None
            equal, counts = summary["equal_rate"], summary["counts"]
            with_encoder, equal_with_encoder = summary["bd_rate_with_encoder"], summary["equal_rate_with_encoder"]
            if better is not None:
                betters.append(better.percent)
            if equal is not None:
                gains.append(equal.gain_db)
            if with_encoder is not None:
                encoder_betters.append(with_encoder.percent)
            if equal_with_encoder is not None:
                encoder_gains.append(equal_with_encoder.gain_db)
            table.rows.append([r.cell.scene.name, setting_label(setting), f"{top:.3f}",
                               *(_bd_text(rates[a], top, True) for a in ANCHORS), _bd_text(better, top, True),
                               NA if equal is None else f"{equal.bpp:.3f}",
                               NA if equal is None else f"{equal.gain_db:+.2f}",
                               _bd_text(with_encoder, top, True) if summary["encoded"] else MISSING,
                               NA if equal_with_encoder is None else f"{equal_with_encoder.gain_db:+.2f}",
                               _range_text(summary["fills"]), str(summary["points"]),
                               f"{len(counts)}: {counts[0]:,}–{counts[-1]:,}" if counts else MISSING,
                               f"{-summary['deepest_db']:+.2f} dB",
                               _range_text([p["encode_s"] for p in summary["budgeted"]], 0),
                               _range_text([p["encode_s"] for p in summary["encoded"]], 0)])
            rows.append({"cell": r.cell.name,
                         **{f"wide_bd_rate_{a.replace(' ', '').lower()}": "" if rates[a] is None else rates[a].percent
                            for a in ANCHORS},
                         "wide_better_anchor": summary["better_anchor"] or "",
                         "wide_bd_rate_better": "" if better is None else better.percent,
                         "jpegxl_minus_2db_bpp": "" if equal is None else equal.bpp,
                         "gain_over_jpegxl_db": "" if equal is None else equal.gain_db,
                         "wide_bd_rate_with_encoder": "" if with_encoder is None else with_encoder.percent,
                         "gain_over_jpegxl_with_encoder_db": "" if equal_with_encoder is None
                         else equal_with_encoder.gain_db,
                         "budget_fill_min": min(summary["fills"], default=""),
                         "budget_fill_max": max(summary["fills"], default=""),
                         "primitive_counts": len(counts)})
        table.rows.append([f"mean ({len(summaries)}/{len(plan.scenes)} scenes)", setting_label(setting), "", "", "",
                           _mean_bd_text(betters), "", f"{np.mean(gains):+.2f}" if gains else MISSING,
                           _mean_bd_text(encoder_betters, len(summaries)),
                           f"{np.mean(encoder_gains):+.2f} ({len(encoder_gains)})" if encoder_gains else MISSING,
                           "", "", "", "", "", ""])
        table.bold.update({(len(table.rows) - 1, 5), (len(table.rows) - 1, 8)})
    return table, rows


def rate_distortion_figures(plan: BenchPlan, results: list[CellResult]) -> list[Path]:
    """`rd_<setting>.png`: per scene, each codec's Pareto front and the two model files."""
    from .ratedistortion import FLOAT16, FLOAT32, WIDE_RANGE_DB, pareto

    drawn = []
    for setting in plan.settings:
        panels = {}
        for r in results:
            if r.rd is None or r.cell.setting != setting:
                continue
            codecs: dict[str, list[dict[str, Any]]] = {}
            for point in r.rd["points"]:
                codecs.setdefault(point["codec"], []).append(point)
            fronts = {codec: pareto(points) if codec not in (FLOAT32, FLOAT16) else points
                      for codec, points in codecs.items()}
            panels[r.cell.scene.name] = (r.rd["fit_psnr"], {
                codec: ([p["bpp"] for p in front], [p["psnr"] for p in front]) for codec, front in fronts.items()})
        if panels:
            name = Path(f"rd_{setting}.png")
            figures.rate_distortion_figure({f"{scene}, {setting_label(setting)}": panel
                                            for scene, panel in panels.items()}, plan.folder / name,
                                           WIDE_RANGE_DB if PRESETS[plan.preset].budget_fractions else (1.0, 0.0))
            drawn.append(name)
    return drawn


@dataclass
class FrequencyCurve:
    """Radially binned error spectra of one setting, `method` against `reference`, over the (scene, seed)
    pairs both finished; of one colour channel, or all (`channel` None)."""

    setting: str
    reference: str
    method: str
    channel: int | None
    edges: np.ndarray
    mse_reference: np.ndarray
    mse_method: np.ndarray
    delta_pct: np.ndarray  # mean over pairs of (MSE_reference − MSE_method) / MSE_reference, %
    pairs: int

    @property
    def label(self) -> str:
        channel = "" if self.channel is None else f", {CHANNEL_NAMES[self.channel]}"
        return f"{setting_label(self.setting)}{channel}"


def _nanmean(stack: np.ndarray) -> np.ndarray:
    """Mean over axis 0 ignoring NaN; NaN where a column has no value (no warning)."""
    valid = ~np.isnan(stack)
    counts = valid.sum(axis=0)
    return np.where(counts > 0, np.where(valid, stack, 0.0).sum(axis=0) / np.maximum(counts, 1), np.nan)


def frequency_curves(plan: BenchPlan, results: list[CellResult], reference: str = "baseline",
                     method: str = "cvqpg", channel: int | None = None) -> list[FrequencyCurve]:
    """ΔMSE% of `method` over `reference` per radial frequency bin and setting, from each cell's
    `spectrum.json` (one colour channel's spectrum when `channel` is given)."""
    curves = []
    for setting in plan.settings:
        spectra = {(r.cell.scene.name, r.cell.config.optimisation.seed, r.cell.method): r.spectrum for r in results
                   if r.spectrum is not None and r.cell.setting == setting}
        if channel is not None:
            spectra = {key: {**record, "power": record["channel_power"][channel]} for key, record in spectra.items()
                       if len(record.get("channel_power", ())) > channel}
        pairs = sorted({key[:2] for key in spectra if key[2] == reference and (*key[:2], method) in spectra})
        if not pairs:
            continue
        power = {m: np.array([[np.nan if p is None else p for p in spectra[(*pair, m)]["power"]] for pair in pairs],
                             dtype=float) for m in (reference, method)}
        base, ours = power[reference], power[method]
        with np.errstate(invalid="ignore", divide="ignore"):
            delta = np.where(base > 0, (base - ours) / base * 100, np.nan)
        curves.append(FrequencyCurve(setting, reference, method, channel,
                                     np.array(spectra[(*pairs[0], reference)]["edges"]), _nanmean(base),
                                     _nanmean(ours), _nanmean(delta), len(pairs)))
    return curves


def channel_frequency_curves(plan: BenchPlan, results: list[CellResult]) -> list[FrequencyCurve]:
    """Per colour channel, ΔMSE% of per-channel curvature over shared CVQPG, where both ran."""
    if not {"cvqpg", "per-channel"} <= set(plan.methods):
        return []
    return [curve for channel in range(len(CHANNEL_NAMES))
            for curve in frequency_curves(plan, results, "cvqpg", "per-channel", channel)]


def frequency_rows(curves: list[FrequencyCurve]) -> list[dict[str, Any]]:
    """`frequency.csv`: one row per setting (and channel) and bin; the last bin holds the corners beyond
    Nyquist. A bin that no frequency of the image size falls into is left empty."""
    rows = []
    for c in curves:
        for b in range(len(c.delta_pct)):
            channel = {} if c.channel is None else {"channel": CHANNEL_NAMES[c.channel]}
            rows.append({"setting": c.setting, **channel, "bin": b, "rho_low": c.edges[b], "rho_high": c.edges[b + 1],
                         "band": "in band" if c.edges[b + 1] <= 1.0 else "beyond Nyquist (corners)",
                         **{k: "" if math.isnan(v) else v for k, v in (
                             (f"mse_{c.reference}", c.mse_reference[b]), (f"mse_{c.method}", c.mse_method[b]),
                             ("delta_mse_pct", c.delta_pct[b]))}, "pairs": c.pairs})
    return rows


def frequency_lines(curves: list[FrequencyCurve]) -> list[str]:
    """One line per curve: the peak ΔMSE and its band, next to the paper's peak where it has one."""
    peaks = paper_numbers()["frequency_peak_delta_mse_pct"]
    lines = []
    for c in curves:
        band = c.delta_pct[:-1]
        if np.all(np.isnan(band)):
            continue
        peak = int(np.nanargmax(band))
        paper = (f"; paper, ten scenes: peak about {peaks[c.setting.split('-')[0]]}%"
                 if (c.reference, c.method, c.channel) == ("baseline", "cvqpg", None) else "")
        lines.append(f"{c.label}: peak ΔMSE of {METHODS[c.method].label} over {METHODS[c.reference].label} "
                     f"{band[peak]:+.1f}% at ρ = {c.edges[peak]:.2f}–{c.edges[peak + 1]:.2f} "
                     f"({c.pairs} scene/seed pairs{paper})")
    return lines or ["No setting has both a finished baseline and CVQPG cell yet."]


def _csv(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return ""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def _plotted(curves: list[FrequencyCurve]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """label → (in-band bin centres ρ, ΔMSE %)."""
    return {c.label: ((c.edges[:-2] + c.edges[1:-1]) / 2, c.delta_pct[:-1]) for c in curves}


def draw_figures(plan: BenchPlan, results: list[CellResult], curves: list[FrequencyCurve],
                 channel_curves: list[FrequencyCurve]) -> list[Path]:
    """Frequency plots, QPF figure and one comparison per scene and setting (first seed); relative paths."""
    folder = plan.folder / "figures"
    folder.mkdir(parents=True, exist_ok=True)
    figures.frequency_figure(_plotted(curves), plan.folder / "frequency.png")
    figures.qpf_figure(folder / "qpf.png")
    done = {(r.cell.scene.name, r.cell.setting, r.cell.method, r.cell.config.optimisation.seed): r for r in results
            if r.status == DONE}
    drawn = [Path("frequency.png"), Path("figures/qpf.png")]
    if channel_curves:
        figures.frequency_figure(_plotted(channel_curves), plan.folder / "frequency_channels.png",
                                 "ΔMSE of per-channel γ over shared CVQPG (%)")
        drawn.append(Path("frequency_channels.png"))
    compared = [m for m in ("baseline", "cvqpg") if m in plan.methods]
    for scene in plan.scenes:
        for setting in plan.settings:
            runs = {METHODS[m].label: done[key] for m in compared
                    if (key := (scene.name, setting, m, plan.seeds[0])) in done}
            if len(runs) < 2 or not all((plan.cell_dir(r.cell) / "target_plane0.png").is_file()
                                        for r in runs.values()):  # a recorded cell keeps no images
                continue
            config = next(iter(runs.values())).cell.config
            name = Path("figures") / f"compare_{scene.name}_{setting}.png"
            figures.comparison_figure({label: plan.cell_dir(r.cell) for label, r in runs.items()},
                                      config.plane_distances, f"{scene.name}, {setting_label(setting)}, "
                                      f"N = {config.primitive_count:,}, {config.optimisation.steps} steps",
                                      plan.folder / name)
            drawn.append(name)
    return drawn


def fitted_on(result: CellResult) -> str:
    """The device a finished cell's fit ran on, as its `metrics.json` records it (`cpu: <model>`,
    `cuda: <GPU>`); empty for a cell not finished or recorded before devices were."""
    return ((result.metrics or {}).get("run") or {}).get("device") or ""


def devices_line(results: list[CellResult]) -> str:
    """Which devices the finished cells ran on, with how many each; says so when they were several."""
    counts: dict[str, int] = {}
    for r in results:
        if fitted_on(r):
            counts[fitted_on(r)] = counts.get(fitted_on(r), 0) + 1
    listed = "; ".join(f"{device} ({n})" for device, n in sorted(counts.items()))
    if len(counts) > 1:
        return f"finished cells ran on several devices: {listed}; the Device column of the cell list says which"
    return f"finished cells ran on {listed or 'no recorded device'}"


def overview_lines(plan: BenchPlan, results: list[CellResult]) -> list[str]:
    """What the bench folder holds and how it was fitted."""
    counts: dict[str, int] = {}
    for r in results:
        counts[r.status] = counts.get(r.status, 0) + 1
    config = plan.cells[0].config
    return [f"cells: {counts.get(DONE, 0)} of {len(results)} done"
            + "".join(f", {n} {status}" for status, n in sorted(counts.items()) if status != DONE),
            f"scenes: {', '.join(s.name for s in plan.scenes)}; seeds: {', '.join(map(str, plan.seeds))}",
            (f"fits: {config.targets.width}×{config.targets.height} px, {config.optimisation.steps} steps "
             f"(warm-up {config.optimisation.curvature_warmup}), device {plan.cells[0].run.device}"),
            devices_line(results),
            ("metrics that this machine cannot compute read n/a; the means of a setting cover the scenes every "
             "method has finished (see the scenes column, the notes and the cell list)")]


def summary_markdown(plan: BenchPlan, overview: list[str], tables: list[Table], frequency: list[str],
                     images: list[Path]) -> str:
    """summary.md: overview, the tables, the frequency analysis and links to the figures."""
    parts = [f"# Bench `{plan.preset}`\n", *(f"- {line}" for line in overview), ""]
    parts += [t.markdown() for t in tables[:-1]]
    parts += ["### Frequency analysis (ΔMSE: how much lower a method's error is, per frequency band)\n",
              *(f"- {line}" for line in frequency),
              "", "### Figures\n", *(f"- [{p.stem}]({p.as_posix()})" for p in images), "", tables[-1].markdown()]
    return "\n".join(parts)


REPORT_STYLE = ("body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em}"
                "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;padding:2px 6px;"
                "font-size:13px;text-align:right}td:first-child,th:first-child{text-align:left}"
                "img{max-width:100%}.note{color:rgb(85, 85, 85);font-size:13px}")


def _paragraphs(lines: list[str]) -> str:
    return "".join(f"<p>{html.escape(line)}</p>" for line in lines)


def report_html(plan: BenchPlan, overview: list[str], tables: list[Table], frequency: list[str],
                images: list[Path]) -> str:
    """One HTML file; the images are referenced by paths relative to the bench folder."""
    title = f"cvqpg bench {html.escape(plan.preset)}"
    pictures = "".join(f"<figure><img src='{html.escape(p.as_posix())}' alt='{html.escape(p.stem)}'>"
                       f"<figcaption>{html.escape(p.stem)}</figcaption></figure>" for p in images)
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{title}</title><style>{REPORT_STYLE}"
            f"</style></head><body><h1>{title}</h1>{_paragraphs(overview)}{''.join(t.html() for t in tables[:-1])}"
            f"<h3>Frequency analysis</h3>{_paragraphs(frequency)}<h3>Figures</h3>{pictures}{tables[-1].html()}"
            "</body></html>\n")


def write_summary(plan: BenchPlan) -> Path:
    """(Re)write summary.md, summary.csv, cells.csv, frequency.csv/png, figures/ and report.html; returns
    the path of summary.md. Cells that are not finished are marked and left out of the means."""
    plan.folder.mkdir(parents=True, exist_ok=True)
    results = collect(plan)
    main, main_rows = main_table(plan, results)
    cells, cell_rows = cells_table(plan, results)
    curves, channel_curves = frequency_curves(plan, results), channel_frequency_curves(plan, results)
    rd_tables, rd_rows = rate_distortion_table(plan, results)
    tables = [main, *rd_tables, per_scene_table(plan, results), *variant_tables(plan, results),
              *seed_tables(plan, results), cells]
    overview = overview_lines(plan, results)
    frequency = frequency_lines(curves) + (frequency_lines(channel_curves) if channel_curves else [])
    images = rate_distortion_figures(plan, results) + draw_figures(plan, results, curves, channel_curves)
    write_atomic(plan.folder / "summary.csv", _csv(main_rows))
    write_atomic(plan.folder / "cells.csv", _csv(cell_rows))
    if rd_rows:
        write_atomic(plan.folder / "rd.csv", _csv(rd_rows))
    write_atomic(plan.folder / "frequency.csv", _csv(frequency_rows(curves)))
    if channel_curves:
        write_atomic(plan.folder / "frequency_channels.csv", _csv(frequency_rows(channel_curves)))
    write_atomic(plan.folder / "report.html", report_html(plan, overview, tables, frequency, images))
    write_atomic(plan.folder / "summary.md", summary_markdown(plan, overview, tables, frequency, images))
    return plan.folder / "summary.md"
