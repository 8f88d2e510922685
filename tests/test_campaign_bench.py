"""`cvqpg bench`: the quick preset end to end, resumable and shardable cells, tables against the
paper, and the radial error spectrum of the frequency analysis."""

import csv
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg.campaign import bench
from cvqpg.campaign.bench import (DONE, INTERRUPTED, BenchError, Overrides, cell_status, folder_plan, make_plan,
                                  parse_shard, run_cell, run_plan)
from cvqpg.cli import main
from cvqpg.control import SILENT, RunControl
from cvqpg.app import provenance
from cvqpg.metrics import radial_error_spectrum
from cvqpg.campaign.report import CellResult, cells_table, devices_line, main_table, paper_numbers, seed_tables
from cvqpg.runs import start_run
from cvqpg.storage import load_checkpoint, save_checkpoint

TINY_STAR = {"size": (48, 36), "steps": 3, "methods": ["baseline"]}


@pytest.fixture(scope="module")
def quick_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "quick"
    assert main(["bench", "--preset", "quick", "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.slow
def test_quick_preset_writes_tables_figures_and_report(quick_bench):
    plan = make_plan("quick", quick_bench)
    assert len(plan.cells) == 4 and {c.method for c in plan.cells} == {"baseline", "cvqpg"}
    for cell in plan.cells:
        assert cell_status(plan.cell_dir(cell)) == DONE
        spectrum = json.loads((plan.cell_dir(cell) / "spectrum.json").read_text())
        assert len(spectrum["power"]) == spectrum["bins"] + 1 and spectrum["mse"] > 0
    summary = (quick_bench / "summary.md").read_text()
    assert "cells: 4 of 4 done" in summary and "| Grayscale 10% | Δ (CVQPG − Baseline) |  | 2/2 |" in summary
    with open(quick_bench / "summary.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["method"] for r in rows] == ["baseline", "cvqpg", "delta cvqpg-baseline"]
    assert all(float(r["psnr"]) > 5 for r in rows[:2])
    metrics = json.loads((plan.cell_dir(plan.cells[0]) / "metrics.json").read_text())
    for name in ("lpips", "cvvdp"):
        if metrics["mean"][name] is None:
            assert {r[name] for r in rows} == {"n/a"}
    with open(quick_bench / "cells.csv") as handle:
        cells = list(csv.DictReader(handle))
    assert {(c["status"], c["steps"], c["updates"]) for c in cells} == {("done", "60", "61")}
    assert all(float(c["seconds"]) > 0 for c in cells)
    with open(quick_bench / "frequency.csv") as handle:
        bands = list(csv.DictReader(handle))
    assert len(bands) == 33 and {b["pairs"] for b in bands} == {"2"} and bands[-1]["band"].startswith("beyond")
    report = (quick_bench / "report.html").read_text()
    images = re.findall(r"src='([^']+)'", report)
    assert {"frequency.png", "figures/qpf.png", "figures/compare_demo_gray-10.png"} <= set(images)
    assert all((quick_bench / image).is_file() for image in images) and report.count("<table>") >= 3


@pytest.mark.slow
def test_rerun_skips_finished_cells_and_summary_only_fits_nothing(quick_bench, capsys):
    stamps = {p: p.stat().st_mtime_ns for p in quick_bench.glob("cells/*/metrics.json")}
    assert len(stamps) == 4
    assert main(["bench", "--preset", "quick", "--out", str(quick_bench), "--quiet"]) == 0
    assert "0 done, 4 skipped" in capsys.readouterr().out
    (quick_bench / "summary.md").unlink()
    assert main(["bench", "--preset", "quick", "--out", str(quick_bench), "--summary-only"]) == 0
    assert (quick_bench / "summary.md").is_file()
    assert {p: p.stat().st_mtime_ns for p in quick_bench.glob("cells/*/metrics.json")} == stamps


@pytest.mark.slow
def test_finished_cells_with_other_settings_are_refused(quick_bench, capsys):
    assert main(["bench", "--preset", "quick", "--out", str(quick_bench), "--steps", "5", "--quiet"]) == 2
    error = capsys.readouterr().err
    assert "fitted with other settings" in error and "steps=60" in error and error.count("\n") == 1


@pytest.mark.slow
def test_report_links_cells_that_have_a_view_page(quick_bench):
    plan = make_plan("quick", quick_bench)
    viewed, *others = plan.cells
    assert main(["view", str(plan.cell_dir(viewed)), "--distances", "0.001", "0.005", "2", "--quiet"]) == 0
    assert main(["bench", "--preset", "quick", "--out", str(quick_bench), "--summary-only"]) == 0
    link = f"cells/{viewed.name}/view.html"
    assert f"<a href='{link}'>{viewed.name}</a>" in (quick_bench / "report.html").read_text()
    assert f"[{viewed.name}]({link})" in (quick_bench / "summary.md").read_text()
    assert re.findall(r"href='([^']+)'", (quick_bench / "report.html").read_text()) == [link]
    assert all(not (plan.cell_dir(cell) / "view.html").exists() for cell in others)


def test_shards_partition_the_grid(scenes_dir, tmp_path):
    plan = make_plan("paper", tmp_path / "bench", Overrides(scenes_dir=scenes_dir))
    names = [c.name for c in plan.cells]
    assert len(names) == len(set(names)) == 3 * 2 * 2 * 3
    for count in (1, 2, 5, 7, 40):
        shards = [[c.name for c in plan.shard(index, count)] for index in range(1, count + 1)]
        assert sorted(n for shard in shards for n in shard) == sorted(names)
        assert sum(len(shard) for shard in shards) == len(names)
    assert parse_shard("2/4") == (2, 4)
    for bad in ("3/2", "0/4", "1/0", "a/b", "1", "1/2/3"):
        with pytest.raises(BenchError):
            parse_shard(bad)


def test_methods_map_to_the_papers_configurations(scenes_dir, tmp_path):
    plan = make_plan("paper", tmp_path / "bench", Overrides(scenes_dir=scenes_dir))
    counts = {(c.setting, c.method): c.config.primitive_count for c in plan.cells}
    for setting, methods in paper_numbers()["table1"].items():
        for method, values in methods.items():
            assert counts[(setting, method)] == values["n"], (setting, method)
    ablation_plan = make_plan("ablation", tmp_path / "a", Overrides(scenes_dir=scenes_dir))
    ablation = {c.method: c.config.primitives for c in ablation_plan.cells}
    assert (ablation["baseline"].kind, ablation["cvqpg"].bound, ablation["cvqpg"].qpf) == ("flat", "adaptive",
                                                                                           "mahalanobis")
    assert (ablation["no-bound"].bound, ablation["no-bound"].qpf) == ("global", "mahalanobis")
    assert (ablation["no-mahalanobis"].bound, ablation["no-mahalanobis"].qpf) == ("adaptive", "standard")
    assert (ablation["vanilla"].bound, ablation["vanilla"].qpf, ablation["vanilla"].kind) == (
        "global", "standard", "cvqpg")
    star = make_plan("star").cells
    assert {(c.config.targets.num_planes, c.config.targets.color, c.config.primitive_count)
            for c in star} == {(1, "gray", 7680)}
    assert make_plan("quick", overrides=Overrides(steps=50)).cells[0].config.optimisation.curvature_warmup == 10


def test_chromatic_preset_compares_at_equal_n_and_at_per_channel_parameter_count(scenes_dir, tmp_path):
    plan = make_plan("chromatic", tmp_path / "bench", Overrides(scenes_dir=scenes_dir, scene_names=["tiger"]))
    configs = {(c.setting, c.method): c.config for c in plan.cells}
    assert plan.settings == ("rgb-20", "rgb-10")
    for setting, n in (("rgb-10", 15360), ("rgb-20", 30720)):
        assert {m: configs[(setting, m)].primitive_count for m in plan.methods} == {
            "baseline": n, "cvqpg": n, "per-channel": n, "channel-bound": n,
            "baseline+pc": round(n * 15 / 12), "cvqpg+pc": round(n * 15 / 13)}
    curvatures = {m: (configs[("rgb-10", m)].primitives.kind, configs[("rgb-10", m)].primitives.curvature)
                  for m in plan.methods}
    assert curvatures["per-channel"] == ("cvqpg", "per-channel")
    assert curvatures["channel-bound"] == ("cvqpg", "channel-bound")
    assert curvatures["cvqpg+pc"] == ("cvqpg", "shared") and curvatures["baseline+pc"][0] == "flat"


@pytest.mark.slow
def test_chromatic_bench_reports_variants_and_per_channel_spectra(tmp_path):
    root = tmp_path / "scenes" / "noise"
    root.mkdir(parents=True)
    generator = np.random.default_rng(3)
    Image.fromarray(generator.integers(0, 256, (36, 48, 3), dtype=np.uint8)).save(root / "image.png")
    Image.fromarray(np.tile(np.linspace(0, 255, 48, dtype=np.uint8), (36, 1))).save(root / "depth.png")
    out = tmp_path / "bench"
    assert main(["bench", "--preset", "chromatic", "--scenes", str(root.parent), "--size", "48", "36",
                 "--steps", "4", "--ratios", "0.1", "--out", str(out), "--quiet"]) == 0
    summary = (out / "summary.md").read_text()
    assert "### Variants against the baseline, RGB 10%" in summary
    assert "| CVQPG, γ per channel | 86 |" in summary and "| Baseline (per-channel's params) | 108 |" in summary
    with open(out / "frequency_channels.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["channel"] for r in rows[::33]] == ["red", "green", "blue"] and len(rows) == 3 * 33
    assert {"mse_cvqpg", "mse_per-channel", "delta_mse_pct"} <= set(rows[0])
    assert (out / "frequency_channels.png").is_file()
    assert "blue: peak ΔMSE of CVQPG, γ per channel over CVQPG" in summary


@pytest.mark.slow
def test_partial_files_do_not_mark_a_cell_done_and_it_restarts(tmp_path):
    plan = make_plan("star", tmp_path / "bench", Overrides(**TINY_STAR))
    cell = plan.cells[0]
    folder = start_run(plan.cell_dir(cell), cell.config, cell.scene.source)
    (folder / "metrics.json.partial").write_text('{"mean": ')
    (folder / "metrics.json.4242.partial").write_text("{}")
    (folder / "checkpoint.pt").write_bytes(b"cut short")
    assert cell_status(folder) == INTERRUPTED
    outcome = run_plan(plan, control=SILENT)
    assert outcome.statuses == {cell.name: DONE} and cell_status(folder) == DONE
    assert json.loads((folder / "metrics.json").read_text())["updates"] == 4


@pytest.mark.slow
def test_interrupted_cell_resumes_from_its_checkpoint_to_the_same_result(tmp_path):
    overrides = Overrides(size=(48, 36), steps=8, curvature_warmup=2, methods=["cvqpg"])
    plan, reference = (make_plan("star", tmp_path / name, overrides) for name in ("bench", "reference"))
    cell = plan.cells[0]
    folder = plan.cell_dir(cell)
    checks = iter(range(100))
    assert run_cell(cell, folder, RunControl(progress=False, stop_requested=lambda: next(checks) > 5)) == INTERRUPTED
    assert cell_status(folder) == INTERRUPTED and not (folder / "metrics.json").exists()
    assert load_checkpoint(folder / "checkpoint.pt")["step"] == 5
    assert run_plan(plan, control=SILENT).statuses == {cell.name: DONE}
    assert run_plan(reference, control=SILENT).statuses == {cell.name: DONE}
    resumed, fresh = (json.loads((p.cell_dir(cell) / "metrics.json").read_text()) for p in (plan, reference))
    assert resumed["mean"] == fresh["mean"] and resumed["updates"] == 9


@pytest.mark.slow
def test_a_cell_checkpointed_on_another_device_restarts_from_step_0(tmp_path, caplog):
    plan = make_plan("star", tmp_path / "bench", Overrides(**TINY_STAR))
    cell = plan.cells[0]
    folder = plan.cell_dir(cell)
    checks = iter(range(100))
    assert run_cell(cell, folder, RunControl(progress=False, stop_requested=lambda: next(checks) > 2)) == INTERRUPTED
    payload = load_checkpoint(folder / "checkpoint.pt")
    payload["device"], payload["generator"] = "cuda", torch.zeros(16, dtype=torch.uint8)
    save_checkpoint(folder / "checkpoint.pt", payload)
    with caplog.at_level("WARNING", logger="cvqpg"):
        assert run_plan(plan, control=SILENT).statuses == {cell.name: DONE}
    assert "written on cuda" in caplog.text and "restarts from step 0" in caplog.text


@pytest.mark.slow
def test_jobs_run_cells_in_worker_processes(tmp_path):
    plan = make_plan("quick", tmp_path / "bench", Overrides(size=(48, 36), steps=2))
    outcome = run_plan(plan, jobs=2, control=SILENT)
    assert outcome.count(DONE) == 4 and not outcome.failures
    assert all((plan.cell_dir(c) / "spectrum.json").is_file() for c in plan.cells)


@pytest.mark.slow
def test_threads_set_each_fit_s_thread_count_whatever_the_jobs(tmp_path):
    """As many threads each as the machine has cores, two fits at once: not the cores/jobs share."""
    plan = make_plan("quick", tmp_path / "bench", Overrides(size=(48, 36), steps=2, methods=["cvqpg"]))
    cores = os.cpu_count()
    assert run_plan(plan, jobs=2, control=SILENT, threads=cores).count(DONE) == 2
    runs = [json.loads((plan.cell_dir(c) / "metrics.json").read_text())["run"] for c in plan.cells]
    assert [run["torch_threads"] for run in runs] == [cores, cores]


def test_one_job_fits_with_its_threads_and_gives_the_caller_its_own_back(tmp_path, monkeypatch):
    plan = make_plan("quick", tmp_path / "bench", Overrides(size=(48, 36), steps=2, methods=["cvqpg"]))
    seen = []

    def attempt(*_args: object) -> tuple[str, None]:
        seen.append((torch.get_num_threads(), numba.get_num_threads()))
        return DONE, None

    monkeypatch.setattr(bench, "_attempt", attempt)
    before = torch.get_num_threads(), numba.get_num_threads()
    threads = 2 if before[0] == 1 else 1  # not the caller's count, so that giving it back shows
    assert run_plan(plan, control=SILENT, threads=threads).count(DONE) == 2
    assert seen == [(threads, min(threads, numba.config.NUMBA_NUM_THREADS))] * 2
    assert (torch.get_num_threads(), numba.get_num_threads()) == before


def test_a_run_on_some_scenes_or_one_colour_summarises_every_cell_the_folder_records(scenes_dir, tmp_path):
    axes = {"ratios": [0.1], "methods": ["cvqpg"]}
    earlier = make_plan("paper", tmp_path / "bench", Overrides(scenes_dir=scenes_dir, scene_names=["sushi", "zebra"],
                                                               colors=["gray"], **axes))
    for cell in earlier.cells:
        start_run(earlier.cell_dir(cell), cell.config, cell.scene.source)
    (scenes_dir / "zebra" / "image.png").unlink()  # a recorded scene whose files are gone still summarises
    now = Overrides(scenes_dir=scenes_dir, scene_names=["tiger"], colors=["rgb"], **axes)
    assert [c.name for c in make_plan("paper", tmp_path / "bench", now).cells] == ["tiger_rgb-10_cvqpg_s100"]
    summarised = folder_plan("paper", tmp_path / "bench", now)
    assert sorted(c.name for c in summarised.cells) == sorted(
        f"{scene}_{color}-10_cvqpg_s100" for scene in ("sushi", "tiger", "zebra") for color in ("gray", "rgb"))
    assert folder_plan("paper", tmp_path / "other", now).cells == make_plan("paper", tmp_path / "other", now).cells
    assert [s.name for s in make_plan("paper", tmp_path / "bench", Overrides(scenes_dir=scenes_dir)).scenes] == [
        "sushi", "tiger"]  # the default scenes are still the --scenes folder's


def test_table_puts_the_papers_same_scene_means_beside_ours_and_na_for_unavailable(scenes_dir, tmp_path):
    plan = make_plan("paper", tmp_path / "bench", Overrides(scenes_dir=scenes_dir, scene_names=["sushi", "tiger"],
                                                            colors=["gray"], ratios=[0.1],
                                                            methods=["baseline", "cvqpg"]))
    results = [CellResult(c, DONE, {"mean": {"psnr": 28.0 + 0.5 * (c.method == "cvqpg"), "ssim": 0.8,
                                             "lpips": None, "flip": 0.08, "cvvdp": None}}, None) for c in plan.cells]
    table, rows = main_table(plan, results)
    baseline, _, delta = table.rows
    paper = paper_numbers()["per_scene"]
    means = {m: np.mean([paper[s]["gray-10"][m]["psnr"] for s in ("sushi", "tiger")]) for m in ("baseline", "cvqpg")}
    assert baseline[4] == f"28.000 ({means['baseline']:.3f})" and baseline[3] == "2/2"
    assert delta[4] == f"+0.500 ({means['cvqpg'] - means['baseline']:+.3f})"
    assert baseline[6].startswith("n/a") and baseline[8].startswith("n/a")
    assert rows[0]["lpips"] == "n/a" and rows[0]["psnr"] == 28.0
    assert (1, 4) in table.bold and (0, 4) not in table.bold and (0, 5) in table.bold and (1, 5) in table.bold
    missing, _ = main_table(plan, [])
    assert missing.rows[0][4:] == ["–"] * 5


def test_table_rows_are_means_over_the_scenes_every_method_has_finished(scenes_dir, tmp_path):
    plan = make_plan("paper", tmp_path / "bench", Overrides(scenes_dir=scenes_dir, scene_names=["sushi", "tiger"],
                                                            colors=["gray"], ratios=[0.1],
                                                            methods=["baseline", "cvqpg"]))
    psnr = {("sushi", "baseline"): 28.0, ("tiger", "baseline"): 30.0, ("sushi", "cvqpg"): 28.5}
    results = [CellResult(c, DONE, {"mean": {"psnr": psnr[(c.scene.name, c.method)], "ssim": 0.8, "lpips": None,
                                             "flip": 0.08, "cvvdp": None}}, None)
               for c in plan.cells if (c.scene.name, c.method) in psnr]
    table, rows = main_table(plan, results)
    baseline, cvqpg, delta = table.rows
    sushi = paper_numbers()["per_scene"]["sushi"]["gray-10"]
    assert baseline[3:5] == ["1/2", f"28.000 ({sushi['baseline']['psnr']:.3f})"]  # tiger waits for its CVQPG cell
    assert delta[3:5] == ["1/2", f"+0.500 ({sushi['cvqpg']['psnr'] - sushi['baseline']['psnr']:+.3f})"]
    assert (1, 4) in table.bold and (0, 4) not in table.bold
    assert "(sushi); 1 more finished cell joins them" in table.note and rows[0]["scenes"] == 1


def test_seed_spread_table_pairs_methods_within_each_seed(tmp_path):
    plan = make_plan("quick", tmp_path / "bench", Overrides(seeds=[1, 2]))
    psnr = {("baseline", 1): 20.0, ("cvqpg", 1): 20.5, ("baseline", 2): 21.0, ("cvqpg", 2): 21.1}
    results = [CellResult(c, DONE, {"mean": {"psnr": psnr[(c.method, c.config.optimisation.seed)], "ssim": 0.5,
                                             "lpips": None, "flip": 0.2, "cvvdp": None}}, None) for c in plan.cells]
    (table,) = seed_tables(plan, results)
    assert table.rows[0][2:] == ["20.000", "21.000", f"{math.sqrt(0.5):.3f}"]
    assert table.rows[2][1:] == ["Δ (CVQPG − Baseline)", "+0.500", "+0.100", f"{math.sqrt(0.08):.3f}"]
    assert seed_tables(make_plan("quick", tmp_path / "one"), results) == []


def test_summary_says_which_device_each_cell_ran_on(tmp_path):
    plan = make_plan("quick", tmp_path / "bench")
    devices = ["cpu: AMD EPYC", "cuda: NVIDIA H100", "cuda: NVIDIA H100", None]
    results = [CellResult(c, DONE if device else INTERRUPTED,
                          {"mean": {"psnr": 20.0, "ssim": 0.5, "lpips": None, "flip": 0.2, "cvvdp": None},
                           "steps": 60, "updates": 61, "seconds": 3.0, "run": {"device": device}} if device else None,
                          None) for c, device in zip(plan.cells, devices)]
    table, rows = cells_table(plan, results)
    assert [row["device"] for row in rows] == ["cpu: AMD EPYC", "cuda: NVIDIA H100", "cuda: NVIDIA H100", ""]
    assert [r[table.header.index("Device")] for r in table.rows] == [row["device"] for row in rows]
    line = devices_line(results)
    assert "several devices" in line and "cpu: AMD EPYC (1)" in line and "cuda: NVIDIA H100 (2)" in line
    assert devices_line(results[1:]) == "finished cells ran on cuda: NVIDIA H100 (2)"


def test_paper_numbers_per_scene_means_reproduce_table_1():
    paper = paper_numbers()
    assert {"sushi", "flower", "dragon", "tiger", "windmill", "bento"} <= set(paper["per_scene"])
    assert len(paper["per_scene"]) == 10
    for setting, methods in paper["table1"].items():
        for method, values in methods.items():
            for metric in ("psnr", "ssim", "lpips", "flip", "cvvdp"):
                mean = np.mean([scene[setting][method][metric] for scene in paper["per_scene"].values()])
                assert mean == pytest.approx(values[metric], abs=5e-4), (setting, method, metric)


def test_radial_spectrum_sums_to_the_pixel_mse():
    generator = torch.Generator().manual_seed(0)
    recon, target = (torch.rand(2, 3, 36, 50, generator=generator) for _ in range(2))
    edges, power, counts = radial_error_spectrum(recon, target, bins=16)
    assert len(edges) == 18 and edges[16] == 1.0 and edges[17] == pytest.approx(math.sqrt(2))
    assert counts.sum() == 36 * 50 and counts[-1] > 0
    mse = ((recon.double() - target.double()) ** 2).mean().item()
    assert np.nansum(power * counts) / counts.sum() == pytest.approx(mse, rel=1e-12)


@pytest.mark.parametrize("cycles, expected_bin", [(29, 9), (48, 15), (0, 0)])
def test_sinusoidal_error_lands_in_its_frequency_bin(cycles, expected_bin):
    height, width, bins = 64, 96, 16
    x = torch.arange(width, dtype=torch.float64)
    error = (0.1 * torch.cos(2 * math.pi * cycles * x / width)).expand(1, height, width)
    edges, power, counts = radial_error_spectrum(error, torch.zeros_like(error), bins)
    energy = np.nan_to_num(power * counts)
    assert int(np.argmax(energy)) == expected_bin and energy[expected_bin] / energy.sum() > 0.999
    assert edges[expected_bin] <= 2 * cycles / width <= edges[expected_bin + 1]


@pytest.mark.parametrize("arguments, message", [
    (["--preset", "paper"], "needs --scenes DIR"),
    (["--shard", "3/2"], "--shard 3/2"),
    (["--preset", "nonsense"], "unknown preset"),
    (["--methods", "magic"], "--methods magic"),
    (["--scenes", "no-such-folder"], "no such folder"),
    (["--jobs", "0"], "--jobs 0"),
    (["--threads", "0"], "--threads 0"),
])
def test_bad_bench_input_is_one_line_and_exit_code_2(arguments, message, capsys, tmp_path):
    assert main(["bench", *arguments, "--out", str(tmp_path / "bench"), "--quiet"]) == 2
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error and error.count("\n") == 1
    assert not (tmp_path / "bench").exists()


def test_scene_folder_without_depth_is_refused(scenes_dir, capsys, tmp_path):
    (scenes_dir / "tiger" / "depth.png").unlink()
    assert main(["bench", "--preset", "paper", "--scenes", str(scenes_dir), "--dry-run"]) == 2
    error = capsys.readouterr().err
    assert "scene tiger" in error and "depth.png is missing" in error and error.count("\n") == 1


TINY_PAPER = {"size": (48, 36), "steps": 2, "curvature_warmup": 1, "colors": ["gray"], "ratios": [0.1],
              "scene_names": ["sushi", "tiger"]}


@pytest.mark.slow
def test_every_cell_records_commit_machine_threads_time_and_peak_memory(tmp_path):
    plan = make_plan("star", tmp_path / "bench", Overrides(**TINY_STAR))
    run_plan(plan, control=SILENT)
    metrics = json.loads((plan.cell_dir(plan.cells[0]) / "metrics.json").read_text())
    run = metrics["run"]
    assert run["commit"] == provenance.code_commit() and run["cvqpg_version"]  # tests/test_app_provenance.py
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", run["date"])
    assert run["device"].startswith("cpu: ") and len(run["device"]) > 5
    assert run["torch_threads"] >= 1 and run["numba_threads"] >= 1 and run["torch"] == torch.__version__
    assert run["loop_seconds"] == metrics["seconds"] > 0
    # a process that imported torch and ran a fit holds well over 50 MB resident
    assert run["peak_memory_bytes"] > 50 * 2**20 and run["peak_memory_kind"] in ("rss", "rss-process")


FREED_BEFORE_THE_FIT = """
import torch
from cvqpg.app.allocator import keep_freed_memory
from cvqpg.app.provenance import peak_memory, reset_peak_memory
cpu = torch.device("cpu")
assert keep_freed_memory()
reset_peak_memory(cpu)
before = peak_memory(cpu)["peak_memory_bytes"]
earlier_work = torch.ones(64 * 2**20)  # 256 MiB, freed but kept by the process
del earlier_work
reset_peak_memory(cpu)
print((peak_memory(cpu)["peak_memory_bytes"] - before) / 2**20)
"""


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="the peak RSS resets on Linux only")
def test_memory_freed_before_a_fit_is_not_counted_in_its_peak():
    # a bench process fits its cells one after another, and glibc keeps what each frees
    done = subprocess.run([sys.executable, "-c", FREED_BEFORE_THE_FIT], capture_output=True, text=True, check=True)
    assert float(done.stdout) < 64, done.stdout


@pytest.mark.slow
def test_a_recorded_folder_rebuilds_its_tables_without_run_folders_or_scene_files(scenes_dir, tmp_path, capsys):
    fitted = tmp_path / "fitted"
    arguments = ["--preset", "paper", "--methods", "baseline", "cvqpg", "--size", "48", "36", "--steps", "2",
                 "--curvature-warmup", "1", "--colors", "gray", "--ratios", "0.1", "--scene-names", "sushi", "tiger", "--quiet"]
    assert main(["bench", "--scenes", str(scenes_dir), "--out", str(fitted), *arguments]) == 0
    recorded = tmp_path / "results" / "paper"
    for metrics in fitted.glob("cells/*/metrics.json"):
        cell = recorded / "cells" / metrics.parent.name
        cell.mkdir(parents=True)
        for name in ("config.json", "spectrum.json", "metrics.json"):
            (cell / name).write_bytes((metrics.parent / name).read_bytes())
    for scene in scenes_dir.iterdir():
        for file in scene.iterdir():
            file.unlink()
    capsys.readouterr()
    assert main(["bench", "--out", str(recorded), *arguments]) == 0
    assert "0 done, 4 skipped" in capsys.readouterr().out
    # the settings left out are the recorded cells', not the preset's (2000 steps, 640×480, six scenes, ...)
    for given in (arguments, ["--preset", "paper", "--methods", "baseline", "cvqpg", "--quiet"]):
        assert main(["bench", "--out", str(recorded), "--summary-only", *given]) == 0
        for table in ("summary.csv", "cells.csv", "frequency.csv"):
            assert (recorded / table).read_text() == (fitted / table).read_text(), table
        # the same summary, less the comparison figures that need the run folders' images
        without_images = [line for line in (fitted / "summary.md").read_text().splitlines() if "compare_" not in line]
        assert (recorded / "summary.md").read_text().splitlines() == without_images
        assert "compare_" not in (recorded / "report.html").read_text()


@pytest.mark.slow
def test_cells_finished_in_another_grid_are_reused_not_refitted(scenes_dir, tmp_path, capsys):
    table1, ablation = tmp_path / "paper", tmp_path / "ablation"
    common = ["--scenes", str(scenes_dir), "--size", "48", "36", "--steps", "2", "--curvature-warmup", "1", "--ratios", "0.1",
              "--colors", "rgb", "--scene-names", "tiger", "--quiet"]
    assert main(["bench", "--preset", "paper", "--out", str(table1), "--methods", "baseline", "cvqpg", *common]) == 0
    capsys.readouterr()
    ablation_cells = ["bench", "--preset", "ablation", "--out", str(ablation), "--methods", "baseline", "cvqpg",
                      "vanilla", "--reuse", str(table1), *common]
    assert main([*ablation_cells, "--dry-run"]) == 0
    listed = capsys.readouterr().out
    assert "reusable  tiger_rgb-10_baseline_s100" in listed and "reusable  tiger_rgb-10_cvqpg_s100" in listed
    assert "missing  tiger_rgb-10_vanilla_s100" in listed
    assert main(ablation_cells) == 0
    assert "1 done, 0 skipped, 2 reused" in capsys.readouterr().out
    for method in ("baseline", "cvqpg"):
        name = f"tiger_rgb-10_{method}_s100"
        assert (ablation / "cells" / name / "metrics.json").read_bytes() == \
            (table1 / "cells" / name / "metrics.json").read_bytes()
        assert not (ablation / "cells" / name / "model.safetensors").exists()
    other_steps = [a if a != "2" else "3" for a in common]
    assert main(["bench", "--preset", "ablation", "--out", str(tmp_path / "longer"), "--methods", "baseline",
                 "--reuse", str(table1), *other_steps]) == 0
    assert "1 done, 0 skipped, 0 reused" in capsys.readouterr().out


@pytest.mark.parametrize("name, content, message", [
    ("metrics.json", '{"mean": ', "metrics.json is not a readable JSON file"),
    ("metrics.json", '{"steps": 3}', "metrics.json lacks mean; restore it, or delete the cell folder"),
])
def test_summary_only_names_a_damaged_cell_record_in_one_line(tmp_path, name, content, message, capsys):
    plan = make_plan("quick", tmp_path / "bench")
    cell = plan.cells[0]
    folder = start_run(plan.cell_dir(cell), cell.config, cell.scene.source)
    (folder / "metrics.json").write_text(json.dumps({"mean": {m: 20.0 for m in ("psnr", "ssim", "lpips", "flip",
                                                                                "cvvdp")}}))
    (folder / name).write_text(content)
    assert main(["bench", "--preset", "quick", "--out", str(plan.folder), "--summary-only", "--quiet"]) == 2
    error = capsys.readouterr().err
    assert f"{folder / name}" in error and message in error and error.count("\n") == 1 and "Traceback" not in error


def test_a_damaged_config_json_of_a_recorded_scene_is_one_line(tmp_path, capsys):
    config_file = tmp_path / "bench" / "cells" / "sushi_rgb-10_baseline_s100" / "config.json"
    config_file.parent.mkdir(parents=True)
    config_file.write_text("[]")
    assert main(["bench", "--preset", "paper", "--out", str(tmp_path / "bench"), "--summary-only", "--quiet"]) == 2
    error = capsys.readouterr().err
    assert f"{config_file} holds a JSON list, not an object; restore the file" in error and error.count("\n") == 1


def test_threads_beyond_the_machine_s_cores_are_capped_with_a_note(tmp_path, caplog):
    plan = make_plan("star", tmp_path / "bench", Overrides(**TINY_STAR))
    with caplog.at_level("WARNING", logger="cvqpg"):
        run_plan(plan, plan.cells[:0], control=SILENT, threads=100_000)
    assert f"--threads 100000: this machine offers {os.cpu_count()} cores" in caplog.text
