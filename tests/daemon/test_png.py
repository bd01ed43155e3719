"""The snapshots' 16-bit PNGs (`nhfd.daemon.png`, OpenCV's encoder): what decoders read back is
exactly the 16-bit values the writer was given, grey and colour, big-endian in the file, and the
file replaced atomically."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image

from nhfd.daemon.png import PNG16_MAX, to_uint16, write_png16
from nhfd.demos.serve import read_png16


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, out = 8, []
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        out.append((data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]))
        pos += 12 + n
    return out


def _decoders(path) -> list[np.ndarray]:
    """The file as uint16 through Pillow, OpenCV and the demo's own unfiltered-row reader."""
    with Image.open(path) as im:
        pil = np.asarray(im)
    cv = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    demo = np.round(read_png16(path) * PNG16_MAX).astype(np.uint16)
    return [pil, cv, demo]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_seeded_uint16_values_round_trip_exactly(tmp_path, dtype):
    want = np.random.default_rng(11).integers(0, PNG16_MAX + 1, (41, 67), dtype=np.uint16)
    want[0, :2] = 0, PNG16_MAX  # both ends of the range
    path = tmp_path / "grey.png"
    write_png16(path, (want / PNG16_MAX).astype(dtype))
    for got in _decoders(path):
        assert got.dtype == np.uint16 and got.shape == want.shape
        assert np.array_equal(got, want)
    # 16-bit greyscale, and the samples big-endian as PNG requires (libpng swaps them).
    chunks = _chunks(path.read_bytes())
    (ihdr,) = [body for kind, body in chunks if kind == b"IHDR"]
    assert struct.unpack(">IIBBBBB", ihdr) == (67, 41, 16, 0, 0, 0, 0)
    raw = zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8).reshape(41, 1 + 2 * 67)
    assert not rows[:, 0].any()  # unfiltered rows
    assert np.array_equal(rows[:, 1:].copy().view(">u2"), want)


def test_a_random_float_image_is_stored_rounded_to_16_bits(tmp_path):
    image = np.random.default_rng(12).random((37, 53))
    path = tmp_path / "f.png"
    write_png16(path, image)
    want = np.round(image * PNG16_MAX).astype(np.uint16)
    for got in _decoders(path):
        assert np.array_equal(got, want)


def test_a_colour_capture_is_stored_as_the_channel_mean(tmp_path):
    image = np.random.default_rng(13).random((3, 29, 31))  # [C, H, W]
    path = tmp_path / "c.png"
    write_png16(path, image)
    want = np.round(image.mean(axis=0) * PNG16_MAX).astype(np.uint16)
    assert np.array_equal(to_uint16(image), want)
    for got in _decoders(path):
        assert got.shape == (29, 31) and np.array_equal(got, want)


def test_nan_inf_and_out_of_range_values_are_clipped_not_refused(tmp_path):
    # The hand-written encoder's behaviour, kept: a snapshot of a bad frame is still written.
    image = np.full((2, 4), 0.5)
    image[0] = np.nan, np.inf, -np.inf, -0.25
    image[1, :2] = 1.5, -1e300
    path = tmp_path / "bad.png"
    write_png16(path, image)
    want = np.array([[0, PNG16_MAX, 0, 0], [PNG16_MAX, 0, 32768, 32768]], np.uint16)
    for got in _decoders(path):
        assert np.array_equal(got, want)


def test_the_file_is_replaced_atomically_and_its_folder_made(tmp_path):
    path = tmp_path / "new" / "folder" / "snap.png"
    write_png16(path, np.zeros((4, 4)))
    write_png16(path, np.ones((5, 6)))  # over the old one
    assert sorted(p.name for p in path.parent.iterdir()) == ["snap.png"]  # no temporary left
    for got in _decoders(path):
        assert np.array_equal(got, np.full((5, 6), PNG16_MAX, np.uint16))


@pytest.mark.parametrize("shape", [(5,), (0, 4), (2, 3, 4, 5)])
def test_what_is_not_an_image_is_refused_naming_its_shape(tmp_path, shape):
    with pytest.raises(ValueError, match=str(shape).replace("(", r"\(").replace(")", r"\)")):
        write_png16(tmp_path / "x.png", np.zeros(shape))
    assert not list(tmp_path.iterdir())
