"""Image / CompressedImage decoding: encodings, step padding, endianness, compression."""

from types import SimpleNamespace

import struct
import tracemalloc

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
    msg = _raw(np.zeros((2, 2), np.float32), "32FC1")  # a depth image is not a camera for us
    with pytest.raises(DataError) as e:
        decode_image(msg, topic="/cam/raw")
    s = str(e.value)
    assert "\n" not in s and "32FC1" in s and "/cam/raw" in s


def test_short_data_and_undecodable_compressed():
    msg = _raw(np.zeros((4, 4), np.uint8), "mono8")
    msg.data = msg.data[:5]
    with pytest.raises(DataError, match="/cam"):
        decode_image(msg, topic="/cam")
    bad = SimpleNamespace(header=HEADER, format="jpeg", data=np.arange(50, dtype=np.uint8))
    with pytest.raises(DataError, match="neither PNG nor JPEG"):
        decode_image(bad, topic="/cam")


def _compressed(ext, px):
    return SimpleNamespace(header=HEADER, format=ext.lstrip("."), data=cv2.imencode(ext, px)[1].reshape(-1))


def _set_jpeg_size(data, w, h):
    d = data.copy()
    sof = next(i for i in range(2, len(d) - 1) if d[i] == 0xFF and d[i + 1] in (0xC0, 0xC2))
    d[sof + 5:sof + 9] = np.frombuffer(struct.pack(">HH", h, w), np.uint8)
    return d


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_lying_compressed_header_is_refused_before_decoding(ext):
    """A small image whose header claims 30000x30000 (or 4000x3000 in 3 KB): DataError from the header,
    with no big allocation; the genuine image still decodes."""
    px = np.random.default_rng(5).integers(0, 256, (48, 64), dtype=np.uint8)
    msg = _compressed(ext, px)
    assert decode_image(msg, topic="/c").pixels.shape == (48, 64)
    for w, h, why in ((30000, 30000, "100 Mpixel limit"), (4000, 3000, "its data can encode")):
        d = msg.data.copy()
        if ext == ".png":
            d[16:24] = np.frombuffer(struct.pack(">II", w, h), np.uint8)
        else:
            d = _set_jpeg_size(d, w, h)
        tracemalloc.start()
        with pytest.raises(DataError, match=f"/c.*{w}x{h} pixels, more than .*{why}"):
            decode_image(SimpleNamespace(header=HEADER, format=msg.format, data=d), topic="/c")
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < 1_000_000


def test_truncated_and_corrupt_jpeg_are_errors_not_grey(capfd):
    px = np.random.default_rng(6).integers(0, 256, (64, 80, 3), dtype=np.uint8)
    msg = _compressed(".jpg", px)
    with pytest.raises(DataError, match="end-of-image marker"):
        decode_image(SimpleNamespace(header=HEADER, format="jpeg", data=msg.data[: len(msg.data) // 2]), topic="/c")
    padded = np.r_[msg.data, np.zeros(1000, np.uint8)]  # as UVC cameras pad MJPEG frames
    assert decode_image(SimpleNamespace(header=HEADER, format="jpeg", data=padded), topic="/c").pixels.shape == px.shape
    d = msg.data.copy()
    d[len(d) // 2:len(d) // 2 + 40] = 0xFF  # fill bytes inside the entropy-coded data
    d[len(d) // 2 + 40] = 0xD0
    with pytest.raises(DataError, match=r"/c.*cannot decode \(Corrupt JPEG data"):
        decode_image(SimpleNamespace(header=HEADER, format="jpeg", data=d), topic="/c")
    assert capfd.readouterr().err == ""  # libjpeg's complaints never reach the terminal


def test_empty_raw_image_and_odd_yuv_width():
    msg = _raw(np.zeros((4, 4), np.uint8), "mono8")
    msg.width = 0
    with pytest.raises(DataError, match="0x4 pixels has no pixels"):
        decode_image(msg, topic="/cam")
    yuv = _raw(np.zeros((4, 6), np.uint8), "yuv422")
    yuv.width = 3
    with pytest.raises(DataError, match="even width"):
        decode_image(yuv, topic="/cam")


def _mosaic(bgr, pattern):
    """The Bayer mosaic a camera with ``pattern`` (e.g. "rggb": row 0 = R G, row 1 = G B) records."""
    idx = {"r": 2, "g": 1, "b": 0}
    out = np.zeros(bgr.shape[:2], bgr.dtype)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        out[dy::2, dx::2] = bgr[dy::2, dx::2, idx[pattern[k]]]
    return out


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize("bits", [8, 16])
def test_bayer_mosaics_demosaic_to_the_right_colours(pattern, bits):
    # a flat colour with different R, G, B: any pattern mix-up swaps channels
    colour = np.array([40, 120, 220])  # B, G, R
    scale = 16 if bits == 16 else 1  # 12-bit data in 16 bits
    bgr = np.broadcast_to(colour * scale, (16, 20, 3)).astype(np.uint16 if bits == 16 else np.uint8)
    img = decode_image(_raw(_mosaic(bgr, pattern), f"bayer_{pattern}{bits}", pad=2), topic="/c")
    assert img.pixels.shape == (16, 20, 3) and img.pixels.dtype == np.uint8
    inner = img.pixels[2:-2, 2:-2].reshape(-1, 3).mean(axis=0)
    expect = colour if bits == 8 else colour * 255.0 / 220  # 16-bit: scaled to the image's maximum
    np.testing.assert_allclose(inner, expect, atol=2)


@pytest.mark.parametrize("enc", ["yuv422", "yuv422_yuy2"])
def test_yuv422_packed_to_bgr(enc):
    # no chroma (U = V = 128), Y = 150 packed in the encoding's byte order; video-range BT.601
    # gives 1.164 * (150 - 16) = 156 in every channel; reading the other order would give ~130
    h, w, y = 6, 8, 150
    quad = [128, y, 128, y] if enc == "yuv422" else [y, 128, y, 128]  # UYVY / YUY2
    packed = np.tile(np.array(quad, np.uint8), (h, w // 2)).reshape(h, w, 2)
    img = decode_image(_raw(packed, enc), topic="/c")
    assert img.pixels.shape == (h, w, 3)
    np.testing.assert_allclose(img.pixels.astype(float), 1.164 * (y - 16), atol=2)
