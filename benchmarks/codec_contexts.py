"""What context models could save on a model's `.cvq` streams, before any is built: ideal code lengths.

    python benchmarks/codec_contexts.py runs/sushi-gray/model.safetensors --rungs 0 -2

For each rung of `search.LADDER` (0: the default depths), the model is quantised as the file codes it
(`codec.quantise`, primitives in Morton order, each value at its derived depth) and every stream is
measured in bits: what the current format writes for it (`codec.encode_stream`), and the ideal code
length (Σ −log2 p) of its symbols under candidate models:

- `static`: one adaptive frequency table per depth (the current format's static tables, with their cost of
  learning in place of a header's histogram);
- `ctx:<name>`: one adaptive table per depth and context bucket, the context drawn from values the decoder
  holds before the symbol;
- `res:<name>`: the symbol minus a prediction from such values (periodic attributes modulo their levels),
  coded with an adaptive table per depth.

Adaptive tables count symbols as they come (Krichevsky–Trofimov, ½ per unseen symbol), so their lengths
include what a per-file table costs to learn; a static table stored in the header costs its histogram instead.
Neighbours are causal: the primitives before it in the file's order (`prev`) or the k nearest among them in
position (`knn`). One JSON line per rung and stream.
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict

import numpy as np
import torch

from cvqpg.codec import encode_stream, quantise
from cvqpg.search import LADDER
from cvqpg.storage import load_model

NEIGHBOURS = 4


def adaptive_bits(symbols: np.ndarray, contexts: np.ndarray, alphabet: np.ndarray) -> float:
    """Code length (bits) of `symbols` in order, one KT-adaptive table per context, each of `alphabet` symbols."""
    counts: dict = defaultdict(lambda: defaultdict(float))
    totals: dict = defaultdict(float)
    bits: dict = defaultdict(float)
    for symbol, context, size in zip(symbols.tolist(), contexts.tolist(), alphabet.tolist()):
        key = (context, size)
        bits[key] -= math.log2((counts[key][symbol] + 0.5) / (totals[key] + 0.5 * size))
        counts[key][symbol] += 1
        totals[key] += 1
    # a table that does not pay is not used: its symbols raw
    return sum(min(b, totals[key] * math.log2(key[1])) for key, b in bits.items())


def causal_neighbours(xy: np.ndarray, k: int) -> np.ndarray:
    """For each primitive, the indices of the k nearest primitives before it (−1 where fewer)."""
    found = np.full((len(xy), k), -1, np.int64)
    for i in range(1, len(xy)):
        distance = ((xy[:i] - xy[i]) ** 2).sum(axis=1)
        nearest = np.argsort(distance, kind="stable")[:k]
        found[i, :len(nearest)] = nearest
    return found


def bucket(values: np.ndarray, edges: int = 4) -> np.ndarray:
    """Values in `edges` buckets of equal count (their quantiles)."""
    cuts = np.quantile(values, np.linspace(0, 1, edges + 1)[1:-1])
    return np.searchsorted(cuts, values)


def wrapped(residual: np.ndarray, levels: np.ndarray) -> np.ndarray:
    return np.mod(residual + levels // 2, levels) - levels // 2


def measure(path: str, delta: int) -> list[dict]:
    primitives, config = load_model(path)
    bits = LADDER[3 + delta]
    encoded = quantise(primitives, config, bits, frozenset())  # format 4's symbols: no tools
    streams, widths = encoded.streams, encoded.widths
    count, channels = primitives.count, config.channels
    gaps = streams["position"].astype(np.uint64)
    code = np.cumsum(gaps, dtype=np.uint64)
    x = np.zeros(count, np.int64)
    y = np.zeros(count, np.int64)
    for b in range(32):
        x |= ((code >> np.uint64(2 * b)) & np.uint64(1)).astype(np.int64) << b
        y |= ((code >> np.uint64(2 * b + 1)) & np.uint64(1)).astype(np.int64) << b
    xy = np.stack([x, y], axis=1).astype(np.float64)
    near = causal_neighbours(xy, NEIGHBOURS)
    has = near >= 0

    def neighbour_mean(values: np.ndarray) -> np.ndarray:
        """Mean of the causal neighbours' values (the primitive's own where it has none)."""
        mask = has if values.ndim == 1 else has[:, :, None]
        gathered = np.where(mask, values[np.maximum(near, 0)], 0.0)
        n = has.sum(axis=1) if values.ndim == 1 else has.sum(axis=1)[:, None]
        return np.where(n > 0, gathered.sum(axis=1) / np.maximum(n, 1), np.nan)

    scale_levels = 2 ** bits.scale - 1
    lo, hi = encoded.ranges["scale"]
    amp_max = encoded.ranges["amplitude"][1]
    log_scale = lo + streams["scale"] * (hi - lo) / scale_levels
    amp_depth = widths["amplitude"]
    amplitude = streams["amplitude"] * amp_max / np.maximum(2.0 ** amp_depth - 1, 1)
    phase_depth = widths["phase"]
    phase = streams["phase"] * 2 * math.pi / 2.0 ** phase_depth
    rows = []

    def report(stream: str, candidates: dict[str, float], actual: int) -> None:
        rows.append({"model": path, "rung": delta, "stream": stream, "format4_bytes": actual,
                     **{name: round(b / 8, 1) for name, b in candidates.items()}})

    def actual_bytes(name: str) -> int:
        return encode_stream(streams[name], widths.get(name))[0]["bytes"]

    # scale [N, 2]: one table in format 4 (depth fixed)
    s = streams["scale"]
    size = np.full(count, scale_levels + 1)
    sizes2 = np.full(2 * count, scale_levels + 1)
    nb = neighbour_mean(s.astype(float))
    candidates = {
        "static": adaptive_bits(s.ravel(), np.zeros(2 * count, int), sizes2),
        "res:y-x": adaptive_bits(s[:, 0], np.zeros(count, int), size)
        + adaptive_bits(s[:, 1] - s[:, 0] + scale_levels, np.zeros(count, int), 2 * size),
        "ctx:x|y": adaptive_bits(s[:, 0], np.zeros(count, int), size)
        + adaptive_bits(s[:, 1], s[:, 0] // 16, size),
        "res:knn": sum(adaptive_bits(s[:, a] - np.round(np.nan_to_num(nb[:, a], nan=s[:, a].mean())).astype(int)
                                     + scale_levels, np.zeros(count, int), 2 * size) for a in range(2)),
        "ctx:knn": sum(adaptive_bits(s[:, a], np.nan_to_num(nb[:, a], nan=-16).astype(int) // 32, size)
                       for a in range(2)),
        "ctx:x|y+knn": adaptive_bits(s[:, 0], np.nan_to_num(nb.mean(1), nan=-16).astype(int) // 32, size)
        + adaptive_bits(s[:, 1] - s[:, 0] + scale_levels, np.nan_to_num(np.abs(nb[:, 0] - nb[:, 1]), nan=-1)
                        .astype(int) // 8, 2 * size),
    }
    report("scale", candidates, actual_bytes("scale"))

    # amplitude [N, C] at depth per primitive
    a, d = streams["amplitude"], amp_depth
    flat_ctx = np.zeros(a.size, int)
    nb_amp = neighbour_mean(np.log(np.maximum(amplitude.mean(1), 1e-12)))
    area = log_scale.sum(1)
    candidates = {
        "static": adaptive_bits(a.ravel(), d.ravel(), 2 ** d.ravel()),
        "ctx:area": adaptive_bits(a.ravel(), np.repeat(bucket(area), channels), 2 ** d.ravel()),
        "ctx:knn": adaptive_bits(a.ravel(), np.repeat(bucket(np.nan_to_num(nb_amp, nan=-30)), channels),
                                 2 ** d.ravel()),
        "ctx:knn8": adaptive_bits(a.ravel(), np.repeat(bucket(np.nan_to_num(nb_amp, nan=-30), 8), channels),
                                  2 ** d.ravel()),
    }
    if channels > 1:
        first = adaptive_bits(a[:, 0], d[:, 0], 2 ** d[:, 0])
        res = a[:, 1:] - a[:, :-1]
        candidates["res:prev-channel"] = first + adaptive_bits(res.ravel() + 2 ** d[:, 1:].ravel(), d[:, 1:].ravel(),
                                                              2 ** (d[:, 1:].ravel() + 1))
        ctx = np.minimum(a[:, :-1] * 8 // np.maximum(2 ** d[:, :-1], 1), 7)
        candidates["ctx:prev-channel"] = first + adaptive_bits(a[:, 1:].ravel(), ctx.ravel(), 2 ** d[:, 1:].ravel())
        ctx16 = np.minimum(a[:, :-1] * 16 // np.maximum(2 ** d[:, :-1], 1), 15)
        candidates["ctx:prev-channel16"] = first + adaptive_bits(a[:, 1:].ravel(), ctx16.ravel(),
                                                                 2 ** d[:, 1:].ravel())
        candidates["ctx:prev-channel16+first-knn"] = adaptive_bits(
            a[:, 0], bucket(np.nan_to_num(nb_amp, nan=-30)), 2 ** d[:, 0]) + adaptive_bits(
            a[:, 1:].ravel(), ctx16.ravel(), 2 ** d[:, 1:].ravel())
    del flat_ctx
    report("amplitude", candidates, actual_bytes("amplitude"))

    # phase [N, C] at depth per value
    p, d = streams["phase"], phase_depth
    live = d > 0
    candidates = {"static": adaptive_bits(p[live], d[live], 2 ** d[live])}
    nb_phase = []
    for c in range(channels):
        gathered = np.where(has, phase[np.maximum(near, 0), c], np.nan)
        nb_phase.append(gathered[:, 0])
    nearest_phase = np.stack(nb_phase, axis=1)
    pred = np.round(np.nan_to_num(nearest_phase) / (2 * math.pi) * 2.0 ** d).astype(np.int64)
    res = wrapped(p - pred, 2 ** d)
    candidates["res:nearest"] = adaptive_bits(res[live] + 2 ** d[live] // 2, d[live], 2 ** d[live])
    if channels > 1:
        prev = np.round(phase[:, :-1] / (2 * math.pi) * 2.0 ** d[:, 1:]).astype(np.int64)
        res = p.copy()
        res[:, 1:] = wrapped(p[:, 1:] - prev, 2 ** d[:, 1:]) + 2 ** d[:, 1:] // 2
        candidates["res:prev-channel"] = adaptive_bits(res[live], d[live], 2 ** d[live])
        wl = np.asarray(config.wavelengths)
        scaled = np.round(np.mod(phase[:, :-1] * (wl[:-1] / wl[1:]), 2 * math.pi) / (2 * math.pi)
                          * 2.0 ** d[:, 1:]).astype(np.int64)
        res = p.copy()
        res[:, 1:] = wrapped(p[:, 1:] - scaled, 2 ** d[:, 1:]) + 2 ** d[:, 1:] // 2
        candidates["res:prev-channel·λ"] = adaptive_bits(res[live], d[live], 2 ** d[live])
    report("phase", candidates, actual_bytes("phase"))

    # rotation [N]
    r, d = streams["rotation"], widths["rotation"]
    live = d > 0
    rot = r * math.pi / 2.0 ** d
    gathered = np.where(has[:, 0], rot[np.maximum(near[:, 0], 0)], 0.0)
    pred = np.round(gathered / math.pi * 2.0 ** d).astype(np.int64)
    candidates = {"static": adaptive_bits(r[live], d[live], 2 ** d[live]),
                  "res:nearest": adaptive_bits(wrapped(r - pred, 2 ** d)[live] + 2 ** d[live] // 2, d[live],
                                               2 ** d[live])}
    report("rotation", candidates, actual_bytes("rotation"))

    if "curvature" in streams:
        k, d = streams["curvature"], widths["curvature"]
        half = 2 ** (d - 1) - 1
        flatk, flatd = k.ravel(), d.ravel()
        share = k / np.maximum(half, 1)
        nbk = neighbour_mean(share if share.ndim == 1 else share.mean(1))
        ctx = bucket(np.nan_to_num(nbk, nan=0.0))
        if k.ndim > 1:
            ctx = np.repeat(ctx, k.shape[1])
        candidates = {"static": adaptive_bits(flatk + 2 ** (flatd - 1), flatd, 2 ** flatd),
                      "ctx:knn": adaptive_bits(flatk + 2 ** (flatd - 1), ctx, 2 ** flatd),
                      "ctx:scale": adaptive_bits(flatk + 2 ** (flatd - 1), np.repeat(bucket(area), k.size // count),
                                                 2 ** flatd)}
        report("curvature", candidates, actual_bytes("curvature"))
    report("position", {}, actual_bytes("position"))
    report("fraction", {}, actual_bytes("fraction"))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="+")
    parser.add_argument("--rungs", type=int, nargs="+", default=[0, -2])
    args = parser.parse_args()
    torch.set_num_threads(1)
    for path in args.models:
        for delta in args.rungs:
            for row in measure(path, delta):
                print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
