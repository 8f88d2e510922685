"""docs/results.md is generated from results/ and held to it."""

import json
import shutil
from pathlib import Path

import pytest

from cvqpg.campaign.bench import SPECTRUM_BINS
from cvqpg.cli import main
from cvqpg.errors import CvqpgError
from cvqpg.campaign.report import paper_numbers
from cvqpg.campaign.results import ABLATION_METHODS, ABLATION_SCENES, CAMPAIGN, RecordError, campaign_plan, document

REPOSITORY = Path(__file__).resolve().parents[1]


def record_cell(root: Path, preset: str, name: str, psnr: float, device: str = "cpu: test CPU",
                run_changes: dict | None = None, **config_changes) -> Path:
    """Write a campaign cell's record (config, spectrum, metrics) as a finished fit leaves it."""
    grid = next(g for g in CAMPAIGN if g.preset == preset)
    cell = next(c for c in campaign_plan(grid, root).cells if c.name == name)
    folder = root / preset / "cells" / name
    folder.mkdir(parents=True, exist_ok=True)
    config = {"cvqpg_version": "0.1.0", "source": {"scene": cell.scene.name},
              **cell.config.replace(**config_changes).to_dict()}
    (folder / "config.json").write_text(json.dumps(config))
    edges = [i / SPECTRUM_BINS for i in range(SPECTRUM_BINS + 1)] + [2 ** 0.5]
    power = [1.0 / psnr] * (SPECTRUM_BINS + 1)
    (folder / "spectrum.json").write_text(json.dumps({"bins": SPECTRUM_BINS, "edges": edges, "power": power,
                                                      "counts": [1] * (SPECTRUM_BINS + 1), "mse": 1.0 / psnr}))
    mean = {"psnr": psnr, "ssim": 0.8, "lpips": None, "flip": 0.1, "cvvdp": None}
    run = {"commit": "0" * 40, "date": "2026-11-25T09:00:00+00:00", "device": device, "torch": "2.13.0",
           "torch_threads": 2, "numba_threads": 2, "loop_seconds": 480.0, "load_average": 3.0, "machine_cores": 2,
           "peak_memory_bytes": 2**30, "peak_memory_kind": "rss", **(run_changes or {})}
    (folder / "metrics.json").write_text(json.dumps({"mean": mean, "per_plane": {k: [v, v] for k, v in mean.items()},
                                                     "steps": 2000, "seconds": 480.0, "run": run}))
    return folder


def test_the_committed_document_is_the_one_the_recorded_cells_give():
    committed = (REPOSITORY / "docs" / "results.md").read_text()
    assert document(REPOSITORY / "results") == committed, "run `cvqpg results` and commit docs/results.md"


def test_a_changed_record_changes_the_document(tmp_path):
    if (REPOSITORY / "results").is_dir():  # the recorded cells, plus two where none are recorded yet
        shutil.copytree(REPOSITORY / "results", tmp_path, dirs_exist_ok=True)
    for method, psnr in (("baseline", 27.5), ("cvqpg", 27.8)):
        name = f"bento_rgb-10_{method}_s100"
        if not (tmp_path / "paper" / "cells" / name / "metrics.json").exists():
            record_cell(tmp_path, "paper", name, psnr)
    before = document(tmp_path)
    metrics_file = tmp_path / "paper" / "cells" / "bento_rgb-10_cvqpg_s100" / "metrics.json"
    metrics = json.loads(metrics_file.read_text())
    metrics["mean"]["psnr"] += 0.0125
    metrics_file.write_text(json.dumps(metrics))
    after = document(tmp_path)
    assert after != before
    assert f"{metrics['mean']['psnr']:.3f}" in after


def test_the_document_compares_gains_per_scene_and_states_each_claim(tmp_path):
    supplement = paper_numbers()["per_scene"]["tiger"]["rgb-10"]
    values = {"baseline": supplement["baseline"]["psnr"] + 0.02, "baseline+": supplement["baseline+"]["psnr"],
              "cvqpg": supplement["cvqpg"]["psnr"] + 0.25}
    for method, psnr in values.items():
        record_cell(tmp_path, "paper", f"tiger_rgb-10_{method.replace('+', '-plus')}_s100", psnr)
    text = document(tmp_path)
    gain, paper_gain = values["cvqpg"] - values["baseline"], supplement["cvqpg"]["psnr"] - supplement["baseline"]["psnr"]
    assert f"| tiger | RGB 10% | {values['baseline']:.3f} | {supplement['baseline']['psnr']:.3f} | +0.020 |" in text
    assert f"ours {gain:+.3f} dB on 1 scene, paper {paper_gain:+.3f} on the same scenes" in text
    assert f"outside the tolerance so far (Δ {gain - paper_gain:+.3f}" in text  # 0.23 dB apart: outside 0.1 dB
    # load 1.5
    assert "Time of CVQPG against the Baseline, RGB 10%: paper +0.0%; ours not comparable from these cells" in text
    assert "Per-scene PSNR within 0.3 dB of the supplementary table: 3 of 3 recorded values" in text
    assert "| Table 1 | `results/paper` | 3 | 72 | 69 |" in text
    assert "3 cells on cpu: test CPU, 2 torch / 2 Numba threads" in text
    assert ("| RGB 10% | CVQPG | 15,360 | 1 | 1 × test CPU, 2 threads | 8.0 | – | 1.00 | +0.0% (1) | 1.5 | 17.0 | "
            "+0.0% | 10.9 | -0.1% |") in text  # load 1.5 per core: no time to compare


def test_methods_of_one_scene_fitted_on_different_cpus_are_named(tmp_path):
    record_cell(tmp_path, "paper", "tiger_gray-10_baseline_s100", 24.0, device="cpu: CPU A")
    record_cell(tmp_path, "paper", "tiger_gray-10_cvqpg_s100", 24.3, device="cpu: CPU B")
    record_cell(tmp_path, "paper", "bento_gray-10_baseline_s100", 24.0, device="cpu: CPU A")
    record_cell(tmp_path, "paper", "bento_gray-10_cvqpg_s100", 24.3, device="cpu: CPU A")
    lines = [line for line in document(tmp_path).splitlines() if "ran on different devices" in line]
    assert lines == ["- Table 1: the methods of 1 scene–setting group ran on different devices, so their differences "
                     "carry the ±0.05 dB spread between CPUs: tiger Grayscale 10% (Baseline on cpu: CPU A; CVQPG on "
                     "cpu: CPU B)."]


def test_times_are_compared_only_between_cells_of_one_scene_on_the_same_machine(tmp_path):
    quiet = {"load_average": 2.0}  # 1.0 per core: each fit had its core to itself
    record_cell(tmp_path, "paper", "tiger_gray-10_baseline_s100", 24.0, device="cpu: CPU A", run_changes=quiet)
    record_cell(tmp_path, "paper", "tiger_gray-10_cvqpg_s100", 24.3, device="cpu: CPU B",
                run_changes={**quiet, "loop_seconds": 240.0})
    record_cell(tmp_path, "paper", "bento_gray-10_baseline_s100", 24.0, device="cpu: CPU A", run_changes=quiet)
    record_cell(tmp_path, "paper", "bento_gray-10_cvqpg_s100", 24.3, device="cpu: CPU A",
                run_changes={**quiet, "loop_seconds": 600.0})
    text = document(tmp_path)
    assert ("| Grayscale 10% | CVQPG | 7,680 | 2 | 1 × CPU A, 2 threads; 1 × CPU B, 2 threads | 7.0 | +25.0% (1) | "
            "1.00 | +0.0% (1) | 1.0 |") in text  # the mean time is over both cells, Δ over bento's pair only
    assert ("Time of CVQPG against the Baseline, Grayscale 10%: paper +3.4%, ours +25.0% on 1 scene whose two cells "
            "ran the same commit on the same machine, each with its cores to itself.") in text
    record_cell(tmp_path, "paper", "bento_gray-10_cvqpg_s100", 24.3, device="cpu: CPU A",
                run_changes={"load_average": 4.0, "loop_seconds": 600.0})
    assert ("Time of CVQPG against the Baseline, Grayscale 10%: paper +3.4%; ours not comparable from these cells: "
            "no scene has both cells fitted by the same commit on the same machine, each with its cores to itself, "
            "and a recorded cell is not fitted again") in document(tmp_path)
    record_cell(tmp_path, "paper", "bento_gray-10_cvqpg_s100", 24.3, device="cpu: CPU A",
                run_changes={**quiet, "loop_seconds": 600.0, "commit": "1" * 40})
    row = ("| Grayscale 10% | CVQPG | 7,680 | 2 | 1 × CPU A, 2 threads; 1 × CPU B, 2 threads | 7.0 | – | 1.00 | "
           "– |")
    assert row in document(tmp_path)  # other code: neither time nor memory compares


def test_the_chromatic_tables_compare_variants_on_the_same_scenes_with_their_time(tmp_path):
    for scene in ("bento", "dragon"):
        record_cell(tmp_path, "chromatic", f"{scene}_rgb-10_baseline_s100", 27.0, run_changes={"load_average": 2.0})
    record_cell(tmp_path, "chromatic", "bento_rgb-10_per-channel_s100", 27.4,
                run_changes={"loop_seconds": 720.0, "load_average": 2.0})
    text = document(tmp_path)
    chromatic = text[text.index("## Chromatic curvature"):text.index("## Runtime")]
    # no paper values beside the chromatic grid's
    assert "| Baseline | 15,360 | – | 1/6 | 27.000 | **0.8000** | n/a | **0.1000** | n/a |" in chromatic
    assert "| CVQPG, γ per channel | 15,360 | +0.400 | 1/6 | **27.400** |" in chromatic
    assert ("RGB 10%: means over the scenes every method has finished (bento); 1 more finished cell joins them once "
            "the other methods finish their scenes.") in chromatic
    assert "| scene | CVQPG | CVQPG, γ per channel | CVQPG, bound per λ |" in chromatic  # gains per scene
    assert "| bento | – | +0.400 | – |" in chromatic and "| dragon |" not in chromatic
    assert "PSNR gain over the Baseline per scene (dB), RGB 20%" not in chromatic  # nothing to show yet
    assert ("| RGB 10% | CVQPG, γ per channel | 15,360 | 1 | 1 × test CPU, 2 threads | 12.0 | +50.0% (1) | 1.00 | "
            "+0.0% (1) | 1.0 |") in chromatic


def test_the_chromatic_target_needs_the_gain_and_the_lead_at_equal_parameter_count(tmp_path):
    record_cell(tmp_path, "chromatic", "bento_rgb-10_baseline_s100", 27.0)
    record_cell(tmp_path, "chromatic", "bento_rgb-10_per-channel_s100", 27.4)
    record_cell(tmp_path, "chromatic", "bento_rgb-20_baseline_s100", 28.0)
    record_cell(tmp_path, "chromatic", "bento_rgb-20_per-channel_s100", 28.35)

    def verdicts() -> list[str]:
        return [line for line in document(tmp_path).splitlines() if line.startswith("- CVQPG, γ per channel, RGB")]

    assert verdicts() == [
        "- CVQPG, γ per channel, RGB 10%: +0.400 dB over the Baseline at equal N on 1 scene: met so far at equal N "
        "(the Baseline at its parameter count is not fitted yet).",
        "- CVQPG, γ per channel, RGB 20%: +0.350 dB over the Baseline at equal N on 1 scene: met so far at equal N "
        "(the equal-parameter cells are fitted at RGB 10% only)."]
    record_cell(tmp_path, "chromatic", "bento_rgb-10_baseline-pluspc_s100", 27.5)
    assert verdicts()[0].endswith(", -0.100 dB against the Baseline at its parameter count on 1 scene: not met so far.")
    record_cell(tmp_path, "chromatic", "bento_rgb-10_baseline-pluspc_s100", 27.3)
    assert verdicts()[0].endswith(", +0.100 dB against the Baseline at its parameter count on 1 scene: met so far.")
    record_cell(tmp_path, "chromatic", "bento_rgb-10_baseline-pluspc_s100", 27.42)
    assert verdicts()[0].endswith(", -0.020 dB against the Baseline at its parameter count on 1 scene: undecided so "
                                  "far: level with the Baseline at its parameter count (closer than 0.05 dB, one "
                                  "fit's spread between machines).")


def ablation_line(root: Path, shifts: dict[str, float]) -> str:
    """The ablation's claim line once every cell holds the paper's mean PSNR plus the method's shift (dB)."""
    means = paper_numbers()["ablation"]["methods"]
    for scene in ABLATION_SCENES:
        for method in ABLATION_METHODS:
            record_cell(root, "ablation", f"{scene}_rgb-10_{method}_s100", means[method]["psnr"] + shifts.get(method, 0))
    return next(line for line in document(root).splitlines() if line.startswith("- Ablation order"))


def test_the_ablation_order_is_judged_once_every_cell_is_recorded(tmp_path):
    line = ablation_line(tmp_path, {})
    assert line.endswith(": the paper's order.")
    assert "ours CVQPG ≈ w/o Mahalanobis QPF > w/o adaptive bound ≈ vanilla (neither) ≈ Baseline" in line
    assert "w/o Mahalanobis QPF +0.149 (paper +0.149)" in line


def test_the_ablation_names_the_pairs_that_break_the_papers_order(tmp_path):
    # w/o adaptive bound 0.217 dB higher than the paper's: above both CVQPG and w/o Mahalanobis QPF
    assert ablation_line(tmp_path / "reversed", {"no-bound": 0.217}).endswith(
        ": differs from the paper's order (reversed by 0.05 dB or more: CVQPG − w/o adaptive bound -0.080 dB "
        "(paper +0.137); w/o Mahalanobis QPF − w/o adaptive bound -0.116 dB (paper +0.101)).")
    # 0.09 dB higher: level with both, which the paper separates from it by 0.1 dB or more
    assert ablation_line(tmp_path / "level", {"no-bound": 0.09}).endswith(
        ": differs from the paper's order (separated by the paper by 0.05 dB or more, by ours less: CVQPG − "
        "w/o adaptive bound +0.047 dB (paper +0.137); w/o Mahalanobis QPF − w/o adaptive bound +0.011 dB "
        "(paper +0.101)).")


def test_a_cell_recorded_with_other_settings_is_refused(tmp_path, capsys):
    record_cell(tmp_path, "paper", "tiger_rgb-10_cvqpg_s100", 28.0, steps=500)
    with pytest.raises(RecordError, match="steps=500"):
        document(tmp_path)
    assert main(["results", "--root", str(tmp_path), "--out", str(tmp_path / "results.md")]) == 2
    assert "steps=500" in capsys.readouterr().err and not (tmp_path / "results.md").exists()


def test_the_papers_ablation_means_are_those_of_five_of_its_per_scene_rows():
    numbers = paper_numbers()
    scenes = numbers["ablation"]["scenes_matched"]
    for method in ("baseline", "cvqpg"):
        for metric, value in numbers["ablation"]["methods"][method].items():
            mean = sum(numbers["per_scene"][s]["rgb-10"][method][metric] for s in scenes) / len(scenes)
            assert mean == pytest.approx(value, abs=1e-3)  # one unit of the last printed digit


@pytest.mark.parametrize("name, damage, message", [
    ("metrics.json", lambda record: "{cut short", "metrics.json is not a readable JSON file"),
    ("metrics.json", lambda record: {k: v for k, v in record.items() if k != "mean"}, "metrics.json lacks mean;"),
    ("metrics.json", lambda record: {**record, "mean": {"psnr": 28.0}}, "lacks mean.ssim, mean.lpips"),
    ("metrics.json", lambda record: {**record, "run": {"commit": None}}, "lacks run.device"),
    ("spectrum.json", lambda record: [], "spectrum.json holds a JSON list, not an object"),
    ("config.json", lambda record: "", "config.json is not a readable JSON file"),
    ("config.json", lambda record: {k: v for k, v in record.items() if k != "targets"}, "config.json lacks targets"),
])
def test_a_damaged_cell_record_is_one_line_naming_it(tmp_path, name, damage, message, capsys):
    folder = record_cell(tmp_path, "paper", "tiger_rgb-10_cvqpg_s100", 28.0)
    damaged = damage(json.loads((folder / name).read_text()))
    (folder / name).write_text(damaged if isinstance(damaged, str) else json.dumps(damaged))
    assert main(["results", "--root", str(tmp_path), "--out", str(tmp_path / "results.md")]) == 2
    error = capsys.readouterr().err
    assert str(folder / name) in error and message in error and error.count("\n") == 1 and "Traceback" not in error
    assert "restore" in error and not (tmp_path / "results.md").exists()


def test_the_psnr_against_seconds_figure_waits_for_both_histories_then_is_drawn(tmp_path):
    from cvqpg.campaign.results import write_figures

    figure = "beyond_seconds_gray10.png"
    for preset, steps, seconds in (("paper", 2000, 390.0), ("beyond-time", 7745, 1500.0)):
        assert f"]({figure})" not in document(tmp_path) and write_figures(tmp_path, tmp_path / "docs") == []
        folder = record_cell(tmp_path, preset, "sushi_gray-10_cvqpg_s100", 30.0)
        (folder / "history.csv").write_text("step,seconds,loss,psnr\n0,0.2,1.0,9.0\n"
                                            f"{steps},{seconds},0.01,30.0\n")
    assert f"![PSNR against minutes, sushi, Grayscale 10%]({figure})" in document(tmp_path)
    assert ("PSNR against minutes, sushi, RGB 10%: waits for its CVQPG cells in `results/paper` and "
            "`results/beyond-time`, each with a `history.csv`") in document(tmp_path)
    (tmp_path / "docs").mkdir()
    assert write_figures(tmp_path, tmp_path / "docs") == [tmp_path / "docs" / figure]
    assert (tmp_path / "docs" / figure).read_bytes().startswith(b"\x89PNG")
    with pytest.raises(CvqpgError, match="exists"):
        write_figures(tmp_path, tmp_path / "docs")
    assert write_figures(tmp_path, tmp_path / "docs", overwrite=True) == [tmp_path / "docs" / figure]
