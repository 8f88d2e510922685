"""The rate–distortion benchmark (`cvqpg bench --preset compression`): cells that take their fit from
another grid or fit it, their `rd.json`, the tables rebuilt from the records alone, and BD-rate."""

import csv
import json
import shutil

import pytest

from cvqpg.cli import main
from cvqpg.campaign.ratedistortion import (bd_rate, budget_fill, budgets_for, cell_summary, equal_rate_gain, pareto,
                                           wide_summary)

pytest.importorskip("imagecodecs", reason="the JPEG 2000 / JPEG XL anchors need the `compression` extra")

TINY = ["--size", "48", "36", "--steps", "2", "--curvature-warmup", "1", "--colors", "gray", "--scene-names", "sushi",
        "--quiet"]
CELL = "sushi_gray-10_cvqpg_s100"
RECORDS = ("config.json", "spectrum.json", "metrics.json", "rd.json")


@pytest.fixture(scope="module")
def grids(module_scenes_dir, tmp_path_factory):
    """A Table 1 grid that fitted the cell, a compression grid that took its model from there, and a rate grid."""
    root = tmp_path_factory.mktemp("rd")
    scenes = ["--scenes", str(module_scenes_dir)]
    assert main(["bench", "--preset", "paper", "--methods", "cvqpg", "--ratios", "0.1", "--out", str(root / "paper"),
                 *scenes, *TINY]) == 0
    assert main(["bench", "--preset", "compression", "--out", str(root / "rd"), "--fits", str(root / "paper"),
                 "--finetune", "2", *scenes, *TINY]) == 0
    # the rate grid fits its own cell, large enough for a file of a few primitives within each budget
    assert main(["bench", "--preset", "rate", "--out", str(root / "rate"), *scenes, *TINY, "--size", "128", "96"]) == 0
    return root


@pytest.mark.slow
def test_a_compression_cell_takes_the_fit_from_another_grid_and_records_its_points(grids):
    fitted, cell = grids / "paper" / "cells" / CELL, grids / "rd" / "cells" / CELL
    assert not (cell / "model.safetensors").exists()  # not refitted
    assert (cell / "metrics.json").read_bytes() == (fitted / "metrics.json").read_bytes()
    record = json.loads((cell / "rd.json").read_text())
    codecs = {p["codec"] for p in record["points"]}
    assert codecs == {"cvqpg", "JPEG 2000", "JPEG XL", "model float32", "model float16"}
    assert record["model_bytes"] == (fitted / "model.safetensors").stat().st_size and record["finetune_steps"] == 2
    tuned = [p for p in record["points"] if p["setting"].startswith("--finetune 2: ")]
    drops = {p["setting"]: record["fit_psnr"] - p["psnr"] for p in record["points"] if p["setting"].startswith("pos")}
    rungs = sum(0.1 < drop <= 4.0 for drop in drops.values())
    assert len(tuned) == rungs and record["prune_fractions"] == [0.05, 0.1, 0.2]
    pruned = [p for p in record["points"] if p["setting"].startswith("--prune ")]
    assert len(pruned) == (3 if rungs else 0)
    float32 = next(p for p in record["points"] if p["codec"] == "model float32")
    assert float32["psnr"] == pytest.approx(record["fit_psnr"], abs=1e-6)
    assert all(p["bpp"] == pytest.approx(8 * p["bytes"] / (48 * 36)) and p["decode_s"] > 0 for p in record["points"])
    assert record["run"]["load_average"] is not None and record["cpu_seconds"] > 0
    summary = (grids / "rd" / "summary.md").read_text()
    assert "Rate–distortion" in summary and "rd_gray-10.png" in summary and "| 2 steps |" in summary
    assert (grids / "rd" / "rd_gray-10.png").is_file()
    row = next(csv.DictReader((grids / "rd" / "rd.csv").open()))
    assert row["cell"] == CELL and row["finetune_steps"] == "2" and float(row["fraction_of_model"]) == pytest.approx(
        cell_summary(record)["fraction"])


@pytest.mark.slow
def test_a_rate_cell_records_the_codec_at_bpp_budgets_that_it_never_exceeds(grids):
    record = json.loads((grids / "rate" / "cells" / CELL / "rd.json").read_text())
    budgeted = [p for p in record["points"] if p["budget_bpp"] is not None]
    assert record["budget_fractions"] == [0.7, 0.5, 0.36, 0.26, 0.19, 0.14] and record["budget_finetune_steps"] == 100
    assert budgeted and all(p["codec"] == "cvqpg" and p["setting"].startswith("--bpp ") for p in budgeted)
    assert all(0 < budget_fill(p) <= 1 and p["bytes"] <= p["budget_bpp"] * 128 * 96 / 8 for p in budgeted)
    assert all(p["primitives"] >= 1 for p in record["points"] if p["codec"] == "cvqpg")
    summary = (grids / "rate" / "summary.md").read_text()
    assert "BD-rate over [fit − 3, fit − 0.1] dB" in summary and "rd_gray-10.png" in summary
    row = next(csv.DictReader((grids / "rate" / "rd.csv").open()))
    assert float(row["budget_fill_max"]) <= 1 and int(row["primitive_counts"]) == len(wide_summary(record)["counts"])


@pytest.mark.slow
def test_summary_only_rebuilds_the_tables_from_the_records_alone(grids, tmp_path, capsys):
    recorded = tmp_path / "results" / "compression"
    (recorded / "cells" / CELL).mkdir(parents=True)
    for name in RECORDS:
        shutil.copy(grids / "rd" / "cells" / CELL / name, recorded / "cells" / CELL / name)
    assert main(["bench", "--preset", "compression", "--out", str(recorded), "--summary-only", *TINY]) == 0
    assert (recorded / "rd.csv").read_text() == (grids / "rd" / "rd.csv").read_text()
    assert (recorded / "summary.md").read_text() == (grids / "rd" / "summary.md").read_text()
    capsys.readouterr()
    assert main(["bench", "--preset", "compression", "--out", str(recorded), *TINY]) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out


@pytest.mark.slow
def test_a_compression_cell_without_a_kept_fit_fits_it_first(module_scenes_dir, tmp_path):
    out = tmp_path / "rd"
    assert main(["bench", "--preset", "compression", "--scenes", str(module_scenes_dir), "--out", str(out),
                 *TINY]) == 0
    cell = out / "cells" / CELL
    assert (cell / "model.safetensors").is_file() and (cell / "rd.json").is_file()
    assert json.loads((cell / "rd.json").read_text())["model_file"] == str(cell / "model.safetensors")


@pytest.mark.parametrize("arguments, message", [
    (["--preset", "paper", "--fits", "."], "--fits is for rate–distortion grids"),
    (["--preset", "compression", "--fits", "no-such-folder"], "--fits no-such-folder: not a bench folder"),
    (["--preset", "paper", "--finetune", "5"], "--finetune is for rate–distortion grids"),
    (["--preset", "compression", "--finetune", "-1"], "--finetune -1: give a number of steps ≥ 0"),
])
def test_bad_fits_are_one_line_and_exit_code_2(arguments, message, module_scenes_dir, tmp_path, capsys):
    assert main(["bench", *arguments, "--scenes", str(module_scenes_dir), "--out", str(tmp_path / "b"), "--quiet"]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1 and not (tmp_path / "b").exists()


def curve(rates, psnrs):
    return [{"bpp": b, "bytes": b, "psnr": q} for b, q in zip(rates, psnrs)]


def test_bd_rate_of_a_codec_that_halves_the_bytes_is_minus_50_percent():
    psnrs = [30.0, 33.0, 35.0, 36.0, 36.5]
    anchor = curve([1, 2, 3, 4, 5], psnrs)
    half = curve([0.5, 1, 1.5, 2, 2.5], psnrs)
    rate = bd_rate(anchor, half, top_psnr=36.5)
    assert rate.percent == pytest.approx(-50, abs=1e-9) and (rate.low, rate.high) == (35.5, 36.5)
    assert bd_rate(half, anchor, top_psnr=36.5).percent == pytest.approx(100, abs=1e-9)


def test_bd_rate_range_is_narrowed_to_both_curves_and_dominated_points_are_dropped():
    anchor = curve([1, 2, 3, 4], [30.0, 33.0, 35.0, 36.0])
    test = curve([1, 2, 2.5, 3], [33.5, 35.2, 34.0, 35.6])  # the third point is worse than the second
    assert [p["psnr"] for p in pareto(test)] == [33.5, 35.2, 35.6]
    rate = bd_rate(anchor, test, top_psnr=36.2)
    assert (rate.low, rate.high) == (35.2, 35.6)
    assert bd_rate(anchor, curve([1, 2], [20.0, 21.0]), top_psnr=36.0) is None  # no PSNR in common


def test_budgets_are_fractions_of_the_smallest_ladder_file_within_a_tenth_of_a_decibel():
    from cvqpg.campaign.ratedistortion import Point

    ladder = [Point("cvqpg", str(b), b, b / 10, q, 0.9, 0, 0) for b, q in ((10, 27.0), (20, 29.95), (30, 30.0))]
    assert budgets_for(ladder, 30.0, (1.0, 0.5)) == pytest.approx([2.0, 1.0])
    assert budgets_for(ladder, 35.0, (0.5,)) == pytest.approx([1.5])  # none within: the largest file's


def test_equal_rate_gain_reads_the_codec_at_the_rate_where_the_anchor_is_2_db_down():
    anchor = curve([1, 2, 4], [30.0, 32.0, 34.0])  # 32 dB, 2 dB below 34, at 2 bpp
    codec = curve([1, 4], [31.0, 35.0])  # at 2 bpp, half-way in log rate: 33 dB
    gain = equal_rate_gain(anchor, codec, top_psnr=34.0)
    assert gain.bpp == pytest.approx(2.0) and gain.codec_psnr == pytest.approx(33.0) and gain.gain_db == pytest.approx(1.0)
    assert equal_rate_gain(anchor, curve([3, 4], [33.0, 35.0]), top_psnr=34.0) is None  # the codec starts above 2 bpp


def test_budget_fill_is_bytes_over_the_budget_in_whole_bytes():
    point = {"bytes": 950, "bpp": 8 * 950 / 10_000, "budget_bpp": 0.8}  # 1000 bytes for 10,000 px
    assert budget_fill(point) == pytest.approx(0.95)


def test_the_wide_summary_takes_bd_rate_from_3_db_to_a_tenth_below_the_fit():
    psnrs = [30.0, 33.0, 35.0, 36.0, 36.5]
    anchor = curve([1, 2, 3, 4, 5], psnrs)
    codec = [{**p, "primitives": n} for p, n in zip(curve([0.5, 1, 1.5, 2, 2.5], psnrs), (10, 20, 30, 40, 50))]
    record = {"fit_psnr": 36.6, "points": [*({**p, "codec": "JPEG XL"} for p in anchor),
                                           *({**p, "codec": "JPEG 2000"} for p in anchor),
                                           *({**p, "codec": "cvqpg"} for p in codec)]}
    summary = wide_summary(record)
    better = summary["bd_rate"][summary["better_anchor"]]
    assert better.percent == pytest.approx(-50) and (better.low, better.high) == pytest.approx((33.6, 36.5))
    assert summary["counts"] == [10, 20, 30, 40, 50] and summary["deepest_db"] == pytest.approx(6.6)
    assert summary["fills"] == []
    assert summary["equal_rate"] is None  # JPEG XL is 2 dB down at 2.76 bpp, beyond the codec's largest file
