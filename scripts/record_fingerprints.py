"""Record this machine's fingerprints of the paper recipe's small CPU fits, for tests/test_golden_fits.py.

    python scripts/record_fingerprints.py               # this machine at 2 threads (as the tests run)
    python scripts/record_fingerprints.py --threads 1 2 4

A CPU fit is bit-identical only on the same CPU (its instruction paths), the same torch and Numba (their kernels)
and the same thread count (the order of parallel sums), so tests/data/fit_fingerprints.json holds one set of
SHA-256 digests of the fitted parameters per machine (`machine`). Record a machine's BEFORE a change whose fits must
not move: the test then holds the change to them. A recorded machine is never rewritten; where this machine is
recorded already, the script refits and says whether its fits still match.

    python scripts/record_fingerprints.py --curves      # print the tolerance golden's PSNR curves

prints the PSNR curves that tests/data/fit_curves.json holds (the tolerance golden, which runs on every machine): for
a change meant to alter the fits, replace the file's curves by hand and say why in the commit.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numba
import torch

from cvqpg import FitConfig, builtin_pictures, fit
from cvqpg.app.provenance import code_commit, cpu_model
from cvqpg.control import SILENT

ROOT = Path(__file__).resolve().parents[1]

FINGERPRINTS = ROOT / "tests" / "data" / "fit_fingerprints.json"
CURVES = ROOT / "tests" / "data" / "fit_curves.json"
SIZE = dict(width=64, height=48, num_gaussians=300)
# The fits whose parameters are fingerprinted: the paper recipe, 40 steps, in three shapes of the model.
FITS = {"rgb_cvqpg_2planes": dict(color="rgb", primitive="cvqpg", num_planes=2),
        "gray_flat_1plane": dict(color="gray", primitive="flat", num_planes=1),
        "rgb_perchannel_std": dict(color="rgb", primitive="cvqpg", curvature="per-channel", qpf="standard",
                                   num_planes=2)}
FINGERPRINT_STEPS, FINGERPRINT_WARMUP = 40, 8
# The tolerance golden's fits: each recipe (its settings do not depend on the run's length), over a few dozen steps.
CURVE_STEPS, CURVE_WARMUP, CURVE_GUARD_BAND_PX = 30, 6, 32  # a narrow guard band: a step costs a few ms
CURVE_THREADS = 1  # a second thread changes no step beyond 2e-6 dB, and where the cores are busy it costs tenfold
RECIPE_FITS = ("paper", "beyond")


def machine(threads: int) -> dict[str, Any]:
    """What a fit's bits depend on beside the code: the CPU, torch, Numba and the thread count."""
    return {"cpu": cpu_model(), "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "torch": torch.__version__, "numba": numba.__version__, "threads": threads}


def same_machine(entry: dict[str, Any], here: dict[str, Any]) -> bool:
    return all(entry.get(key) == value for key, value in here.items())


@contextmanager
def threads_set(threads: int) -> Iterator[None]:
    """torch's and Numba's thread counts at `threads` (Numba's within its pool), restored after."""
    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])


def fingerprint_config(name: str) -> FitConfig:
    return FitConfig.create("paper", **SIZE, steps=FINGERPRINT_STEPS, curvature_warmup=FINGERPRINT_WARMUP,
                            **FITS[name])


def curve_config(name: str) -> FitConfig:
    return FitConfig.create(name, **SIZE, steps=CURVE_STEPS, curvature_warmup=CURVE_WARMUP,
                            guard_band_px=CURVE_GUARD_BAND_PX)


def demo_fit(config: FitConfig):
    pictures = builtin_pictures("demo", config.targets.width, config.targets.height)
    return fit(pictures.image, pictures.depth, config, control=SILENT)


def fingerprint(config: FitConfig) -> str:
    """SHA-256 of a demo fit's raw parameters: each field's name, then its bytes, in the model's field order."""
    digest = hashlib.sha256()
    for field_name, tensor in demo_fit(config).gaussians.tensors().items():
        digest.update(field_name.encode())
        digest.update(tensor.detach().contiguous().numpy().tobytes())
    return digest.hexdigest()


def fingerprints(threads: int) -> dict[str, str]:
    with threads_set(threads):
        return {name: fingerprint(fingerprint_config(name)) for name in FITS}


def psnr_curve(name: str) -> list[float]:
    """The progress PSNR (dB) of each step of a tolerance golden fit, to 1e-5 dB."""
    return [round(value, 5) for value in demo_fit(curve_config(name)).history["psnr"]]


def record(threads: int) -> str:
    """Add this machine's fingerprints at `threads` to the file, or check them where they are there already."""
    recorded = json.loads(FINGERPRINTS.read_text())
    here = machine(threads)
    found = next((entry for entry in recorded["machines"] if same_machine(entry, here)), None)
    digests = fingerprints(threads)
    if found is not None:
        moved = sorted(name for name in FITS if found["fits"].get(name) != digests[name])
        return f"{here}: recorded already; " + (f"these fits moved: {moved}" if moved else "every fit matches")
    recorded["machines"].append({**here, "commit": code_commit(), "date": datetime.date.today().isoformat(),
                                 "fits": digests})
    FINGERPRINTS.write_text(json.dumps(recorded, indent=1) + "\n")
    return f"{here}: recorded"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[2],
                        help="thread counts to record the fingerprints at (default: 2)")
    parser.add_argument("--curves", action="store_true", help="print the tolerance golden's PSNR curves instead")
    args = parser.parse_args(argv)
    if args.curves:
        with threads_set(CURVE_THREADS):
            for name in RECIPE_FITS:
                print(f'  "{name}": {json.dumps(psnr_curve(name))}')
        return 0
    for threads in args.threads:
        print(record(threads))
    return 0


if __name__ == "__main__":
    sys.exit(main())
