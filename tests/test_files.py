"""Files a run leaves follow the user's umask, and atomic writes never leave a half-written file."""

import os
import stat

import pytest
import torch

from cvqpg.cli import main
from cvqpg.files import atomic_file, write_atomic
from cvqpg.storage import load_checkpoint, save_checkpoint

UMASK = 0o027
EXPECTED_MODE = 0o666 & ~UMASK


@pytest.fixture
def umask():
    previous = os.umask(UMASK)
    yield UMASK
    os.umask(previous)


def modes(folder):
    return {p.name: stat.S_IMODE(p.stat().st_mode) for p in folder.rglob("*") if p.is_file()}


@pytest.mark.slow
def test_every_file_of_a_run_follows_the_umask(tmp_path, umask):
    out = tmp_path / "run"
    assert main(["fit", "--size", "48", "36", "--steps", "2", "--curvature-warmup", "1", "--quiet", "--out", str(out),
                 "--checkpoint-every", "1"]) == 0
    assert main(["info", str(out), "--half"]) == 0
    written = modes(out)
    assert {"model.safetensors", "model.f16.safetensors", "metrics.json", "config.json"} <= set(written)
    assert {name: mode for name, mode in written.items() if mode != EXPECTED_MODE} == {}


def test_checkpoint_follows_the_umask(tmp_path, umask):
    save_checkpoint(tmp_path / "checkpoint.pt", {"step": torch.tensor(3)})
    assert modes(tmp_path) == {"checkpoint.pt": EXPECTED_MODE}
    assert int(load_checkpoint(tmp_path / "checkpoint.pt")["step"]) == 3


def test_failed_write_keeps_the_previous_file_and_leaves_no_partial(tmp_path):
    target = tmp_path / "metrics.json"
    write_atomic(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_file(target) as handle:
            handle.write(b"half")
            raise RuntimeError("killed mid-write")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]
