"""The rate–distortion benchmark (`cvqpg bench --preset compression`): cells that take their fit from
another grid or fit it, their `rd.json`, the tables rebuilt from the records alone, and BD-rate."""

import csv
import json
import shutil

import pytest

from cvqpg.cli import main
from cvqpg.campaign.presets import ENCODE_FRACTIONS
from cvqpg.campaign.ratedistortion import (bd_rate, budget_fill, budgets_for, cell_summary, equal_rate_gain, pareto,
                                           rate_base, wide_summary)

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
    # the encode grid runs into a copy of the rate grid's folder
    shutil.copytree(root / "rate", root / "encode")
    assert main(["bench", "--preset", "encode", "--out", str(root / "encode"), *scenes, *TINY,
                 "--size", "128", "96"]) == 0
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
def test_an_encode_cell_fits_afresh_at_the_rate_grids_budgets_and_its_tables_show_both(grids, module_scenes_dir,
                                                                                        capsys, tmp_path):
    rated = json.loads((grids / "rate" / "cells" / CELL / "rd.json").read_text())
    cell = grids / "encode" / "cells" / CELL
    record = json.loads((cell / "encode.json").read_text())
    assert not (cell / "encode.partial.json").exists() and not list(cell.glob("*.partial"))  # nor fit folders
    base = rate_base(rated)
    budgets = sorted(p["budget_bpp"] for p in rated["points"] if p["budget_bpp"] is not None)
    assert base * 0.7 == pytest.approx(budgets[-1])
    assert record["fractions"] == list(ENCODE_FRACTIONS) and record["base_bpp"] == pytest.approx(base)
    assert len(record["points"]) + len(record["skipped_bpp"]) == len(ENCODE_FRACTIONS) and record["points"]
    assert all(p["codec"] == "cvqpg encode" and 0 < budget_fill(p) <= 1 for p in record["points"])
    assert [p["budget_bpp"] for p in record["points"]] == pytest.approx([base * f for f in ENCODE_FRACTIONS
                                                                         ][:len(record["points"])])
    # each point is a fit of its own primitive count, not a pruning of the cell's fit
    fitted = [int(p["setting"].split(": ")[1].split()[0]) for p in record["points"]]
    assert fitted == sorted(fitted, reverse=True) and len(set(fitted)) == len(fitted)
    assert all(p["primitives"] <= n for p, n in zip(record["points"], fitted))
    summary = (grids / "encode" / "summary.md").read_text()
    assert "with cvqpg encode: BD-rate vs the better" in summary
    # one row per file, beside the cell's own front and JPEG XL's at its rate
    rows = summary.split("### cvqpg encode's files against")[1].split("\n### ")[0]
    assert sum(line.startswith("| sushi |") for line in rows.splitlines()) == len(record["points"])
    assert f"| {record['points'][0]['psnr']:.3f} | {record['points'][0]['psnr'] - rated['fit_psnr']:+.2f} |" in rows
    # each point's wall and CPU seconds, the fit's over its segments and the rate control's
    assert all(0 < p["encode_cpu_s"] for p in record["points"])
    assert f"| {record['points'][0]['encode_s']:.0f} | {record['points'][0]['encode_cpu_s']:.0f} |" in rows
    written = (grids / "encode" / "rd.csv").read_text()
    row = next(csv.DictReader(written.splitlines()))
    expected = wide_summary({**rated, "points": rated["points"] + record["points"]})["bd_rate_with_encoder"]
    if expected is None:
        assert row["wide_bd_rate_with_encoder"] == ""
    else:
        assert float(row["wide_bd_rate_with_encoder"]) == pytest.approx(expected.percent)
    # the rate preset's tables of the same folder read the encode points as well
    assert main(["bench", "--preset", "rate", "--out", str(grids / "encode"), "--summary-only", *TINY]) == 0
    assert (grids / "encode" / "rd.csv").read_text() == written
    capsys.readouterr()
    assert main(["bench", "--preset", "encode", "--scenes", str(module_scenes_dir), "--out", str(grids / "encode"),
                 *TINY, "--size", "128", "96"]) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out
    # a cell finished before the grid's lowest budget existed runs again for that budget only
    shorter = tmp_path / "shorter"
    shutil.copytree(grids / "encode", shorter)
    lowest = base * ENCODE_FRACTIONS[-1]
    earlier = {**record, "fractions": list(ENCODE_FRACTIONS[:-1]),
               "points": [p for p in record["points"] if not p["budget_bpp"] == pytest.approx(lowest)],
               "skipped_bpp": [b for b in record["skipped_bpp"] if not b == pytest.approx(lowest)]}
    (shorter / "cells" / CELL / "encode.json").write_text(json.dumps(earlier))
    assert main(["bench", "--preset", "encode", "--scenes", str(module_scenes_dir), "--out", str(shorter),
                 *TINY, "--size", "128", "96"]) == 0
    assert "1 done, 0 skipped" in capsys.readouterr().out
    again = json.loads((shorter / "cells" / CELL / "encode.json").read_text())
    assert again["fractions"] == list(ENCODE_FRACTIONS) and again["points"][:len(earlier["points"])] == earlier["points"]
    assert len(again["points"]) + len(again["skipped_bpp"]) == len(ENCODE_FRACTIONS)


@pytest.mark.slow
def test_the_rate_fit_grid_makes_its_cells_record_then_both_encoders_files_at_each_budget(module_scenes_dir, tmp_path,
                                                                                       capsys):
    """`--preset rate-fit` on a tiny grid: each cell fits and records its anchors first, then encodes each budget
    with today's fit and with the rate in the fit, and its tables set the two side by side."""
    from cvqpg.campaign.presets import RATE_FIT_FRACTIONS

    out = tmp_path / "rate-fit"
    assert main(["bench", "--preset", "rate-fit", "--scenes", str(module_scenes_dir), "--out", str(out), *TINY,
                 "--size", "128", "96"]) == 0
    cell = out / "cells" / CELL
    record = json.loads((cell / "encode.json").read_text())
    assert (cell / "rd.json").is_file() and record["rate_losses"] == [False, True]
    assert record["fractions"] == list(RATE_FIT_FRACTIONS)
    points = {(p["codec"], round(p["budget_bpp"], 6)) for p in record["points"]}
    budgets = {round(p["budget_bpp"], 6) for p in record["points"]}
    assert points == {(codec, b) for codec in ("cvqpg encode", "cvqpg encode --rate-loss") for b in budgets}
    assert all(0 < budget_fill(p) <= 1 for p in record["points"])
    summary = (out / "summary.md").read_text()
    assert "The rate in the fit against today's encode" in summary and "| cvqpg encode --rate-loss |" in summary
    capsys.readouterr()
    assert main(["bench", "--preset", "rate-fit", "--scenes", str(module_scenes_dir), "--out", str(out), *TINY,
                 "--size", "128", "96"]) == 0
    assert "0 done, 1 skipped" in capsys.readouterr().out


def test_an_encode_grid_needs_the_rate_grid_first(module_scenes_dir, tmp_path, capsys):
    assert main(["bench", "--preset", "encode", "--scenes", str(module_scenes_dir), "--out", str(tmp_path / "b"),
                 *TINY]) == 2
    error = capsys.readouterr().err
    assert "run `cvqpg bench --preset rate` into the same --out first" in error and error.count("\n") == 1


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
    (["--preset", "paper", "--fits", "."], "--fits is for the rate–distortion grids of fitted models"),
    (["--preset", "compression", "--fits", "no-such-folder"], "--fits no-such-folder: not a bench folder"),
    (["--preset", "paper", "--finetune", "5"], "--finetune is for the rate–distortion grids of fitted models"),
    (["--preset", "compression", "--finetune", "-1"], "--finetune -1: give a number of steps ≥ 0"),
    (["--preset", "encode", "--finetune", "5"], "--finetune is for the rate–distortion grids of fitted models"),
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
    assert summary["encoded"] == [] and summary["bd_rate_with_encoder"] is None


def test_the_wide_summary_sets_the_encoders_points_beside_the_codecs():
    psnrs = [30.0, 33.0, 35.0, 36.0, 36.5]
    anchor = curve([1, 2, 3, 4, 5], psnrs)
    # the codec's own points reach only the top of the range; the encoder's take a quarter of the bits below it
    codec = curve([4, 5], [36.0, 36.5])
    encoded = [{"codec": "cvqpg encode", "bpp": bpp, "bytes": 1250 * bpp, "psnr": psnr, "budget_bpp": bpp / 0.98}
               for bpp, psnr in zip([0.25, 0.5, 0.75, 1.0], psnrs[:4])]  # files of 10,000 px
    record = {"fit_psnr": 36.6, "points": [*({**p, "codec": "JPEG XL"} for p in anchor),
                                           *({**p, "codec": "JPEG 2000"} for p in anchor),
                                           *({**p, "codec": "cvqpg"} for p in codec), *encoded]}
    summary = wide_summary(record)
    assert summary["bd_rate"][summary["better_anchor"]].percent == pytest.approx(0, abs=1)  # 36 … 36.5 dB only
    both = summary["bd_rate_with_encoder"]
    assert (both.low, both.high) == pytest.approx((33.6, 36.5)) and -75 < both.percent < 0
    assert summary["fills"] == pytest.approx([0.98] * 4, abs=0.01)
    assert summary["equal_rate_with_encoder"].gain_db > 0 and summary["equal_rate"] is None


def test_rate_base_reads_the_budgets_fractions_back():
    record = {"budget_fractions": [0.7, 0.5], "points": [{"codec": "JPEG XL", "budget_bpp": None},
                                                         {"codec": "cvqpg", "budget_bpp": 1.4},
                                                         {"codec": "cvqpg", "budget_bpp": 1.0}]}
    assert rate_base(record) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="no `--bpp` budget points"):
        rate_base({"budget_fractions": [], "points": []})


def test_an_encode_cell_resumes_at_the_first_budget_it_has_no_point_for(tmp_path, monkeypatch):
    from cvqpg import FitConfig
    from cvqpg.campaign import bench, ratedistortion

    folder = tmp_path / CELL
    folder.mkdir()
    (folder / "rd.json").write_text(json.dumps({"budget_fractions": [0.7, 0.5],
                                                "points": [{"codec": "cvqpg", "budget_bpp": 1.4}]}))
    done = {"codec": "cvqpg encode", "budget_bpp": 1.4, "bpp": 1.39}
    (folder / "encode.partial.json").write_text(json.dumps({"fractions": [0.7, 0.5, 0.36], "base_bpp": 2.0,
                                                            "points": [done], "skipped_bpp": [1.0]}))
    encoded = []
    monkeypatch.setattr(ratedistortion, "encode_point",
                        lambda scene, config, source, bpp, work, finetune_steps, run, control, rate_loss=False:
                        encoded.append((bpp, work, config.optimisation.steps, config.optimisation.curvature_warmup,
                                        finetune_steps)))
    monkeypatch.setattr(bench, "scene_from_source", lambda source, config: None)
    cell = bench.Cell(bench.BenchScene("sushi", {}, 2), "cvqpg", FitConfig.create(color="gray", ratio=0.1))
    assert bench.run_encode_cell(cell, folder, (0.7, 0.5, 0.36)) == bench.DONE
    # 1.4 bpp has its point and 1.0 was below the smallest file; the fit works in a folder of the cell's
    # (`cvqpg encode`'s 1500 float and 600 quantisation-aware steps in the place of the cell's 2000)
    assert encoded == [(pytest.approx(0.72), folder / "encode-0.7200bpp.partial", 1500, 300, 600)]
    record = json.loads((folder / "encode.json").read_text())
    assert record["points"] == [done] and record["skipped_bpp"] == pytest.approx([1.0, 0.72])
    assert "load_average" in record["run"] and not (folder / "encode.partial.json").exists()
    assert bench.run_encode_cell(cell, folder, (0.7, 0.5, 0.36)) == bench.SKIPPED
    # a budget the grid gained is fitted into the finished cell, which keeps its points and skips
    assert bench.run_encode_cell(cell, folder, (0.7, 0.5, 0.36, 0.26)) == bench.DONE
    assert encoded[1:] == [(pytest.approx(0.52), folder / "encode-0.5200bpp.partial", 1500, 300, 600)]
    record = json.loads((folder / "encode.json").read_text())
    assert record["points"] == [done] and record["skipped_bpp"] == pytest.approx([1.0, 0.72, 0.52])
    assert record["fractions"] == [0.7, 0.5, 0.36, 0.26] and not (folder / "encode.partial.json").exists()
    assert bench.run_encode_cell(cell, folder, (0.7, 0.26)) == bench.SKIPPED and len(encoded) == 2


def test_a_stopped_encode_cell_keeps_its_finished_points_and_is_interrupted(tmp_path, monkeypatch):
    from cvqpg import FitConfig
    from cvqpg.campaign import bench, ratedistortion
    from cvqpg.control import RunControl
    from cvqpg.fitting import FitInterrupted

    folder = tmp_path / CELL
    folder.mkdir()
    (folder / "rd.json").write_text(json.dumps({"budget_fractions": [0.7], "points": [{"budget_bpp": 1.4}]}))

    def encode_point(scene, config, source, bpp, work, finetune_steps, run, control, rate_loss=False):
        if control.should_stop():
            raise FitInterrupted(3)
        return ratedistortion.Point("cvqpg encode", "--bpp", 10, bpp, 30.0, 0.9, 1.0, 0.1, 5, bpp)

    monkeypatch.setattr(ratedistortion, "encode_point", encode_point)
    monkeypatch.setattr(bench, "scene_from_source", lambda source, config: None)
    cell = bench.Cell(bench.BenchScene("sushi", {}, 2), "cvqpg", FitConfig.create(color="gray", ratio=0.1))
    calls = iter([False, False, False, True])  # the second budget's fit is stopped
    control = RunControl(progress=False, stop_requested=lambda: next(calls))
    assert bench.run_encode_cell(cell, folder, (0.7, 0.5), control) == bench.INTERRUPTED
    record = json.loads((folder / "encode.partial.json").read_text())
    assert [p["budget_bpp"] for p in record["points"]] == [pytest.approx(1.4)] and not (folder / "encode.json").exists()
