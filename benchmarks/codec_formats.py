"""Two `.cvq` format versions (or two encoder settings) on the same fits, codec alone: BD-rate at equal PSNR.

    # the points of the code importable here, one file per fit run folder:
    python benchmarks/codec_formats.py points runs/sushi-gray runs/bento-rgb --out v5.json
    # the same fits coded by an older commit (a worktree of it), with this script:
    git worktree add /tmp/old <commit>
    PYTHONPATH=/tmp/old python benchmarks/codec_formats.py points runs/sushi-gray runs/bento-rgb --out v4.json
    # BD-rate of the second against the first, per fit:
    python benchmarks/codec_formats.py compare v4.json v5.json

`points`: each run folder's float model coded at the `search.LADDER` rungs −3 … 0 and at rungs −2 … 0 with
positions one bit coarser (7 files per fit), no fine-tuning; each file decoded and rendered as a reader
would, and scored against the run's targets (mean PSNR over the planes). Records the bytes, header bytes,
PSNR, encode and decode seconds (medians of `--repeat` turns, one thread) and the format version of every file.
`--tools NAME ...` restricts format 5's optional tools to those named (`codec.TOOLS`; none: `--tools`
alone), so that each can be measured on its own.

`compare`: per fit, the BD-rate of the second file's points against the first's on their Pareto fronts
(`campaign.ratedistortion.bd_rate`), over [fit − 3, fit − 0.1] dB and over the whole ladder, and the byte
ratio at each rung where both decode to the same PSNR.
"""

from __future__ import annotations

import argparse
import inspect
import json
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from cvqpg import codec
from cvqpg.campaign.ratedistortion import bd_rate
from cvqpg.fitting import render
from cvqpg.metrics import mean_psnr
from cvqpg.runs import load_run_model, scene_from_source
from cvqpg.search import LADDER

RUNGS = (-3, -2, -1, 0)


def settings() -> list[tuple[str, codec.BitDepths]]:
    """The comparison's bit depths: the ladder's rungs −3 … 0, and −2 … 0 with positions one bit coarser."""
    rungs = [(f"rung {delta}", LADDER[3 + delta]) for delta in RUNGS]
    coarser = [(f"rung {delta}, position −1", replace(LADDER[3 + delta], position=LADDER[3 + delta].position - 1))
               for delta in RUNGS[1:]]
    return rungs + coarser


def encoder(tools: list[str] | None):
    """`codec.encode`, restricted to `tools` where the code takes them."""
    if tools is None:
        return codec.encode
    if "tools" not in inspect.signature(codec.encode).parameters:
        raise SystemExit("this codec has no optional tools to choose from")
    return lambda primitives, config, bits: codec.encode(primitives, config, bits, tools=frozenset(tools))


def header_bytes(data: bytes) -> int:
    """A file's bytes outside its streams: prefix, compressed header and checksum."""
    return len(data) - sum(stream["bytes"] for stream in codec.decode(data).streams)


def seconds(action, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        action()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def fit_points(folder: Path, tools: list[str] | None, repeat: int) -> dict:
    primitives, config, source = load_run_model(folder)
    targets = scene_from_source(source, config).targets
    encode = encoder(tools)
    fit_psnr = mean_psnr(render(primitives, config)[1], targets)
    points = []
    for label, bits in settings():
        data = encode(primitives, config, bits)
        decoded = codec.decode(data)
        psnr = mean_psnr(render(decoded.primitives, config)[1], targets)
        points.append({"setting": label, "bits": bits.__dict__, "bytes": len(data),
                       "bpp": codec.bits_per_pixel(len(data), config), "psnr": psnr, "version": decoded.version,
                       "header_bytes": header_bytes(data),
                       "streams": {stream["name"]: stream["bytes"] for stream in decoded.streams},
                       "encode_s": seconds(lambda: encode(primitives, config, bits), repeat),
                       "decode_s": seconds(lambda: codec.decode(data), repeat)})
        print(f"{folder.name} {label}: {len(data)} B, {psnr:.3f} dB", flush=True)
    return {"run": str(folder), "num_primitives": primitives.count, "fit_psnr": fit_psnr, "points": points}


def compare(anchor: dict, test: dict) -> None:
    for run, first in anchor.items():
        second = test.get(run)
        if second is None:
            continue
        fit = first["fit_psnr"]
        near = bd_rate(first["points"], second["points"], fit - 0.1, 2.9)
        whole = bd_rate(first["points"], second["points"], fit, 100.0)
        ratios = [b["bytes"] / a["bytes"] for a, b in zip(first["points"], second["points"])]
        psnr_moved = max(abs(a["psnr"] - b["psnr"]) for a, b in zip(first["points"], second["points"]))
        print(json.dumps({"run": Path(run).name, "N": first["num_primitives"], "fit_psnr": round(fit, 3),
                          "bd_rate_near_fit": None if near is None else round(near.percent, 2),
                          "bd_rate_whole": None if whole is None else round(whole.percent, 2),
                          "range_whole": None if whole is None else [round(whole.low, 1), round(whole.high, 1)],
                          "byte_ratio": [round(r, 4) for r in ratios], "max_psnr_change_db": round(psnr_moved, 4),
                          "header_bytes": [first["points"][3]["header_bytes"], second["points"][3]["header_bytes"]],
                          "encode_s_rung0": [round(p["points"][3]["encode_s"], 4) for p in (first, second)],
                          "decode_s_rung0": [round(p["points"][3]["decode_s"], 4) for p in (first, second)]}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    points = commands.add_parser("points")
    points.add_argument("runs", nargs="+", type=Path, help="run folders of fits")
    points.add_argument("--out", type=Path, required=True)
    points.add_argument("--tools", nargs="*", default=None, help="format 5's tools to use [default: all]")
    points.add_argument("--repeat", type=int, default=3, help="turns timed per file (medians)")
    versus = commands.add_parser("compare")
    versus.add_argument("anchor", type=Path)
    versus.add_argument("test", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.command == "points":
        record = {str(run): fit_points(run, args.tools, args.repeat) for run in args.runs}
        args.out.write_text(json.dumps(record, indent=1))
    else:
        compare(json.loads(args.anchor.read_text()), json.loads(args.test.read_text()))


if __name__ == "__main__":
    main()
