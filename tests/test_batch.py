"""`cvqpg batch` (`cvqpg.app.batch`): items of a folder of scenes or a CSV manifest fitted into one batch folder,
a bad item recorded in one line while the others go on, reruns that skip finished items and resume interrupted
ones to the parameters of an uninterrupted fit, and the summaries."""

import csv
import json
import signal

import numpy as np
import pytest
import torch
from PIL import Image

from cvqpg import cli
from cvqpg.app import batch, executors, signals
from cvqpg.app.batch import BatchInput, BatchSettings, plan_item, read_inputs
from cvqpg.app.encoding import start_encode
from cvqpg.cli import main
from cvqpg.errors import InputError
from cvqpg.storage import load_model, read_compressed
from stopping import CountedStop

W, H = 32, 24
TINY = ["--size", str(W), str(H), "--steps", "3", "--quiet"]


def picture(path, shade=0):
    y, x = np.mgrid[0:H, 0:W]
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.stack([x * 5 + shade, y * 7, (x + y) * 3], axis=-1).astype(np.uint8)).save(path)
    return path


def depth_map(path):
    Image.fromarray(np.tile(np.linspace(0, 255, W).astype(np.uint8), (H, 1))).save(path)
    return path


def scene_folders(root, names=("a", "b", "c", "d", "e"), corrupt=(), without_depth=()):
    """Scene folders NAME/image.png with NAME/depth.png, as ../shared/scenes holds them."""
    for shade, name in enumerate(names):
        image = picture(root / name / "image.png", 20 * shade)
        if name in corrupt:
            image.write_bytes(image.read_bytes()[:40])
        if name not in without_depth:
            depth_map(root / name / "depth.png")
    return root


def summary(folder):
    with open(folder / "summary.csv", newline="") as handle:
        return {row["name"]: row for row in csv.DictReader(handle)}


def one_line_error(capsys):
    """The one line of stderr besides the library's notes."""
    lines = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("cvqpg: note:")]
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    return lines[0]


@pytest.fixture
def fits(monkeypatch):
    """The items that fit (`batch.fit_in_folder` calls), by the folder they fit in."""
    called = []
    original = batch.fit_in_folder
    monkeypatch.setattr(batch, "fit_in_folder", lambda folder, *args, **kwargs: called.append(folder.name)
                        or original(folder, *args, **kwargs))
    return called


@pytest.mark.slow
def test_a_batch_records_a_corrupt_image_in_one_line_and_a_rerun_fits_nothing_again(tmp_path, fits, capsys):
    scenes = scene_folders(tmp_path / "scenes", corrupt=("c",), without_depth=("d",))
    out = tmp_path / "out"
    assert main(["batch", str(scenes), "--out", str(out), *TINY]) == cli.EXIT_USAGE
    assert "c: image" in one_line_error(capsys)
    assert sorted(fits) == ["a.partial", "b.partial", "d.partial", "e.partial"]
    rows = summary(out)
    assert list(rows) == ["a", "b", "c", "d", "e"]
    assert {name: row["status"] for name, row in rows.items()} == {**dict.fromkeys("abde", "done"), "c": "failed"}
    assert "not an image file" in rows["c"]["error"] and not rows["a"]["error"]
    for name in "abde":
        metrics = json.loads((out / name / "metrics.json").read_text())
        assert float(rows[name]["psnr_db"]) == pytest.approx(metrics["mean"]["psnr"], abs=1e-4)
        assert int(rows[name]["bytes"]) == (out / name / "model.safetensors").stat().st_size
        assert rows[name]["steps"] == "3" and rows[name]["device"].startswith("cpu")
    assert json.loads((out / "d" / "config.json").read_text())["targets"]["num_planes"] == 1
    assert rows["d"]["note"] == batch.NO_DEPTH_NOTE and not rows["a"]["note"]
    assert "| c | failed |" in (out / "summary.md").read_text()
    assert not any(p.name.endswith(".partial") for p in out.iterdir())
    written = {name: (out / name / "model.safetensors").stat().st_mtime_ns for name in "abde"}

    fits.clear()
    capsys.readouterr()
    assert main(["batch", str(scenes), "--out", str(out), *TINY]) == cli.EXIT_USAGE  # c fails again
    assert fits == [] and "0 done, 4 skipped" in capsys.readouterr().out
    assert {name: (out / name / "model.safetensors").stat().st_mtime_ns for name in "abde"} == written
    assert summary(out) == rows


def test_a_batch_folder_takes_no_other_folder_and_one_writer_at_a_time(tmp_path, capsys):
    scenes = scene_folders(tmp_path / "scenes", names=("a",))
    foreign = tmp_path / "foreign"
    (foreign / "mine").mkdir(parents=True)
    assert main(["batch", str(scenes), "--out", str(foreign), *TINY]) == cli.EXIT_USAGE
    assert "not a batch folder" in one_line_error(capsys) and [p.name for p in foreign.iterdir()] == ["mine"]
    assert main(["batch", str(scenes), "--out", str(foreign), "--overwrite", *TINY]) == cli.EXIT_USAGE
    assert "not a batch folder" in one_line_error(capsys) and [p.name for p in foreign.iterdir()] == ["mine"]
    assert main(["batch", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out"), *TINY]) == cli.EXIT_USAGE
    assert "no such folder of scenes or CSV manifest" in one_line_error(capsys) and not (tmp_path / "out").exists()
    from cvqpg.app.outputs import claimed
    with claimed(tmp_path / "out"):
        assert main(["batch", str(scenes), "--out", str(tmp_path / "out"), *TINY]) == cli.EXIT_USAGE
    assert "being written by another cvqpg command" in one_line_error(capsys)


def write_manifest(path, rows):
    path.write_text("\n".join(",".join(row) for row in rows) + "\n")
    return path


def test_a_manifest_names_its_items_and_reads_its_paths_beside_it(tmp_path):
    picture(tmp_path / "frames" / "one.png")
    picture(tmp_path / "frames" / "sushi" / "image.png")
    depth_map(tmp_path / "frames" / "one_depth.png")
    manifest = write_manifest(tmp_path / "list.csv", [
        ("image", "depth", "name", "steps", "color"), ("frames/one.png", "frames/one_depth.png", "", "", ""),
        ("frames/sushi/image.png", "", "", "7", "gray"), ("frames/one.png", "", "again", "", "")])
    items = read_inputs(manifest)
    assert [item.name for item in items] == ["one", "sushi", "again"]
    assert items[0].image == tmp_path / "frames" / "one.png" and items[0].depth == tmp_path / "frames/one_depth.png"
    assert items[1].depth is None and items[1].options == {"steps": "7", "color": "gray"}
    sushi = plan_item(items[1], tmp_path / "out", BatchSettings(settings={"width": W, "height": H, "steps": 3}))
    targets = sushi.config.targets
    assert (sushi.config.optimisation.steps, targets.color, targets.num_planes) == (7, "gray", 1)
    assert sushi.note == batch.NO_DEPTH_NOTE and sushi.budget is None and sushi.output == tmp_path / "out" / "sushi"


@pytest.mark.parametrize("rows, message", [
    ([("image", "colour"), ("a.png", "gray")], "unknown column 'colour'; the columns are image, depth, name, color"),
    ([("name", "depth"), ("a", "a.png")], "has no image column"),
    ([("image",), ("x/a.png",), ("y/a.png",)], "the name 'a' is line 2's too"),
    ([("image", "name"), ("a.png", ".hidden")], "'.hidden' cannot name an item"),
    ([("image",), ("a.png", "b.png")], "line 2 has more cells than the header has columns"),
    ([("image", "name"), ("", "a")], "line 2 names no image")])
def test_a_manifest_that_cannot_be_read_is_one_line_before_any_fit(tmp_path, rows, message, capsys):
    manifest = write_manifest(tmp_path / "list.csv", rows)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        read_inputs(manifest)
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), *TINY]) == cli.EXIT_USAGE
    assert message.split(";")[0] in one_line_error(capsys) and not (tmp_path / "out").exists()


def test_an_items_own_options_replace_the_commands_and_those_that_cannot_work_fail_that_item(tmp_path):
    settings = BatchSettings(settings={"width": W, "height": H, "num_gaussians": 50, "num_planes": None},
                             bpp=8.0)
    item = BatchInput("a", tmp_path / "a.png", tmp_path / "a_depth.png", {"ratio": "0.1", "max_bytes": "600"}, "row 2")
    planned = plan_item(item, tmp_path, settings)
    assert planned.config.primitive_count == round(0.1 * W * H / 2) and planned.config.targets.num_planes == 2
    assert (planned.budget.bpp, planned.budget.max_bytes) == (None, 600) and planned.output == tmp_path / "a.cvq"
    assert planned.config.optimisation.steps == batch.ENCODE_STEPS  # a .cvq item's default, as encode's
    assert plan_item(BatchInput("b", tmp_path / "b.png"), tmp_path, settings).budget.bpp == 8.0
    for options, message in (({"steps": "many"}, "row 2: column steps: 'many' is not a whole number"),
                             ({"color": "sepia"}, "row 2: `color` 'sepia' is not one of"),
                             ({"planes": "3"}, "row 2: 3 planes (`num_planes`) need a depth map"),
                             ({"max_bytes": "100"}, "row 2: .*smallest file"),
                             ({"bpp": "1", "max_bytes": "300"}, "give one goal")):
        with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
            plan_item(BatchInput("b", tmp_path / "b.png", None, options, "row 2"), tmp_path, settings)


@pytest.mark.slow
def test_a_manifests_rows_fit_with_their_own_options_into_run_folders_and_cvq_files(tmp_path, capsys):
    picture(tmp_path / "in" / "one.png")
    picture(tmp_path / "in" / "two.png", 40)
    picture(tmp_path / "in" / "three.png", 80)
    depth_map(tmp_path / "in" / "two_depth.png")
    manifest = write_manifest(tmp_path / "in" / "list.csv", [
        ("image", "depth", "bpp", "color", "steps"), ("one.png", "", "8", "gray", ""),
        ("two.png", "two_depth.png", "", "gray", ""), ("three.png", "", "", "", "x")])
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out), *TINY, "--finetune", "2"]) == cli.EXIT_USAGE
    assert "three: line 4: column steps: 'x' is not a whole number" in one_line_error(capsys).replace(
        f"manifest {manifest} ", "")
    rows = summary(out)
    assert {name: row["status"] for name, row in rows.items()} == {"one": "done", "two": "done", "three": "failed"}
    assert int(rows["one"]["bytes"]) == (out / "one.cvq").stat().st_size <= 8 * W * H / 8
    assert float(rows["one"]["bpp"]) <= 8 and rows["one"]["output"] == "one.cvq"
    assert read_compressed(out / "one.cvq").config.targets.color == "gray"
    two = json.loads((out / "two" / "config.json").read_text())
    assert (two["targets"]["color"], two["targets"]["num_planes"]) == ("gray", 2)
    assert sorted(p.name for p in out.iterdir()) == [".batch", "one.cvq", "summary.csv", "summary.md", "two"]


def test_an_item_that_hits_a_bug_leaves_its_traceback_beside_it_and_the_batch_exits_1(tmp_path, monkeypatch,
                                                                                       capsys):
    scenes = scene_folders(tmp_path / "scenes", names=("a",))
    monkeypatch.setattr(batch, "scene_from_source", lambda *args: 1 / 0)
    out = tmp_path / "out"
    assert main(["batch", str(scenes), "--out", str(out), *TINY]) == cli.EXIT_BUG
    error = one_line_error(capsys)
    assert "a: internal error (ZeroDivisionError: division by zero); traceback in" in error
    assert "Traceback" in (out / "a.error.log").read_text() and summary(out)["a"]["status"] == "failed"


def test_the_summaries_list_every_item_and_are_rewritten_at_most_every_few_seconds_while_items_run(tmp_path,
                                                                                                   monkeypatch):
    inputs = [BatchInput(name, tmp_path / f"{name}.png") for name in ("a", "b", "c")]
    batch.start_batch(tmp_path, inputs, {"a": "a", "b": "b.cvq", "c": "c"}, {"c": batch.NO_DEPTH_NOTE})
    (tmp_path / "b.cvq.partial").mkdir()
    batch.update_summary(tmp_path)
    rows = summary(tmp_path)
    assert [(row["status"], row["output"], row["note"]) for row in rows.values()] == [
        ("not started", "a", ""), ("interrupted", "b.cvq.partial", ""), ("not started", "c", batch.NO_DEPTH_NOTE)]
    batch.write_record(tmp_path, {"name": "a", "status": "done", "output": "a", "psnr_db": 31.25, "bytes": 10,
                                  "bpp": 0.1, "steps": 3, "seconds": 2.0, "device": "cpu: x"})
    batch.update_summary(tmp_path)  # a moment after the last: left for the next, or the batch's end
    assert summary(tmp_path)["a"]["status"] == "not started"
    batch.update_summary(tmp_path, now=True)
    assert summary(tmp_path)["a"]["psnr_db"] == "31.2500" and "| a | done | a | 31.2500 |" in (
        tmp_path / "summary.md").read_text()
    monkeypatch.setattr(batch, "SUMMARY_SECONDS", 0.0)
    batch.write_record(tmp_path, {"name": "c", "status": "failed", "output": "c", "error": "bad", "kind": "input"})
    batch.update_summary(tmp_path)
    assert summary(tmp_path)["c"]["error"] == "bad"


@pytest.mark.slow
def test_an_interrupted_batch_resumes_to_the_parameters_of_an_uninterrupted_one(tmp_path, monkeypatch, capsys):
    scenes = scene_folders(tmp_path / "scenes", names=("a", "b"))
    steps = ["--steps", "8", "--checkpoint-every", "2"]
    assert main(["batch", str(scenes), "--out", str(tmp_path / "whole"), *TINY, *steps]) == 0
    monkeypatch.setattr(executors, "POLL_SECONDS", 0.0)  # every step asks: the stop comes at the same step each time
    monkeypatch.setattr(signals, "StopRequest", CountedStop)
    monkeypatch.setattr(CountedStop, "asked", [])
    monkeypatch.setattr(CountedStop, "after", 5)  # a stops within its first steps, keeping a checkpoint
    out = tmp_path / "out"
    assert main(["batch", str(scenes), "--out", str(out), *TINY, *steps]) == 128 + signal.SIGINT
    rows = summary(out)
    assert rows["a"]["status"] == "interrupted" and rows["a"]["output"] == "a.partial"
    assert (out / "a.partial" / "checkpoint.pt").is_file() and not (out / "a").exists()
    assert rows["b"]["status"] == "not started"
    monkeypatch.setattr(CountedStop, "after", None)
    assert main(["batch", str(scenes), "--out", str(out), *TINY, *steps]) == 0
    assert {row["status"] for row in summary(out).values()} == {"done"}
    for name in ("a", "b"):
        resumed, whole = (load_model(folder / name / "model.safetensors")[0].tensors()
                          for folder in (out, tmp_path / "whole"))
        assert all(torch.equal(resumed[key], whole[key]) for key in whole)


@pytest.mark.slow
def test_overwrite_fits_finished_items_again_and_replaces_each(tmp_path, fits):
    scenes = scene_folders(tmp_path / "scenes", names=("a",))
    out = tmp_path / "out"
    assert main(["batch", str(scenes), "--out", str(out), *TINY]) == 0
    assert main(["batch", str(scenes), "--out", str(out), *TINY, "--overwrite", "--steps", "4"]) == 0
    assert fits == ["a.partial", "a.partial"]
    assert json.loads((out / "a" / "metrics.json").read_text())["steps"] == 4 and summary(out)["a"]["steps"] == "4"


def models(folder, names):
    return {name: load_model(folder / name / "model.safetensors")[0].tensors() for name in names}


@pytest.mark.slow
@pytest.mark.xdist_group("ray")  # with the other tests that start Ray (test_executors.py), one at a time
def test_a_batch_on_ray_gives_the_local_executors_results_bit_for_bit(tmp_path):
    scenes = scene_folders(tmp_path / "scenes", corrupt=("c",))
    arguments = ["batch", str(scenes), *TINY, "--threads", "1"]
    assert main([*arguments, "--out", str(tmp_path / "local")]) == cli.EXIT_USAGE
    assert main([*arguments, "--out", str(tmp_path / "ray"), "--executor", "ray"]) == cli.EXIT_USAGE  # Ray on 2 CPUs
    local, on_ray = summary(tmp_path / "local"), summary(tmp_path / "ray")
    assert [row["status"] for row in on_ray.values()] == [row["status"] for row in local.values()]
    assert on_ray["c"]["error"] == local["c"]["error"] and "not an image file" in local["c"]["error"]
    names = [name for name, row in local.items() if row["status"] == "done"]
    assert names == ["a", "b", "d", "e"]
    ray_models, local_models = models(tmp_path / "ray", names), models(tmp_path / "local", names)
    assert all(torch.equal(ray_models[name][key], local_models[name][key])
               for name in names for key in local_models[name])


@pytest.mark.slow
def test_an_interrupted_cvq_item_resumes_from_its_checkpoint_to_the_same_file(tmp_path, monkeypatch):
    scenes = scene_folders(tmp_path / "scenes", names=("a",))
    arguments = ["batch", str(scenes), *TINY, "--steps", "8", "--finetune", "2", "--bpp", "8", "--checkpoint-every",
                 "2"]
    assert main([*arguments, "--out", str(tmp_path / "whole")]) == 0
    started = []
    monkeypatch.setattr(batch, "start_encode", lambda *args: started.append(args) or start_encode(*args))
    monkeypatch.setattr(executors, "POLL_SECONDS", 0.0)  # every step asks: the stop comes at the same step each time
    monkeypatch.setattr(signals, "StopRequest", CountedStop)
    monkeypatch.setattr(CountedStop, "asked", [])
    monkeypatch.setattr(CountedStop, "after", 5)
    out = tmp_path / "out"
    assert main([*arguments, "--out", str(out)]) == 128 + signal.SIGINT
    assert summary(out)["a"]["status"] == "interrupted" and (out / "a.cvq.partial" / "checkpoint.pt").is_file()
    monkeypatch.setattr(CountedStop, "after", None)
    assert main([*arguments, "--out", str(out)]) == 0
    assert len(started) == 1  # the rerun resumed the encode's folder instead of starting it again
    assert (out / "a.cvq").read_bytes() == (tmp_path / "whole" / "a.cvq").read_bytes()
    assert not (out / "a.cvq.partial").exists() and summary(out)["a"]["status"] == "done"


def test_an_item_owns_only_the_output_its_record_names(tmp_path):
    """The batch takes an output for an item's only where the item's record names it by its fingerprint (or, for a
    record of cvqpg 0.3, which has none, where it says the item is done); a copy put in its place is not."""
    item = plan_item(BatchInput("a", picture(tmp_path / "a.png")), tmp_path / "out", BatchSettings())
    output = item.output
    (item.folder / ".batch").mkdir(parents=True)
    output.mkdir()
    for name, text in (("config.json", "{}"), ("model.safetensors", "model"), ("metrics.json", "{}")):
        (output / name).write_text(text)
    assert not item.owned() and not item.finished()
    batch.write_record(item.folder, {"name": "a", "status": "failed", "output": "a",
                                     "fingerprint": batch.fingerprint(output)})
    assert item.owned() and not item.finished()
    batch.write_record(item.folder, {"name": "a", "status": "done", "output": "a"})  # the fingerprint is kept
    assert item.finished() and batch.item_problem(item) is None
    (output / "metrics.json").write_text('{"rewritten": "by eval"}')
    assert item.finished()
    (output / "model.safetensors").write_text("another fit's model")
    assert not item.owned() and "not a run folder this batch wrote" in batch.item_problem(item)
    batch.write_json(batch._record_path(item.folder, "a"), {"name": "a", "status": "done", "output": "a"})
    assert item.finished()  # cvqpg 0.3's record


@pytest.mark.parametrize("name, message", [
    ("n" * 235, "235 bytes long"), ("é" * 118, "236 bytes long"), ("a\x00b", "U+0000"), ("a\nb", "U+000A"),
    ("a\x7fb", "U+007F"), ("a\udcffb", "not valid UTF-8")])
def test_a_name_the_batch_cannot_write_beside_is_refused_where_it_is_read(name, message):
    with pytest.raises(InputError, match=message.replace("+", r"\+")):
        batch.check_name(name, "here")
    assert batch.check_name("n" * (batch.NAME_BYTES - batch.ADDED_NAME_BYTES), "here")
