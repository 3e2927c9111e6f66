"""Image / CompressedImage decoding: encodings, step padding, endianness, compression."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from clcgraph.errors import DataError
from clcgraph.frontend.images import decode_image

HEADER = SimpleNamespace(stamp=SimpleNamespace(sec=12, nanosec=345), frame_id="cam")


def _raw(px, encoding, *, pad=0, big=False):
    h, w = px.shape[:2]
    b = px.astype(px.dtype.newbyteorder(">" if big else "<")).tobytes()
    rowbytes = len(b) // h
    buf = np.full((h, rowbytes + pad), 0x5A, np.uint8)
    buf[:, :rowbytes] = np.frombuffer(b, np.uint8).reshape(h, rowbytes)
    return SimpleNamespace(header=HEADER, height=h, width=w, encoding=encoding,
                           is_bigendian=int(big), step=rowbytes + pad, data=buf.reshape(-1))


@pytest.fixture
def bgr():
    return np.random.default_rng(3).integers(0, 256, (5, 7, 3), dtype=np.uint8)


@pytest.mark.parametrize("pad", [0, 3])
def test_colour_encodings_to_bgr(bgr, pad):
    alpha = np.full((5, 7, 1), 9, np.uint8)
    cases = {
        "bgr8": bgr,
        "rgb8": bgr[..., ::-1],
        "bgra8": np.concatenate([bgr, alpha], axis=2),
        "rgba8": np.concatenate([bgr[..., ::-1], alpha], axis=2),
    }
    for enc, px in cases.items():
        img = decode_image(_raw(np.ascontiguousarray(px), enc, pad=pad), topic="/c")
        assert img.pixels.shape == (5, 7, 3) and img.pixels.dtype == np.uint8, enc
        np.testing.assert_array_equal(img.pixels, bgr, err_msg=enc)
        assert img.encoding == enc and img.stamp_ns == 12_000_000_345


@pytest.mark.parametrize("enc", ["mono8", "8UC1"])
def test_mono8(enc):
    px = np.arange(35, dtype=np.uint8).reshape(5, 7)
    img = decode_image(_raw(px, enc, pad=1), topic="/m")
    np.testing.assert_array_equal(img.pixels, px)


@pytest.mark.parametrize("enc", ["mono16", "16UC1"])
@pytest.mark.parametrize("big", [False, True])
def test_mono16_endianness(enc, big):
    px = (np.arange(35, dtype=np.uint16) * 1871).reshape(5, 7)
    img = decode_image(_raw(px, enc, pad=2, big=big), topic="/m16")
    assert img.pixels.dtype == np.uint16
    np.testing.assert_array_equal(img.pixels, px)


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_compressed(fmt):
    # smooth colour gradients: what jpeg is meant for
    y, x = np.mgrid[0:50, 0:70]
    big = np.stack([x * 3, y * 4, 255 - x * 2], axis=-1).astype(np.uint8)
    mono = cv2.cvtColor(big, cv2.COLOR_BGR2GRAY)
    for px in (big, mono):
        ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", px, [cv2.IMWRITE_JPEG_QUALITY, 95])
        msg = SimpleNamespace(header=HEADER, format=fmt, data=buf.reshape(-1))
        img = decode_image(msg, topic="/cc")
        assert img.pixels.shape == px.shape
        err = np.abs(img.pixels.astype(int) - px.astype(int))
        if fmt == "png":
            assert err.max() == 0
        else:
            assert err.mean() < 2 and err.max() < 20, (err.mean(), err.max())


def test_unknown_encoding_names_it():
    msg = _raw(np.zeros((2, 2), np.uint8), "bayer_rggb8")
    with pytest.raises(DataError) as e:
        decode_image(msg, topic="/cam/raw")
    s = str(e.value)
    assert "\n" not in s and "bayer_rggb8" in s and "/cam/raw" in s


def test_short_data_and_undecodable_compressed():
    msg = _raw(np.zeros((4, 4), np.uint8), "mono8")
    msg.data = msg.data[:5]
    with pytest.raises(DataError, match="/cam"):
        decode_image(msg, topic="/cam")
    bad = SimpleNamespace(header=HEADER, format="jpeg", data=np.arange(50, dtype=np.uint8))
    with pytest.raises(DataError, match="cannot decode compressed"):
        decode_image(bad, topic="/cam")
