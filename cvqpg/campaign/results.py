"""`docs/results.md`, generated from the cell records kept in `results/`: the paper's tables and
claims with ours beside them.

The campaign is fixed here: which grids, scenes, settings and methods make up the paper's
evidence, and the commands that fit them. The document therefore says how many cells are still
missing, and a recorded cell fitted with settings other than the campaign's is refused. Every
number in the document comes from a cell's `metrics.json` or `spectrum.json` and from
`paper_numbers.json`; nothing is typed by hand.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..app.outputs import FIGURE, check_output
from ..runs import HISTORY_FILE, read_history
from .bench import (DONE, FOLDER_SCENE_PLANES, METHODS, PRESETS, BenchPlan, BenchScene, Cell, cell_config,
                    config_differences, setting_label)
from ..config import LONG_RUN_BETAS, PAPER_BETAS, SHORT_RUN_STEPS, FitConfig
from ..initialisation import EDGES_UNIFORM_SHARE
from ..errors import CvqpgError
from .figures import psnr_seconds_figure
from .presets import DISPLAY_METHODS
from .report import (DECIMALS, TABLE1_METHODS, CellResult, Metrics, Table, baseline_gain, channel_frequency_curves,
                     collect, frequency_curves, frequency_lines, paired_delta, paper_numbers, paper_scene_mean,
                     primitive_count, scene_values, setting_methods, shared_means, variant_tables, waiting_note)

SCENES = ("bento", "dragon", "flower", "sushi", "tiger", "windmill")
# The paper's ablation means match its per-scene rows of pencil, sushi, flower, tiger and burger; of
# those we have three, and bento and dragon complete our five.
ABLATION_SCENES = ("bento", "dragon", "flower", "sushi", "tiger")
CHROMATIC_METHODS = ("baseline", "cvqpg", "per-channel", "channel-bound")
ABLATION_METHODS = ("baseline", "cvqpg", "no-bound", "no-mahalanobis", "vanilla")
BEYOND_METHODS = ("baseline", "cvqpg")
BEYOND_SETTINGS = ("gray-10", "rgb-10")
SETTINGS = ("rgb-20", "rgb-10", "gray-20", "gray-10")
SCENE_TOLERANCE_DB = 0.3
GAIN_TOLERANCE_DB = 0.1
FREQUENCY_TOLERANCE_POINTS = 5.0
CHROMATIC_TARGET_DB = 0.30
SIMILAR_DB = 0.05  # the spread of one fit between CPUs; closer values are not ordered
QUIET_LOAD_PER_CORE = 1.25  # above it a fit shared the cores, and its time says little about the method
GIB = 2**30


@dataclass(frozen=True)
class Block:
    """Part of a grid: one colour, its ratios and the methods fitted at each."""

    color: str
    ratios: tuple[float, ...]
    methods: tuple[str, ...]


@dataclass(frozen=True)
class Grid:
    """A bench folder of the campaign, `results/<preset>`, and the commands that fit it."""

    preset: str
    title: str
    scenes: tuple[str, ...]
    blocks: tuple[Block, ...]
    commands: tuple[str, ...]


def _bench(preset: str, options: str, reuse: bool = False) -> str:
    return (f"cvqpg bench --preset {preset} --scenes ../shared/scenes --out results/{preset} {options}"
            + (" --reuse results/paper" if reuse else "")).replace("  ", " ").strip()


CAMPAIGN = (
    Grid("paper", "Table 1", SCENES,
         (Block("rgb", (0.1, 0.2), TABLE1_METHODS), Block("gray", (0.1, 0.2), TABLE1_METHODS)),
         (_bench("paper", "--colors rgb --ratios 0.1"), _bench("paper", "--colors rgb --ratios 0.2"),
          _bench("paper", "--colors gray"))),
    Grid("chromatic", "Chromatic curvature (beyond the paper)", SCENES,
         (Block("rgb", (0.1, 0.2), CHROMATIC_METHODS), Block("rgb", (0.1,), ("baseline+pc", "cvqpg+pc"))),
         (_bench("chromatic", "--ratios 0.1", reuse=True),
          _bench("chromatic", "--ratios 0.2 --methods " + " ".join(CHROMATIC_METHODS), reuse=True))),
    Grid("ablation", "Ablation", ABLATION_SCENES, (Block("rgb", (0.1,), ABLATION_METHODS),),
         (_bench("ablation", "--scene-names " + " ".join(ABLATION_SCENES), reuse=True),)),
    Grid("beyond", "Beyond the paper: the new recipe, 2000 steps", SCENES,
         (Block("gray", (0.1,), BEYOND_METHODS), Block("rgb", (0.1,), BEYOND_METHODS)),
         (_bench("beyond", "--colors gray"), _bench("beyond", "--colors rgb"))),
    Grid("beyond-time", "Beyond the paper: the new recipe, the paper's training time", SCENES,
         (Block("gray", (0.1,), ("cvqpg",)), Block("rgb", (0.1,), ("cvqpg",))),
         (_bench("beyond-time", "--colors gray"), _bench("beyond-time", "--colors rgb"))),
    Grid("display", "What a phase-only SLM shows", SCENES,
         (Block("gray", (0.1,), DISPLAY_METHODS), Block("rgb", (0.1,), DISPLAY_METHODS)),
         (_bench("display", "--colors gray"), _bench("display", "--colors rgb"))),
)


class RecordError(CvqpgError):
    """A recorded cell that does not belong to the campaign as defined here."""


@dataclass
class GridResults:
    grid: Grid
    plan: BenchPlan
    results: list[CellResult]

    @property
    def done(self) -> list[CellResult]:
        return [r for r in self.results if r.status == DONE]


def campaign_plan(grid: Grid, root: Path) -> BenchPlan:
    """The grid's cells at its preset's recipe and steps (seed 100), in `root/<preset>`."""
    preset = PRESETS[grid.preset]
    base = FitConfig.create(preset.recipe)
    seed = base.optimisation.seed
    scenes = tuple(BenchScene(name, {"scene": name}, FOLDER_SCENE_PLANES) for name in grid.scenes)
    cells = tuple(Cell(scene, method, cell_config(base.with_steps(preset.steps_for(block.color)), scene,
                                                  block.color, ratio, method, seed))
                  for scene in scenes for block in grid.blocks for ratio in block.ratios for method in block.methods)
    methods = tuple(dict.fromkeys(m for block in grid.blocks for m in block.methods))
    return BenchPlan(grid.preset, root / grid.preset, scenes, methods, (seed,), cells)


def load_grid(grid: Grid, root: Path) -> GridResults:
    """The grid's plan and recorded cells; raises RecordError for a cell recorded with other settings."""
    plan = campaign_plan(grid, root)
    results = collect(plan)
    for r in results:
        if r.status == DONE:
            differences = config_differences(plan.cell_dir(r.cell), r.cell.config)
            if differences:
                raise RecordError(f"{plan.cell_dir(r.cell)} differs from the campaign: {'; '.join(differences[:3])}")
    return GridResults(grid, plan, results)


def _signed(value: float | None, decimals: int = 3) -> str:
    return "–" if value is None else f"{value:+.{decimals}f}"


def _within(difference: float, tolerance: float, complete: bool = True) -> str:
    """The verdict on a claim; with cells still missing, only how it stands so far."""
    if complete:
        return "reproduced" if abs(difference) <= tolerance else "not reproduced"
    return f"{'within' if abs(difference) <= tolerance else 'outside'} the tolerance so far"


def _scenes(count: int) -> str:
    return f"{count} scene{'s' * (count != 1)}"


def _metric(results: list[CellResult], setting: str, method: str, metric: str) -> dict[str, float]:
    """Per scene, the method's `metric` in `setting` (where the cells have it)."""
    return {scene: v[metric] for scene, v in scene_values(results, setting, method).items() if v[metric] is not None}


def _psnr(results: list[CellResult], setting: str, method: str) -> dict[str, float]:
    return _metric(results, setting, method, "psnr")


def status_table(grids: list[GridResults]) -> Table:
    table = Table("Where the campaign stands", ["grid", "folder", "cells recorded", "of", "remaining"])
    for g in grids:
        total = len(g.results)
        table.rows.append([g.grid.title, f"`results/{g.grid.preset}`", str(len(g.done)), str(total),
                           str(total - len(g.done))])
    return table


def machine_lines(grids: list[GridResults]) -> list[str]:
    """The devices, thread counts and commits the recorded cells ran on."""
    runs = [r.metrics.get("run") for g in grids for r in g.done]
    known = [run for run in runs if run]
    lines = []
    if len(known) < len(runs):
        lines.append(f"{len(runs) - len(known)} cells carry no run record.")
    machines = Counter(f"{run['device']}, {run['torch_threads']} torch / {run['numba_threads']} Numba threads"
                       for run in known)
    lines += [f"{count} cell{'s' * (count != 1)} on {machine}" for machine, count in sorted(machines.items())]
    commits = Counter((run["commit"] or "unknown")[:7] + ("+dirty" if str(run["commit"]).endswith("+dirty") else "")
                      for run in known)
    if commits:
        lines.append("commits: " + ", ".join(f"{commit} ({count})" for commit, count in sorted(commits.items())))
    return lines + mixed_machine_lines(grids)


def mixed_machine_lines(grids: list[GridResults]) -> list[str]:
    """Per grid, the scene–setting groups whose methods, compared with each other in the tables, ran on
    different devices: between CPU models one fit differs by about SIMILAR_DB, so their differences are
    weaker evidence."""
    lines = []
    for g in grids:
        devices: dict[tuple[str, str], dict[str, list[str]]] = {}
        for r in g.done:
            run = r.metrics.get("run") or {}
            group = devices.setdefault((r.cell.scene.name, r.cell.setting), {})
            group.setdefault(run.get("device", "unrecorded"), []).append(METHODS[r.cell.method].label)
        mixed = [f"{scene} {setting_label(setting)} ("
                 + "; ".join(f"{', '.join(methods)} on {device}" for device, methods in sorted(by_device.items())) + ")"
                 for (scene, setting), by_device in devices.items() if len(by_device) > 1]
        if mixed:
            lines.append(f"{g.grid.title}: the methods of {len(mixed)} scene–setting group{'s' * (len(mixed) != 1)} "
                         f"ran on different devices, so their differences carry the ±{SIMILAR_DB} dB spread between "
                         f"CPUs: {', '.join(mixed)}.")
    return lines


def table1(paper: GridResults) -> Table:
    """Table 1's rows over our scenes: ours, the paper's same-scene mean, and Δ, per metric."""
    table = Table("Table 1: mean over our scenes; each cell: ours (paper on the same scenes, Δ)",
                  ["Setting", "Method", "N", "scenes", "PSNR↑", "SSIM↑", "LPIPS↓", "FLIP↓", "CVVDP↑"])
    notes = []
    for setting in SETTINGS:
        scenes, means = shared_means(paper.results, setting, list(TABLE1_METHODS))
        papers = {m: paper_scene_mean(scenes, setting, m) if means[m] else None for m in TABLE1_METHODS}
        for method in (*TABLE1_METHODS, "gain"):
            if method == "gain":
                label, n = "Δ (CVQPG − Baseline)", ""
                ours, paper_mean = baseline_gain(means, "cvqpg"), baseline_gain(papers, "cvqpg")
            else:
                label, n = METHODS[method].label, f"{primitive_count(paper.plan, setting, method):,}"
                ours, paper_mean = means[method], papers[method]
            table.rows.append([setting_label(setting), label, n,
                               f"{len(scenes) if ours else 0}/{len(paper.plan.scenes)}",
                               *(_with_delta(ours, paper_mean, m, method == "gain") for m in DECIMALS)])
        notes.append(waiting_note(paper.results, setting, list(TABLE1_METHODS), scenes))
    table.note = " ".join(note for note in notes if note)
    return table


def _with_delta(ours: Metrics | None, paper: Metrics | None, metric: str, signed: bool) -> str:
    if ours is None:
        return "–"
    value = ours[metric]
    if value is None:
        return "n/a"
    decimals = DECIMALS[metric]
    text = f"{value:{'+' if signed else ''}.{decimals}f}"
    if paper is None:
        return text
    return f"{text} ({paper[metric]:{'+' if signed else ''}.{decimals}f}, {value - paper[metric]:+.{decimals}f})"


def per_scene_table(paper: GridResults) -> Table:
    """PSNR per scene and setting, ours beside the supplementary table, and the CVQPG gain."""
    header = ["scene", "setting"]
    for method in TABLE1_METHODS:
        header += [f"{METHODS[method].label} ours", "paper", "Δ"]
    table = Table("PSNR per scene (dB), ours beside the paper's supplementary table",
                  header + ["gain ours", "gain paper"])
    supplement = paper_numbers()["per_scene"]
    for scene in paper.grid.scenes:
        for setting in SETTINGS:
            row = [scene, setting_label(setting)]
            ours = {m: _psnr(paper.results, setting, m).get(scene) for m in TABLE1_METHODS}
            if all(v is None for v in ours.values()):
                continue
            theirs = {m: supplement[scene][setting][m]["psnr"] for m in TABLE1_METHODS}
            for method in TABLE1_METHODS:
                value = ours[method]
                row += ["–" if value is None else f"{value:.3f}", f"{theirs[method]:.3f}",
                        "–" if value is None else f"{value - theirs[method]:+.3f}"]
            gain = None if None in (ours["cvqpg"], ours["baseline"]) else ours["cvqpg"] - ours["baseline"]
            table.rows.append(row + [_signed(gain), f"{theirs['cvqpg'] - theirs['baseline']:+.3f}"])
    return table


def claim_lines(grids: dict[str, GridResults]) -> list[str]:
    """One line per claim of the paper: reproduced or not, by how much, or how many cells are missing."""
    paper = grids["paper"]
    supplement = paper_numbers()["per_scene"]
    table1_paper = paper_numbers()["table1"]
    lines = []
    for setting in SETTINGS:
        delta, same_scenes, scenes = paired_delta(paper.results, setting, "cvqpg", True)
        claimed = table1_paper[setting]["cvqpg"]["psnr"] - table1_paper[setting]["baseline"]["psnr"]
        label = f"CVQPG − Baseline PSNR at equal N, {setting_label(setting)}"
        if delta is None:
            lines.append(f"{label}: paper {claimed:+.3f} dB (ten scenes); not measured yet.")
            continue
        same = same_scenes["psnr"]
        complete = len(scenes) == len(paper.grid.scenes)
        lines.append(f"{label}: ours {delta['psnr']:+.3f} dB on {_scenes(len(scenes))}, paper {same:+.3f} on the "
                     f"same scenes ({claimed:+.3f} on ten): "
                     f"{_within(delta['psnr'] - same, GAIN_TOLERANCE_DB, complete)} "
                     f"(Δ {delta['psnr'] - same:+.3f}, tolerance {GAIN_TOLERANCE_DB} dB).")
    differences = [(ours - supplement[scene][setting][method]["psnr"], scene, setting, method)
                   for setting in SETTINGS for method in TABLE1_METHODS
                   for scene, ours in _psnr(paper.results, setting, method).items()]
    if differences:
        worst = max(differences, key=lambda d: abs(d[0]))
        inside = sum(abs(d[0]) <= SCENE_TOLERANCE_DB for d in differences)
        lines.append(f"Per-scene PSNR within {SCENE_TOLERANCE_DB} dB of the supplementary table: {inside} of "
                     f"{len(differences)} recorded values; the largest difference is {worst[0]:+.3f} dB ({worst[1]}, "
                     f"{setting_label(worst[2])}, {METHODS[worst[3]].label}).")
    wins = [(setting, scene, c > b, c > p) for setting in SETTINGS
            for scene, c in _psnr(paper.results, setting, "cvqpg").items()
            if (b := _psnr(paper.results, setting, "baseline").get(scene)) is not None
            and (p := _psnr(paper.results, setting, "baseline+").get(scene)) is not None]
    if wins:
        lines.append(f"CVQPG above the Baseline in PSNR (paper: in all 200 comparisons of its five metrics): "
                     f"{sum(w[2] for w in wins)} of {len(wins)} scene–setting pairs; above Baseline⁺ at equal "
                     f"parameter count: {sum(w[3] for w in wins)} of {len(wins)}.")
    lines += frequency_claims(paper)
    lines += ablation_claims(grids["ablation"])
    lines += runtime_claims(paper)
    return lines


def frequency_claims(paper: GridResults) -> list[str]:
    peaks = paper_numbers()["frequency_peak_delta_mse_pct"]
    lines = []
    for color in ("rgb", "gray"):
        curves = [c for c in frequency_curves(paper.plan, paper.results) if c.setting.startswith(color)]
        name = "RGB" if color == "rgb" else "grayscale"
        if not curves:
            lines.append(f"Peak ΔMSE of CVQPG over the Baseline, {name}: paper about {peaks[color]}%; "
                         "not measured yet.")
            continue
        pairs = sum(c.pairs for c in curves)
        peak = float(np.nanmean([np.nanmax(c.delta_pct[:-1]) for c in curves]))
        complete = pairs == 2 * len(paper.grid.scenes)  # both ratios of the colour, every scene
        lines.append(f"Peak ΔMSE of CVQPG over the Baseline, {name}: ours {peak:.1f}% (mean of the settings' peaks, "
                     f"{pairs} scene pair{'s' * (pairs != 1)}), paper about {peaks[color]}%: "
                     f"{_within(peak - peaks[color], FREQUENCY_TOLERANCE_POINTS, complete)} (tolerance "
                     f"{FREQUENCY_TOLERANCE_POINTS:g} points).")
    return lines


def _ordered(values: dict[str, float]) -> str:
    """The methods from best to worst, written out with `≈` between neighbours closer than SIMILAR_DB
    (within one fit's spread between machines)."""
    ranked = sorted(values, key=lambda m: -values[m])
    text = METHODS[ranked[0]].label
    for previous, method in zip(ranked, ranked[1:]):
        text += f" {'≈' if values[previous] - values[method] < SIMILAR_DB else '>'} {METHODS[method].label}"
    return text


def order_differences(paper: dict[str, float], ours: dict[str, float]) -> tuple[list[str], list[str]]:
    """Where our means break the paper's order, over every pair of methods (PSNR, dB): pairs ours puts
    the other way round by SIMILAR_DB or more, and pairs the paper separates by SIMILAR_DB or more that
    ours leaves closer than that. Pairs the paper leaves closer than SIMILAR_DB agree unless reversed."""
    ranked = sorted(paper, key=lambda m: -paper[m])
    reversed_pairs, undecided_pairs = [], []
    for i, upper in enumerate(ranked):
        for lower in ranked[i + 1:]:
            ours_gap, paper_gap = ours[upper] - ours[lower], paper[upper] - paper[lower]
            text = (f"{METHODS[upper].label} − {METHODS[lower].label} {ours_gap:+.3f} dB "
                    f"(paper {paper_gap:+.3f})")
            if ours_gap <= -SIMILAR_DB:
                reversed_pairs.append(text)
            elif ours_gap < SIMILAR_DB <= paper_gap:
                undecided_pairs.append(text)
    return reversed_pairs, undecided_pairs


def ablation_claims(ablation: GridResults) -> list[str]:
    """The ablation's order against the paper's, judged pair by pair on means over the grid's scenes."""
    paper = {m: v["psnr"] for m, v in paper_numbers()["ablation"]["methods"].items()}
    claimed = _ordered(paper)
    scenes = set(ablation.grid.scenes)
    complete = {m: _psnr(ablation.results, "rgb-10", m) for m in ABLATION_METHODS}
    label = f"Ablation order by mean PSNR (paper: {claimed})"
    if any(set(v) != scenes for v in complete.values()):
        done = sum(len(v) for v in complete.values())
        return [f"{label}: not measured yet ({done} of {len(ablation.results)} cells)."]
    means = {m: float(np.mean(list(v.values()))) for m, v in complete.items()}
    reversed_pairs, undecided_pairs = order_differences(paper, means)
    gains = ", ".join(f"{METHODS[m].label} {means[m] - means['baseline']:+.3f} (paper "
                      f"{paper[m] - paper['baseline']:+.3f})" for m in ABLATION_METHODS if m != "baseline")
    differences = [f"{kind}: {'; '.join(pairs)}" for kind, pairs in (
        (f"reversed by {SIMILAR_DB} dB or more", reversed_pairs),
        (f"separated by the paper by {SIMILAR_DB} dB or more, by ours less", undecided_pairs)) if pairs]
    verdict = "the paper's order" if not differences else f"differs from the paper's order ({'; '.join(differences)})"
    return [f"{label}: ours {_ordered(means)} ('≈' closer than {SIMILAR_DB} dB; over the Baseline: {gains} dB): "
            f"{verdict}."]


def chromatic_claims(chromatic: GridResults) -> list[str]:
    """Our own target for per-channel curvature, per variant and RGB setting: a PSNR gain of at least
    CHROMATIC_TARGET_DB over the Baseline at equal N while ahead of the Baseline at the variant's parameter
    count (Baseline+pc, in the grid at RGB 10% only), where a lead or lag closer than SIMILAR_DB decides nothing.
    Met or not, or how it stands while cells are missing."""
    lines = []
    scenes = len(chromatic.grid.scenes)
    for method in ("per-channel", "channel-bound"):
        for setting in ("rgb-10", "rgb-20"):
            label = f"{METHODS[method].label}, {setting_label(setting)}"
            gain = _paired(chromatic.results, setting, method, "baseline")
            if gain is None:
                lines.append(f"{label}: not measured yet.")
                continue
            line = f"{label}: {gain[0]:+.3f} dB over the Baseline at equal N on {_scenes(gain[1])}"
            equal_parameters = "baseline+pc" in setting_methods(chromatic.plan, setting)
            ahead = _paired(chromatic.results, setting, method, "baseline+pc") if equal_parameters else None
            if ahead is not None:
                line += f", {ahead[0]:+.3f} dB against the Baseline at its parameter count on {_scenes(ahead[1])}"
            complete = gain[1] == scenes and (not equal_parameters or (ahead is not None and ahead[1] == scenes))
            detail = ""
            if gain[0] < CHROMATIC_TARGET_DB or (ahead is not None and ahead[0] <= -SIMILAR_DB):
                verdict = "not met"
            elif ahead is not None and ahead[0] < SIMILAR_DB:
                verdict, detail = "undecided", (f": level with the Baseline at its parameter count (closer than "
                                                f"{SIMILAR_DB} dB, one fit's spread between machines)")
            else:
                verdict = "met"
                if not equal_parameters:
                    detail = " at equal N (the equal-parameter cells are fitted at RGB 10% only)"
                elif ahead is None:
                    detail = " at equal N (the Baseline at its parameter count is not fitted yet)"
            verdict += ("" if complete else " so far") + detail
            lines.append(f"{line}: {verdict}.")
    return lines


def _paired(results: list[CellResult], setting: str, method: str, other: str) -> tuple[float, int] | None:
    ours, theirs = _psnr(results, setting, method), _psnr(results, setting, other)
    scenes = sorted(set(ours) & set(theirs))
    return (float(np.mean([ours[s] - theirs[s] for s in scenes])), len(scenes)) if scenes else None


def gain_per_scene_table(grid: GridResults, setting: str) -> Table:
    """Per scene, every method's PSNR gain over the Baseline's cell of that scene: whether a mean gain holds
    scene by scene."""
    methods = [m for m in setting_methods(grid.plan, setting) if m != "baseline"]
    table = Table(f"PSNR gain over the Baseline per scene (dB), {setting_label(setting)}",
                  ["scene", *(METHODS[m].label for m in methods)])
    base = _psnr(grid.results, setting, "baseline")
    values = {m: _psnr(grid.results, setting, m) for m in methods}
    for scene in grid.grid.scenes:
        gains = [values[m][scene] - base[scene] if scene in base and scene in values[m] else None for m in methods]
        if any(gain is not None for gain in gains):
            table.rows.append([scene, *(_signed(gain) for gain in gains)])
    return table


def runtime_table(grid: GridResults, with_paper: bool) -> Table:
    """Fit time and peak memory per setting and method, with the machines they ran on; beside the paper's
    supplementary table where `with_paper` (Table 1's settings and methods)."""
    runtime = paper_numbers()["runtime"]
    header = ["Setting", "Method", "N", "cells", "machines", "minutes", "Δ time", "GiB", "Δ memory", "load"]
    title = "Time and peak memory per fit (ours: the fit loop and the process's peak RSS"
    if with_paper:
        header += ["paper minutes", "paper Δ time", "paper GiB", "paper Δ memory"]
        title += f"; paper: {runtime['device']}, peak GPU memory"
    table = Table(f"{title}); Δ against the Baseline", header)
    table.note = ("Δ: the method's total over the Baseline's (in parentheses: over how many scenes), on the scenes "
                  "whose two cells ran the same commit on the same machine and thread count, for time only where "
                  f"both fits had their cores to themselves (load at most {QUIET_LOAD_PER_CORE} per core); – where "
                  "no scene has such a pair. load: the machine's mean 15-minute load average at the cells' ends, over "
                  "its core count (where recorded); above 1 the fits shared the cores with other work and took longer.")
    for setting in (s for s in SETTINGS if s in grid.plan.settings):
        for method in setting_methods(grid.plan, setting):
            ours = _runtime(grid, setting, method)
            row = [setting_label(setting), METHODS[method].label, f"{primitive_count(grid.plan, setting, method):,}",
                   "0" if ours is None else str(ours["cells"]), "–" if ours is None else ours["machines"],
                   "–" if ours is None else f"{ours['minutes']:.1f}", _relative(grid, setting, method, "minutes"),
                   "–" if ours is None else f"{ours['gib']:.2f}", _relative(grid, setting, method, "gib"),
                   "–" if ours is None or ours["load"] is None else f"{ours['load']:.1f}"]
            if with_paper:
                theirs = runtime[setting][method]
                row += [f"{theirs['minutes']:.1f}", f"{theirs['delta_time_pct']:+.1f}%", f"{theirs['memory_gib']:.1f}",
                        f"{theirs['delta_memory_pct']:+.1f}%"]
            table.rows.append(row)
    return table


def _runs(grid: GridResults, setting: str, method: str) -> dict[str, dict[str, Any]]:
    """Per scene, the run record of the method's finished cell in `setting`."""
    return {r.cell.scene.name: r.metrics["run"] for r in grid.done
            if (r.cell.setting, r.cell.method) == (setting, method) and r.metrics.get("run")}


def _machine(run: dict[str, Any]) -> str:
    """A run's device and thread count, short enough for a table cell."""
    device = run["device"].replace("(R)", "").replace("(TM)", "").removeprefix("cpu: ")
    threads = run["torch_threads"]
    return f"{device}, {threads} thread{'s' * (threads != 1)}" if run["device"].startswith("cpu") else device


def _quiet(run: dict[str, Any]) -> bool:
    """Whether the fit had its cores to itself (the load at its end at most QUIET_LOAD_PER_CORE per core)."""
    return run.get("load_average") is not None and run["load_average"] / run["machine_cores"] <= QUIET_LOAD_PER_CORE


def _against_baseline(grid: GridResults, setting: str, method: str, key: str, quiet: bool = False
                      ) -> tuple[float, int] | None:
    """The method's total `key` (minutes or gib) over the Baseline's minus one, and the number of scenes, over
    the scenes whose two cells ran the same code on the same machine and thread count (and, with `quiet`, each
    with its cores to itself): across machines or commits a time says more about them than about the method."""
    ours, base = _runs(grid, setting, method), _runs(grid, setting, "baseline")
    pairs = [(ours[s], base[s]) for s in sorted(set(ours) & set(base))
             if (_machine(ours[s]), ours[s]["commit"]) == (_machine(base[s]), base[s]["commit"])
             and (not quiet or (_quiet(ours[s]) and _quiet(base[s])))]
    if not pairs:
        return None
    field = {"minutes": "loop_seconds", "gib": "peak_memory_bytes"}[key]
    return sum(a[field] for a, _ in pairs) / sum(b[field] for _, b in pairs) - 1, len(pairs)


def _relative(grid: GridResults, setting: str, method: str, key: str) -> str:
    """The table's Δ column: times only from fits that had their cores to themselves, memory from any."""
    ratio = _against_baseline(grid, setting, method, key, quiet=key == "minutes")
    return "–" if ratio is None else f"{ratio[0] * 100:+.1f}% ({ratio[1]})"


def runtime_claims(paper: GridResults) -> list[str]:
    """The paper: CVQPG costs about what the baseline costs (0.0% time in RGB, +3% in grayscale)."""
    runtime = paper_numbers()["runtime"]
    lines = []
    for setting in SETTINGS:
        claimed = runtime[setting]["cvqpg"]["delta_time_pct"]
        label = f"Time of CVQPG against the Baseline, {setting_label(setting)}: paper {claimed:+.1f}%"
        quiet = _against_baseline(paper, setting, "cvqpg", "minutes", quiet=True)
        if not _runs(paper, setting, "cvqpg") or not _runs(paper, setting, "baseline"):
            lines.append(f"{label}; not measured yet.")
        elif quiet is None:
            lines.append(f"{label}; ours not comparable from these cells: no scene has both cells fitted by the same "
                         "commit on the same machine, each with its cores to itself, and a recorded cell is not fitted "
                         "again (`python benchmarks/step.py` times flat and curved steps side by side).")
        else:
            lines.append(f"{label}, ours {quiet[0] * 100:+.1f}% on {_scenes(quiet[1])} whose two cells ran the same "
                         "commit on the same machine, each with its cores to itself.")
    return lines


def _runtime(grid: GridResults, setting: str, method: str) -> dict[str, Any] | None:
    """Mean minutes, GiB and load per core of the method's cells in `setting`, their count and machines."""
    runs = list(_runs(grid, setting, method).values())
    if not runs:
        return None
    loads = [run["load_average"] / run["machine_cores"] for run in runs if run.get("load_average") is not None]
    machines = Counter(_machine(run) for run in runs)
    return {"cells": len(runs), "minutes": float(np.mean([run["loop_seconds"] for run in runs])) / 60,
            "gib": float(np.mean([run["peak_memory_bytes"] for run in runs])) / GIB,
            "load": float(np.mean(loads)) if loads else None,
            "machines": "; ".join(f"{count} × {machine}" for machine, count in sorted(machines.items()))}


BEYOND_TARGET_DB = 0.5  # the target of the beyond recipe's CVQPG over the paper grid's, at 2000 steps
BEYOND_TIME_TARGET_DB = 1.5  # and at the paper's training time over the paper's own per-scene values


def beyond_table(paper: GridResults, beyond: GridResults, setting: str) -> Table:
    """Per scene at equal N and 2000 steps: CVQPG with the new recipe against the paper grid's CVQPG cell
    (PSNR, SSIM, FLIP), and CVQPG's gain over the Baseline under each recipe beside the paper's."""
    table = Table(f"The new recipe against the paper's, {setting_label(setting)}, 2000 steps (dB unless named)",
                  ["scene", "CVQPG paper recipe", "CVQPG new", "Δ PSNR", "Δ SSIM", "Δ FLIP", "gain new",
                   "gain paper recipe", "gain paper"])
    supplement = paper_numbers()["per_scene"]
    old = {m: _metric(paper.results, setting, "cvqpg", m) for m in ("psnr", "ssim", "flip")}
    new = {m: _metric(beyond.results, setting, "cvqpg", m) for m in ("psnr", "ssim", "flip")}
    new_base, old_base = (_metric(g.results, setting, "baseline", "psnr") for g in (beyond, paper))
    for scene in beyond.grid.scenes:
        if scene not in new["psnr"]:
            continue
        deltas = [_signed(new[m][scene] - old[m][scene] if scene in old[m] else None, 4 if m != "psnr" else 3)
                  for m in ("psnr", "ssim", "flip")]
        gains = [_signed(c[scene] - b[scene] if scene in b and scene in c else None)
                 for c, b in ((new["psnr"], new_base), (old["psnr"], old_base))]
        theirs = supplement[scene][setting]
        table.rows.append([scene, "–" if scene not in old["psnr"] else f"{old['psnr'][scene]:.3f}",
                           f"{new['psnr'][scene]:.3f}", *deltas, *gains,
                           f"{theirs['cvqpg']['psnr'] - theirs['baseline']['psnr']:+.3f}"])
    return table


def timed_table(timed: GridResults, setting: str) -> Table:
    """Per scene: CVQPG with the new recipe for the paper's training time, against the paper's own value."""
    table = Table(f"The new recipe at the paper's training time, {setting_label(setting)}",
                  ["scene", "steps", "minutes here", "PSNR", "paper's CVQPG", "Δ"])
    supplement = paper_numbers()["per_scene"]
    for r in timed.done:
        if r.cell.setting != setting:
            continue
        ours, theirs = r.metrics["mean"]["psnr"], supplement[r.cell.scene.name][setting]["cvqpg"]["psnr"]
        minutes = (r.metrics.get("run") or {}).get("loop_seconds")
        table.rows.append([r.cell.scene.name, str(r.cell.config.optimisation.steps),
                           "–" if minutes is None else f"{minutes / 60:.1f}",
                           f"{ours:.3f}", f"{theirs:.3f}", f"{ours - theirs:+.3f}"])
    return table


SECONDS_SCENE = "sushi"  # the scene of the PSNR-against-seconds figures


def seconds_figure_name(setting: str) -> str:
    """E.g. `beyond_seconds_gray10.png`, beside docs/results.md."""
    return f"beyond_seconds_{setting.replace('-', '')}.png"


def seconds_curves(paper: GridResults, timed: GridResults, setting: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """`SECONDS_SCENE`'s CVQPG cells of the paper grid and of the new recipe's timed grid as label → (seconds,
    progress PSNR) from their `history.csv`; cells without one are left out."""
    curves = {}
    for grid, label in ((paper, "the paper's recipe, {steps} steps"),
                        (timed, "the new recipe, the paper's training time ({steps} steps)")):
        cell = next((r.cell for r in grid.done if r.cell.setting == setting and r.cell.method == "cvqpg"
                     and r.cell.scene.name == SECONDS_SCENE), None)
        path = None if cell is None else grid.plan.cell_dir(cell) / HISTORY_FILE
        if path is not None and path.is_file():
            history = read_history(path)
            curves[label.format(steps=f"{cell.config.optimisation.steps:,}")] = (history["seconds"], history["psnr"])
    return curves


SECONDS_GRIDS = ("paper", "beyond-time")


def drawable_seconds_curves(grids: dict[str, GridResults]) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Setting → its curves (`seconds_curves`), for the settings whose every curve is recorded."""
    curves = {s: seconds_curves(*(grids[g] for g in SECONDS_GRIDS), s) for s in BEYOND_SETTINGS}
    return {s: c for s, c in curves.items() if len(c) == len(SECONDS_GRIDS)}


def seconds_lines(grids: dict[str, GridResults]) -> list[str]:
    """The PSNR-against-seconds figures that `write_figures` draws, or what each still waits for."""
    lines = []
    drawable = drawable_seconds_curves(grids)
    for setting in BEYOND_SETTINGS:
        name, label = seconds_figure_name(setting), setting_label(setting)
        if setting in drawable:
            lines += [f"![PSNR against minutes, {SECONDS_SCENE}, {label}]({name})", ""]
        else:
            lines += [f"PSNR against minutes, {SECONDS_SCENE}, {label}: waits for its CVQPG cells in "
                      f"{' and '.join(f'`results/{g}`' for g in SECONDS_GRIDS)}, each with a `{HISTORY_FILE}` (cells "
                      "fitted before it existed have none; refit them to draw it).", ""]
    return lines


def write_figures(root: Path, folder: Path, overwrite: bool = False) -> list[Path]:
    """Draw into `folder` the PSNR-against-seconds figures whose curves the records under `root` hold; returns them.
    An existing figure is replaced only with `overwrite` (`InputError` otherwise, before anything is drawn)."""
    grids = {p: load_grid(next(g for g in CAMPAIGN if g.preset == p), root) for p in SECONDS_GRIDS}
    drawn = {folder / seconds_figure_name(s): (s, curves) for s, curves in drawable_seconds_curves(grids).items()}
    for path in drawn:
        check_output(path, FIGURE, [], overwrite)
    for path, (setting, curves) in drawn.items():
        psnr_seconds_figure(curves, f"{SECONDS_SCENE}, CVQPG, {setting_label(setting)}, one thread each", path)
    return list(drawn)


def beyond_claims(paper: GridResults, beyond: GridResults, timed: GridResults) -> list[str]:
    """The beyond recipe's targets, met or not, or how they stand while cells are missing."""
    lines = []
    scenes = len(beyond.grid.scenes)
    supplement = paper_numbers()["per_scene"]
    for setting in BEYOND_SETTINGS:
        label = f"New recipe's CVQPG over the paper grid's, {setting_label(setting)}, 2000 steps"
        old = {m: _metric(paper.results, setting, "cvqpg", m) for m in ("psnr", "ssim", "flip")}
        new = {m: _metric(beyond.results, setting, "cvqpg", m) for m in ("psnr", "ssim", "flip")}
        shared = sorted(set(old["psnr"]) & set(new["psnr"]))
        if not shared:
            lines.append(f"{label}: not measured yet.")
        else:
            delta = {m: float(np.mean([new[m][s] - old[m][s] for s in shared])) for m in ("psnr", "ssim", "flip")}
            ahead = sum(new["psnr"][s] > old["psnr"][s] for s in shared)
            met = (delta["psnr"] >= BEYOND_TARGET_DB and ahead == len(shared) and delta["ssim"] >= 0
                   and delta["flip"] <= 0)
            lines.append(f"{label}: {delta['psnr']:+.3f} dB mean on {_scenes(len(shared))} (ahead on {ahead}), SSIM "
                         f"{delta['ssim']:+.4f}, FLIP {delta['flip']:+.4f}; target {BEYOND_TARGET_DB:+.1f} dB ahead on "
                         f"every scene with SSIM and FLIP no worse: {'met' if met else 'not met'}"
                         f"{'' if len(shared) == scenes else ' so far'}.")
        gains = _paired(beyond.results, setting, "cvqpg", "baseline")
        if gains is not None:
            paper_gains = [supplement[s][setting]["cvqpg"]["psnr"] - supplement[s][setting]["baseline"]["psnr"]
                           for s in beyond.grid.scenes]
            claimed = float(np.mean(paper_gains))
            lines.append(f"CVQPG − Baseline at equal N under the new recipe, {setting_label(setting)}: "
                         f"{gains[0]:+.3f} dB on {_scenes(gains[1])} (paper {claimed:+.3f} on our six scenes).")
        timed_values = {r.cell.scene.name: r.metrics["mean"]["psnr"] for r in timed.done if r.cell.setting == setting}
        time_label = f"New recipe's CVQPG at the paper's training time, {setting_label(setting)}"
        if not timed_values:
            lines.append(f"{time_label}: not measured yet.")
            continue
        gain = float(np.mean([v - supplement[s][setting]["cvqpg"]["psnr"] for s, v in timed_values.items()]))
        verdict = "met" if gain >= BEYOND_TIME_TARGET_DB else "not met"
        lines.append(f"{time_label}: {gain:+.3f} dB mean over the paper's per-scene values on "
                     f"{_scenes(len(timed_values))}; target {BEYOND_TIME_TARGET_DB:+.1f} dB: {verdict}"
                     f"{'' if len(timed_values) == scenes else ' so far'}.")
    return lines


DISPLAY_SETTINGS = ("gray-10", "rgb-10")
DISPLAY_TARGET_MEAN_DB = 1.2  # the display fit over the complex fit's exported display: mean over the scenes
DISPLAY_TARGET_SCENE_DB = 0.5  # and on every scene
DISPLAY_METRICS = ("psnr", "ssim", "flip")


def _shown(grid: GridResults, setting: str, method: str, metric: str = "psnr") -> dict[str, float]:
    """Per scene, `metric` of what the display shows of the finished cell of `setting` and `method`: a display
    fit's own metrics lead with its display's, and a complex fit exported after it has the export's
    (`report.collect`)."""
    return {r.cell.scene.name: r.metrics["mean"][metric] for r in grid.done
            if r.cell.setting == setting and r.cell.method == method and r.metrics.get("mean")
            and r.metrics["mean"].get(metric) is not None}


def _cell_values(grid: GridResults, setting: str, method: str, key: str) -> dict[str, float]:
    """Per scene, the number `key` of the finished cell's `metrics.json` (`seconds`, `num_params`)."""
    return {r.cell.scene.name: r.metrics[key] for r in grid.done
            if r.cell.setting == setting and r.cell.method == method and r.metrics.get(key) is not None}


def _mean_text(values: dict[str, float], decimals: int) -> str:
    return "–" if not values else f"{np.mean(list(values.values())):.{decimals}f}"


def display_table(grid: GridResults, setting: str) -> Table:
    """Per method, means over its finished scenes of what the display shows, with its parameters, steps and fit
    seconds on this machine."""
    table = Table(f"What the display shows, {setting_label(setting)} (means over the scenes)",
                  ["method", "scenes", "PSNR (dB)", "SSIM", "FLIP", "parameters", "steps", "fit seconds"])
    for method in DISPLAY_METHODS:
        cells = [r.cell for r in grid.results if r.cell.setting == setting and r.cell.method == method]
        if not cells:
            continue
        config = cells[0].config
        psnr = _shown(grid, setting, method)
        table.rows.append([METHODS[method].label, str(len(psnr)), _mean_text(psnr, 3),
                           *(_mean_text(_shown(grid, setting, method, m), 4) for m in ("ssim", "flip")),
                           f"{config.primitive_count * config.params_per_primitive:,}",
                           f"{config.optimisation.steps:,}", _mean_text(_cell_values(grid, setting, method, "seconds"), 0)])
    return table


def display_scene_table(grid: GridResults, setting: str) -> Table:
    """Per scene, the display's PSNR (dB) of every method."""
    table = Table(f"PSNR of what the display shows per scene (dB), {setting_label(setting)}",
                  ["scene", *(METHODS[m].label for m in DISPLAY_METHODS)])
    values = {m: _shown(grid, setting, m) for m in DISPLAY_METHODS}
    for scene in grid.grid.scenes:
        if any(scene in v for v in values.values()):
            table.rows.append([scene, *("–" if scene not in values[m] else f"{values[m][scene]:.3f}"
                                        for m in DISPLAY_METHODS)])
    return table


def _difference(grid: GridResults, setting: str, method: str, other: str) -> dict[str, float]:
    """Per scene where both have finished: the display PSNR of `method` minus that of `other` (dB)."""
    mine, theirs = _shown(grid, setting, method), _shown(grid, setting, other)
    return {s: mine[s] - theirs[s] for s in mine if s in theirs}


def display_claims(grid: GridResults) -> list[str]:
    """The display fit's target against the complex fit's export, and where CVQPG at 10% of the pixels stands
    against the per-pixel hologram at equal steps and at equal time, or how many cells are missing."""
    lines = []
    scenes = len(grid.grid.scenes)
    for setting in DISPLAY_SETTINGS:
        label = setting_label(setting)
        gain = _difference(grid, setting, "cvqpg-dpac", "cvqpg-exported")
        if not gain:
            lines.append(f"CVQPG fitted through the display against fitted complex and exported, {label}: not measured "
                         "yet.")
        else:
            mean, low = float(np.mean(list(gain.values()))), min(gain, key=gain.get)
            met = mean >= DISPLAY_TARGET_MEAN_DB and gain[low] >= DISPLAY_TARGET_SCENE_DB
            lines.append(f"CVQPG fitted through the display against fitted complex and exported, {label}: "
                         f"{mean:+.3f} dB mean on {_scenes(len(gain))}, per scene "
                         + ", ".join(f"{s} {v:+.2f}" for s, v in sorted(gain.items()))
                         + f" (least: {low}); target {DISPLAY_TARGET_MEAN_DB:+.1f} dB mean and "
                         f"{DISPLAY_TARGET_SCENE_DB:+.1f} on every scene: {'met' if met else 'not met'}"
                         f"{'' if len(gain) == scenes else ' so far'}.")
        for other, rival in (("pixel-dpac", "the per-pixel hologram through the display at equal steps"),
                             ("pixel-dpac-time", "the per-pixel hologram through the display at equal time"),
                             ("pixel-phase", "the per-pixel phase pattern at equal steps")):
            delta = _difference(grid, setting, "cvqpg-dpac", other)
            what = f"CVQPG through the display at 10% of the pixels against {rival}, {label}"
            if not delta:
                lines.append(f"{what}: not measured yet.")
                continue
            ahead = sum(v > 0 for v in delta.values())
            seconds = {m: _cell_values(grid, setting, m, "seconds") for m in ("cvqpg-dpac", other)}
            shared = sorted(set(seconds["cvqpg-dpac"]) & set(seconds[other]) & set(delta))
            timing = "" if not shared else (
                f"; fit seconds {np.mean([seconds['cvqpg-dpac'][s] for s in shared]):.0f} against "
                f"{np.mean([seconds[other][s] for s in shared]):.0f}")
            lines.append(f"{what}: {float(np.mean(list(delta.values()))):+.3f} dB mean on {_scenes(len(delta))} "
                         f"(CVQPG ahead on {ahead}), from {min(delta.values()):+.2f} to {max(delta.values()):+.2f}"
                         f"{timing}.")
    return lines


def check_recorded(root: Path) -> None:
    """`RecordError` where `root` holds none of the campaign's cells: its document would summarise nothing."""
    grids = [load_grid(g, root) for g in CAMPAIGN]
    if not any(r.status == DONE for g in grids for r in g.results):
        cells = sum(len(g.results) for g in grids)
        raise RecordError(f"{root} holds none of the campaign's {cells} cells: nothing to summarise; give the folder "
                          "of its bench folders (e.g. results)")


def document(root: Path) -> str:
    """The whole of `docs/results.md` from the records under `root` (`results/`)."""
    grids = {g.preset: load_grid(g, root) for g in CAMPAIGN}
    paper, chromatic, ablation = grids["paper"], grids["chromatic"], grids["ablation"]
    beyond, timed = grids["beyond"], grids["beyond-time"]
    parts = ["# Results against the paper", "",
             "Generated by `cvqpg results` from the cell records in `results/` (each cell's `config.json`, "
             "`metrics.json` and `spectrum.json`); do not edit it by hand, the test suite holds it to those "
             "records. All fits: 640×480, 2 planes at 1 and 5 mm, 2000 steps (2001 updates), warm-up 400, "
             "seed 100. LPIPS and CVVDP read n/a where the fitting machine could not run them (no torchvision).",
             "", status_table(list(grids.values())).markdown(),
             *(f"- {line}" for line in machine_lines(list(grids.values()))), "",
             "The commands, in the campaign's order (each skips the cells already recorded):", "", "```bash",
             *(command for g in CAMPAIGN for command in g.commands), "```", "",
             "## The paper's claims", "", *(f"- {line}" for line in claim_lines(grids)), "",
             "## Table 1", "", table1(paper).markdown(), per_scene_table(paper).markdown(),
             "## Frequency-resolved ΔMSE", "",
             *(f"- {line}" for line in frequency_lines(frequency_curves(paper.plan, paper.results))), "",
             "## Ablation (RGB 10%)", "",
             f"Scenes: {', '.join(ABLATION_SCENES)}. The paper does not name its five; its means match its "
             f"per-scene rows of {', '.join(paper_numbers()['ablation']['scenes_matched'])}.", "",
             *(t.markdown() for t in variant_tables(ablation.plan, ablation.results)),
             *(t.markdown() for t in (gain_per_scene_table(ablation, "rgb-10"),) if t.rows),
             "## Chromatic curvature (beyond the paper)", "",
             "Per-channel γ (`--curvature per-channel`, one γ per colour bounded by its own wavelength) and "
             "channel-bound γ against shared CVQPG and the Baseline at equal N, and at per-channel's parameter "
             f"count (Baseline+pc, CVQPG+pc). Our target: at least {CHROMATIC_TARGET_DB:+.2f} dB over the Baseline at "
             "equal N, while ahead of the Baseline at the variant's parameter count.", "",
             *(f"- {line}" for line in chromatic_claims(chromatic)), "",
             *(t.markdown() for t in variant_tables(chromatic.plan, chromatic.results)),
             *(t.markdown() for t in (gain_per_scene_table(chromatic, s) for s in ("rgb-10", "rgb-20")) if t.rows),
             *(f"- {line}" for line in frequency_lines(channel_frequency_curves(chromatic.plan, chromatic.results))
               if chromatic.done), "", runtime_table(chromatic, with_paper=False).markdown(),
             "## Beyond the paper: the new recipe", "",
             f"`--recipe {PRESETS['beyond'].recipe}` (docs/beyond.md) at equal N against the paper grid's cells above, "
             "evaluated alike (mean PSNR over the planes against the noise-free targets). In runs of more than "
             f"{SHORT_RUN_STEPS} steps, as here, it differs from the paper's recipe in two settings: Adan's β2 is "
             f"{LONG_RUN_BETAS[1]} (the paper's {PAPER_BETAS[1]}), and {1 - EDGES_UNIFORM_SHARE:.0%} of the initial "
             "positions are drawn at the targets' edges (`init` `edges`).", "",
             *(f"- {line}" for line in beyond_claims(paper, beyond, timed)), "",
             *(beyond_table(paper, beyond, s).markdown() for s in BEYOND_SETTINGS),
             *(t.markdown() for t in (timed_table(timed, s) for s in BEYOND_SETTINGS) if t.rows),
             "The progress PSNR (mean over the planes, before clamping) against the minutes of the fit's loop, "
             "from the cells' `history.csv`. Each cell's minutes are its own, on one thread beside the other work "
             "of its machine (the load average is in its `metrics.json`): compare the curves' shapes, and the "
             "steps, rather than their minutes.", "", *seconds_lines(grids),
             "## What a phase-only SLM shows (beyond the paper)", "",
             "Every row is shown on the same simulated display: DPAC of the SLM field on a phase-only SLM of 256 "
             "levels behind the 4f system's aperture (docs/method.md §8), evaluated against the noise-free targets. "
             "`CVQPG, fitted complex, then exported` is today's `cvqpg fit` followed by `cvqpg export`; the others "
             "see that display in their loss (`--display dpac`; the per-pixel phase pattern `--display phase`: its "
             "bare phase, behind the same aperture, which blocks the light a phase-only SLM cannot dim). The Gaussian "
             "rows fit with the default recipe at 10% of the pixels, the "
             "per-pixel rows with the `pixel` recipe (docs/beyond.md); `CVQPG's time` gives the per-pixel hologram "
             "as many steps as take the CVQPG display fit's time on our CPU (docs/bench.md).", "",
             *(f"- {line}" for line in display_claims(grids["display"])), "",
             *(t.markdown() for s in DISPLAY_SETTINGS for t in (display_table(grids["display"], s),
                                                                display_scene_table(grids["display"], s)) if t.rows),
             "## Runtime", "", runtime_table(paper, with_paper=True).markdown()]
    return "\n".join(parts).rstrip() + "\n"
