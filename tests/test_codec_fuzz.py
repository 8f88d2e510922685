"""The `.cvq` reader given altered files: whatever a header field or a stream byte holds, decoding ends in a model or
in one `ModelFileError` line, never in another exception (nor in the entropy coder's abort, which Python cannot
catch as an error). The files are small valid ones (the largest uses every stream coding), written here with the
current encoder; each alteration keeps the checksum valid, so that the reader's checks behind it are the ones
tried."""

from __future__ import annotations

import copy
import json
import math
import warnings
import zlib
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cvqpg.codec import CHECKSUM, MAGIC, PREFIX, BitDepths, decode, deflated, encode, header_start, inflated
from cvqpg.config import FitConfig
from cvqpg.errors import ModelFileError
from cvqpg.primitives import activate, init_gaussians

CONFIGS = (FitConfig.create(width=32, height=24, num_gaussians=12, color="gray", primitive="flat", num_planes=1),
           FitConfig.create(width=32, height=24, num_gaussians=16),
           FitConfig.create(width=32, height=24, num_gaussians=10, curvature="per-channel"),
           FitConfig.create(width=64, height=48, num_gaussians=300))  # enough primitives for every coding of the coder


def small_file(config: FitConfig, seed: int) -> bytes:
    raw = init_gaussians(config.primitive_count, config.channels, config.targets.width, config.targets.height,
                         seed)
    generator = torch.Generator().manual_seed(seed)
    raw.amplitude.uniform_(-1, 1, generator=generator)
    raw.curvature.uniform_(-2, 2, generator=generator)
    return encode(activate(raw, config), config, BitDepths(position=2, scale=6, rotation=5, amplitude=6, phase=5,
                                                           curvature=6))


# the current encoder's files, format 5's golden grayscale file (turned phases), and the golden files of format 4
# (whose header follows the prefix directly)
FILES = [small_file(config, seed) for seed, config in enumerate(CONFIGS)] + \
    [(Path(__file__).parent / "data" / name).read_bytes()
     for name in ("format_v5_gray.cvq", "format_v4.cvq", "format_v4_gray.cvq")]


def parts(data: bytes) -> tuple[int, dict, bytes]:
    _, version, length = PREFIX.unpack_from(data)
    start = header_start(version)
    return version, json.loads(inflated(data[start:start + length], version)), data[start + length:-CHECKSUM.size]


def packed(version: int, header: object, payload: bytes, fingerprint: bytes = bytes(range(16))) -> bytes:
    """A file of `version` (with `fingerprint` from format 5 on) of `header` and `payload`, checksum valid."""
    text = deflated(header, version)
    body = PREFIX.pack(MAGIC, version, len(text)) + fingerprint[:header_start(version) - PREFIX.size] + text + payload
    return body + CHECKSUM.pack(zlib.crc32(body))


def leaves(value: object, path: tuple = ()) -> list[tuple]:
    """The paths (keys and indices) of every value in a JSON document, containers included."""
    found = [path]
    if isinstance(value, dict):
        for key, item in value.items():
            found += leaves(item, path + (key,))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            found += leaves(item, path + (index,))
    return found


HOSTILE_VALUES = st.one_of(
    st.integers(min_value=-2**70, max_value=2**70), st.sampled_from([0, 1, -1, 2**31, 2**63, 2**64, 10**30]),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -0.0, 1e-300, 1e300, 0.5, math.nan]),
    st.booleans(), st.none(), st.text(max_size=8), st.sampled_from(["raw", "laplace", "gaussian", "categorical",
                                                                      "bitlength", "widths", "grouped"]),
    st.lists(st.integers(min_value=-5, max_value=2**20), max_size=3), st.dictionaries(st.text(max_size=4),
                                                                                      st.integers(), max_size=2))


@st.composite
def altered_files(draw) -> bytes:
    """A small valid file with some header fields replaced or removed, some stream bytes replaced, or both; now and
    then cut short or labelled with an older format version."""
    version, header, payload = parts(draw(st.sampled_from(FILES)))
    alter = draw(st.sampled_from(["header", "streams", "both"]))
    for _ in range(draw(st.integers(min_value=1, max_value=3)) if alter != "streams" else 0):
        path = draw(st.sampled_from(leaves(header)[1:]))
        parent = header
        for key in path[:-1]:
            parent = parent[key]
        if draw(st.booleans()) and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = draw(HOSTILE_VALUES)
        header = copy.deepcopy(header)
    payload = bytearray(payload)
    for _ in range(draw(st.integers(min_value=1, max_value=6)) if alter != "header" else 0):
        payload[draw(st.integers(min_value=0, max_value=len(payload) - 1))] = draw(st.integers(0, 255))
    if draw(st.integers(0, 9)) == 0:
        payload = payload[:draw(st.integers(min_value=0, max_value=len(payload)))]
    return packed(version if draw(st.integers(0, 9)) else draw(st.sampled_from([1, 2, 3, 4, 5])), header,
                  bytes(payload))


def test_the_unaltered_files_decode():
    for data, config in zip(FILES, CONFIGS):
        assert decode(data).primitives.count == config.primitive_count
    assert any(turned for data in FILES for turned in ["turn" in json.dumps(parts(data)[1])])


@pytest.mark.slow
@settings(max_examples=2000, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(altered_files())
def test_an_altered_file_decodes_or_is_refused_in_one_line(data):
    try:
        decode(data, "model.cvq")
    except ModelFileError as error:
        assert "\n" not in str(error) and str(error).startswith("model.cvq: ")


@pytest.mark.parametrize("change", [
    lambda stream: stream.update(coding="laplace", params=[0.0, 0.0]),
    lambda stream: stream.update(coding="gaussian", params=[1.0, -2.0]),
    lambda stream: stream.update(coding="laplace", params=[0.0, 1.0], max=stream["min"]),
    lambda stream: stream.update(coding="laplace", params=[0.0, 1.0], max=stream["min"] + 2**24),
    lambda stream: stream.update(coding="categorical", histogram_bytes=0, max=stream["min"] + 2**13),
    lambda stream: stream.update(bytes=stream["bytes"] + 0.5),
    lambda stream: stream.update(bytes=True),
    lambda stream: stream.update(coding="raw", width=0),
    lambda stream: stream.update(coding="raw", width=2**40),
    lambda stream: stream.update(shape="12"),
], ids=["laplace-scale-0", "gaussian-scale-negative", "laplace-one-symbol", "laplace-too-many-symbols",
        "categorical-too-many-symbols", "bytes-float", "bytes-bool", "raw-width-0", "raw-width-huge", "shape-text"])
def test_a_stream_descriptor_the_coder_cannot_take_is_refused_in_one_line(change):
    version, header, payload = parts(FILES[1])
    change(header["streams"][1])
    with pytest.raises(ModelFileError, match="^model.cvq: [^\n]*$"):
        decode(packed(version, header, payload), "model.cvq")


@pytest.mark.parametrize("span", [[-1e308, 1e308], [0.0, 1e308], [-1e300, -1e300]])
def test_ranges_that_overflow_are_refused_in_one_line_without_numpy_s_warnings(span):
    version, header, payload = parts(FILES[1])
    header["ranges"]["scale"] = span
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # NumPy's RuntimeWarning would be an exception here
        try:
            decode(packed(version, header, payload), "model.cvq")
        except ModelFileError as error:
            assert "\n" not in str(error) and str(error).startswith("model.cvq: ")
