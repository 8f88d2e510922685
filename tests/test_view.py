"""`cvqpg view` without a browser: the sweep's distances, the page's structure and embedded data, and `fit --view`
(refusals at the command line: test_hostile.py)."""

import json
import re

import pytest

from cvqpg.cli import main
from cvqpg.errors import CvqpgError
from cvqpg.view import DEFAULT_SWEEP, check_sweep, sweep_distances, write_view

SMALL = ["--size", "48", "36", "--steps", "3", "--curvature-warmup", "1", "--quiet"]
SWEEP = ["--distances", "0.0005", "0.006", "6"]  # 0.5, 1.6, 2.7, 3.8, 4.9, 6 mm and the planes at 1 and 5 mm


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A CVQPG run with an export, a flat run of the same scene, and a run of another size."""
    root = tmp_path_factory.mktemp("view")
    for name, options in (("cvqpg", []), ("flat", ["--primitive", "flat"])):
        assert main(["fit", *SMALL, *options, "--out", str(root / name)]) == 0
    assert main(["export", str(root / "cvqpg")]) == 0
    assert main(["fit", *SMALL[3:], "--size", "64", "48", "--out", str(root / "larger")]) == 0
    return root


def page_data(page: str) -> dict:
    return json.loads(re.search(r'<script id="view-data" type="application/json">(.*?)</script>', page, re.S)
                      .group(1))


def test_the_sweep_holds_count_distances_and_the_training_planes_exactly():
    distances = sweep_distances(*DEFAULT_SWEEP, (1e-3, 5e-3))
    assert len(distances) == 43 and distances == sorted(distances)
    assert distances[0] == 0.5e-3 and distances[-1] == 6e-3 and 1e-3 in distances and 5e-3 in distances
    assert sweep_distances(1e-3, 5e-3, 5, (1e-3, 5e-3)) == pytest.approx([1e-3, 2e-3, 3e-3, 4e-3, 5e-3])
    assert sweep_distances(2e-3, 4e-3, 3, (1e-3, 5e-3)) == pytest.approx([2e-3, 3e-3, 4e-3])
    assert sweep_distances(3e-3, 3e-3, 1, (1e-3,)) == [3e-3]


@pytest.mark.parametrize("sweep, message", [
    ((1e-3, 2e-3, 0), r"COUNT must lie in \[1, 4096\]"),
    ((1e-3, 2e-3, 4097), r"COUNT must lie in \[1, 4096\]"),
    ((0.0, 2e-3, 5), "0 < START ≤ STOP"),
    ((3e-3, 2e-3, 5), "0 < START ≤ STOP"),
    ((1e-9, 2e-3, 5), r"START and STOP 1e-09, 0.002 m must lie in \[1e-06, 10\] m"),
    ((1e-3, 1e300, 5), r"must lie in \[1e-06, 10\] m"),
    ((0.5, 6, 41), "distances are in m"),
])
def test_bad_sweeps_are_refused(sweep, message):
    with pytest.raises(CvqpgError, match=message):
        check_sweep(*sweep)


@pytest.mark.slow
def test_one_run_page_is_self_contained_with_a_frame_per_distance(runs, capsys):
    run = runs / "cvqpg"
    assert main(["view", str(run), *SWEEP, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert re.match(rf"{re.escape(str(run / 'view.html'))}: 8 distances, \d+\.\d MiB, \d+ s", out)
    page = (run / "view.html").read_text()
    # Nothing is fetched: every image is a data URI, and no address points outside the file.
    assert not re.search(r"(src|href)=['\"](?!data:)", page) and "://" not in page
    data = page_data(page)
    assert data["distances_mm"] == pytest.approx([0.5, 1.0, 1.6, 2.7, 3.8, 4.9, 5.0, 6.0])
    assert data["marks"] == [{"index": 1, "label": "1 mm"}, {"index": 6, "label": "5 mm"}]
    assert (data["width"], data["height"]) == (48, 36)
    (shown,) = data["runs"]
    assert shown["name"] == "cvqpg" and len(shown["frames"]) == 8
    assert all(uri.startswith("data:image/jpeg;base64,") for uri in shown["frames"])
    assert len(set(shown["frames"])) == 8  # every distance looks different
    fitted = json.loads((run / "metrics.json").read_text())["per_plane"]["psnr"]
    # At the planes, PSNR against the 8-bit target PNGs is the fit's own PSNR up to the targets' rounding.
    assert [shown["psnr"][1], shown["psnr"][6]] == pytest.approx(fitted, abs=0.05)
    assert [i for i, v in enumerate(shown["psnr"]) if v is not None] == [1, 6]
    assert shown["amplitude"].startswith("data:image/jpeg") and shown["phase"].startswith("data:image/jpeg")
    assert [d["label"].split(" PSNR")[0] for d in shown["display"]] == ["plane 0 · 1 mm", "plane 1 · 5 mm"]
    assert "<table id='settings'>" in page and "<th>N primitives</th><td>173</td>" in page


@pytest.mark.slow
def test_two_runs_side_by_side(runs):
    record = write_view([runs / "cvqpg", runs / "flat"], sweep=(1e-3, 5e-3, 2), progress=False)
    assert record.path == runs / "cvqpg" / "view_vs_flat.html" and record.frames == 2
    page = record.path.read_text()
    assert record.bytes == len(page.encode())
    cvqpg, flat = page_data(page)["runs"]
    assert (cvqpg["name"], flat["name"]) == ("cvqpg", "flat")
    assert len(cvqpg["frames"]) == len(flat["frames"]) == 2 and cvqpg["frames"] != flat["frames"]
    assert None not in cvqpg["psnr"] + flat["psnr"]
    assert flat["display"] == []  # only the CVQPG run was exported
    assert "<th></th><th>cvqpg</th><th>flat</th>" in page and "cvqpg view: cvqpg vs flat" in page


@pytest.mark.slow
def test_a_model_file_in_a_run_is_viewed_with_its_own_metrics(runs):
    run = runs / "cvqpg"
    packed = run / "packed.cvq"
    assert main(["compress", str(run), "--bits", "6", "--out", str(packed)]) == 0
    assert main(["eval", str(packed)]) == 0
    record = write_view([packed, run], sweep=(1e-3, 5e-3, 2), progress=False)
    assert record.path == run / "packed.view_vs_cvqpg.html"
    page = record.path.read_text()
    shown, own = page_data(page)["runs"]
    assert (shown["name"], own["name"]) == ("cvqpg/packed.cvq", "cvqpg")
    assert shown["frames"] != own["frames"] and shown["display"] == [] and own["display"] != []
    psnr = json.loads((run / "packed.metrics.json").read_text())["mean"]["psnr"]
    assert f"<th>PSNR</th><td>{psnr:.3f}</td>" in page


@pytest.mark.slow
def test_fit_with_view_writes_the_page_into_the_run(tmp_path):
    out = tmp_path / "run"
    assert main(["fit", *SMALL, "--view", "--out", str(out)]) == 0
    data = page_data((out / "view.html").read_text())
    assert len(data["runs"][0]["frames"]) == 43
