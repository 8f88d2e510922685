"""Golden `.cvq` files: one RGB and one grayscale file of every format version, each decoded by today's reader and
compared with what the version that wrote it decoded it to.

`tests/data/format_v{N}.cvq` (RGB) and `format_v{N}_gray.cvq` are files as format version N wrote them, and
`format_v{N}[_gray]_decoded.safetensors` the primitives that the same commit's `decode` returned for them
(`Primitives.tensors()`, float32). A change to the decoder (the quantisers, `derived_depths`,
`importance_offsets`, the Morton order, a stream coding) that would read a file already written differently
fails here, even where encoder and decoder were changed alike and every round trip still passes.

How a golden file is made, once, when a format version is introduced: check out the commit that writes version N
(`git worktree add /tmp/old-<commit> <commit>`) and, with `PYTHONPATH=/tmp/old-<commit>`, make random primitives
with `init_gaussians(config.primitive_count, config.channels, width, height, seed)`, draw their raw values
(RGB, seed 3: amplitude U(-1, 1), phase U(-7, 14), rotation U(-7, 7), curvature U(-3, 3), opacity U(-2, 2);
grayscale, seed 5: amplitude ±0.1·exp(1.5·N(0, 1)) with a random sign, log scale plus 1.2·N(0, 1), phase N(0, 0.6),
curvature N(0, 0.4), opacity N(1, 1)), `activate` them, `encode` them at the default `BitDepths()` and store
the bytes and `decode(bytes).primitives.tensors()`. The configurations (`FitConfig` defaults otherwise): 48×32 px
RGB, curvature per channel (ratio 0.3: 230 primitives); 40×32 px grayscale, one plane, shared curvature (96
primitives). Between them the files use every stream coding (raw, laplace, gaussian, categorical, bitlength, widths,
grouped). The commits that wrote them: version 1 337a462 (a285f63's parent), 2 b61bea5 (26e6382's parent), 3
4c01f38 (f53969e's parent), 4 34cc80f; the RGB files of versions 2 and 3 came with 26e6382 and f53969e, and the
same recipe at those commits remakes them byte for byte. Version 5's RGB file follows the same recipe (through
`FitConfig.create`), written with every tool (`codec._file(..., TOOLS)`, 3,243 bytes) so that `channels` is
covered, where `encode` keeps the smaller file without it (3,161 bytes); its grayscale file is of more primitives whose symbols gather, so that `turn` is
used: 160×120 px grayscale, 2 planes, shared curvature, ratio 0.3 (1,440 primitives), `random_primitives(config)`
of tests/test_codec.py (seed 3) with amplitude |amplitude|, phase 0.2·N(0, 1) mod 2π and scale exp(1 + 0.8·N(0, 1))
px drawn in that order from `torch.Generator().manual_seed(1)` (`gathered_primitives`). Version 5 decodes the scale
with `codec.exact_exp`, so its files decode to the same bits on every machine and are compared exactly. Version
6's files were written at the commit that introduced it, its grayscale file by the version-5 recipe (its bytes are
version 5's but for the version number), its RGB file by the version-5 RGB recipe of that commit (the primitives
`random_primitives(config)` drew there) for a model fitted through a DPAC display with a lookup table of 300
phases (0.02·g rad), aperture 0.6 and a 56×40 canvas, so that the header's `display` is covered. Version 6 also
keeps the phase terms beyond the curvature: `format_v6_gray_quadratic-tilt.cvq` and `format_v6_gray_axes-tilt.cvq`
(`PHASED`) were written at the commit that introduced them by the grayscale recipe above through `FitConfig.create`
(40×32 px, one plane, `phase` quadratic+tilt or axes+tilt, 64 primitives; curvature 0 for axes+tilt, which has no
quadratic term), the terms' raw values drawn N(0, 1) after the opacity, so that the `tilt` and `axes` streams, the
header's `phase` and the terms' depths are covered.

**Never regenerate a golden file**: a file written by today's code proves only that today's decoder reads what
today's encoder writes. A new format version adds its own pair of files; a version's files stay as they are.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from cvqpg.codec import FORMAT_VERSION, MAGIC, PREFIX, BitDepths, decode, header_start, inflated, optics
from cvqpg.display import Display

DATA = Path(__file__).parent / "data"
GOLDEN = [(version, kind) for version in range(1, FORMAT_VERSION + 1) for kind in ("rgb", "gray")]


def golden(version: int, kind: str, suffix: str = ".cvq") -> Path:
    """A golden file: `format_v{N}.cvq` holds the RGB model, `format_v{N}_gray.cvq` the grayscale one."""
    return DATA / f"format_v{version}{'' if kind == 'rgb' else '_' + kind}{suffix}"
# Scale is exp of the decoded log scale through numpy's float32 exp, whose last bits may differ between CPUs
# (SIMD paths); curvature in 1/m is its share of a bound that follows the scale. 1e-6 is about 8 float32 ulps:
# far below a quantisation step (1/255 of the range at 8 bits), far above such rounding.
ROUNDED_BY_EXP = {"scale_px": 1e-6, "curvature_per_m": 1e-6}


def header(data: bytes) -> tuple[int, dict]:
    """A `.cvq` file's format version and its header (docs/format.md)."""
    _, version, length = PREFIX.unpack_from(data)
    start = header_start(version)
    return version, json.loads(inflated(data[start:start + length], version))


def test_every_format_version_has_golden_files():
    """A new format version must come with its golden files (this module's docstring says how)."""
    missing = [golden(v, kind).name for v, kind in GOLDEN if not golden(v, kind).is_file()]
    assert not missing, f"no golden files {missing}: write them with the commit that introduces the version"


# Golden files of the phase terms beyond the curvature: (version, `kind` of the file's name, the phase it holds).
PHASED = [(6, "gray_quadratic-tilt", "quadratic+tilt"), (6, "gray_axes-tilt", "axes+tilt")]


@pytest.mark.parametrize("version, kind, phase", PHASED, ids=[kind for _, kind, _ in PHASED])
def test_a_golden_file_of_phase_terms_decodes_as_the_version_that_wrote_it_decoded_it(version, kind, phase):
    data = golden(version, kind).read_bytes()
    expected = load_file(golden(version, kind, "_decoded.safetensors"))
    _, written = header(data)
    decoded = decode(data)
    assert written["optics"]["phase"] == decoded.config.phase.name == phase
    assert decoded.bits == BitDepths(**written["bits"]) and set(written["bits"]) >= set(decoded.primitives.terms)
    tensors = decoded.primitives.tensors()
    assert tensors.keys() == expected.keys() and {"tilt_rad"} <= tensors.keys()
    for name, tensor in tensors.items():
        torch.testing.assert_close(tensor, expected[name], rtol=0, atol=0, msg=name)


@pytest.mark.parametrize("version, kind", GOLDEN, ids=[f"v{v}-{kind}" for v, kind in GOLDEN])
def test_a_golden_file_decodes_as_the_version_that_wrote_it_decoded_it(version, kind):
    data = golden(version, kind).read_bytes()
    expected = load_file(golden(version, kind, "_decoded.safetensors"))
    assert data.startswith(MAGIC) and struct.unpack_from("<H", data, len(MAGIC))[0] == version
    written_version, written = header(data)
    decoded = decode(data)
    assert decoded.version == written_version == version
    assert decoded.bits == BitDepths(**written["bits"])
    rendering = optics(decoded.config)
    assert {name: rendering[name] for name in written["optics"]} == written["optics"]
    assert decoded.config.display == Display.from_dict(written.get("display") if version >= 6 else None)
    tensors = decoded.primitives.tensors()
    assert tensors.keys() == expected.keys()
    for name, tensor in tensors.items():
        rounded = ROUNDED_BY_EXP.get(name, 0.0) if version < 5 else 0.0
        torch.testing.assert_close(tensor, expected[name], rtol=rounded, atol=0, msg=name)
