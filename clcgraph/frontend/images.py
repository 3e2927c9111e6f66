"""Decode sensor_msgs/Image and sensor_msgs/CompressedImage into an Image.

SYNOPSIS
    img = decode_image(msg, topic="/camera/image_raw")
    img.pixels   # (H,W) uint8 / uint16 for mono, (H,W,3) uint8 BGR for colour

Raw encodings: mono8, 8UC1, mono16, 16UC1 (``is_bigendian`` honoured), rgb8, bgr8,
rgba8, bgra8, Bayer mosaics (bayer_rggb8/bggr8/gbrg8/grbg8 and their 16-bit forms, as
machine-vision drivers publish them; demosaiced), yuv422 (UYVY) and yuv422_yuy2 (YUYV, as
usb_cam publishes); ``step`` padding is skipped. Compressed: anything OpenCV's imdecode
PNG and JPEG; a mono image stays mono, alpha is dropped.
Unknown encodings and short data raise DataError naming the topic and encoding. Sizes are
checked before anything is allocated: a compressed image's dimensions are read from its
PNG / JPEG header and refused when above ``MAX_PIXELS`` or more than its bytes can encode
(deflate expands at most 1032-fold; a Huffman-coded JPEG spends at least one bit per 8x8
block); a JPEG without its end marker (truncated) or that the codec reports corrupt is a
DataError too (libjpeg would fill the missing part with grey and print to stderr).
"""

from __future__ import annotations

import os
import struct
import tempfile
import threading

import numpy as np

from ..errors import DataError
from ..types import Image
from .pointcloud import stamp_ns_of

# encoding -> (channels, numpy kind, channel permutation to BGR or None)
_RAW = {
    "mono8": (1, "u1", None),
    "8UC1": (1, "u1", None),
    "mono16": (1, "u2", None),
    "16UC1": (1, "u2", None),
    "bgr8": (3, "u1", None),
    "8UC3": (3, "u1", None),
    "rgb8": (3, "u1", [2, 1, 0]),
    "bgra8": (4, "u1", [0, 1, 2]),
    "rgba8": (4, "u1", [2, 1, 0]),
}
# Bayer / YUV encodings -> (channels, numpy kind, OpenCV conversion to BGR). OpenCV names a Bayer
# pattern by its second row's first two pixels: ROS rggb is OpenCV's BG (as cv_bridge maps it).
_CONVERTED = {
    **{f"bayer_{p}{bits}": (1, kind, f"COLOR_Bayer{cv}2BGR")
       for p, cv in (("rggb", "BG"), ("bggr", "RG"), ("gbrg", "GR"), ("grbg", "GB"))
       for bits, kind in (("8", "u1"), ("16", "u2"))},
    "yuv422": (2, "u1", "COLOR_YUV2BGR_UYVY"),
    "uyvy": (2, "u1", "COLOR_YUV2BGR_UYVY"),
    "yuv422_yuy2": (2, "u1", "COLOR_YUV2BGR_YUY2"),
    "yuyv": (2, "u1", "COLOR_YUV2BGR_YUY2"),
}


# No camera used for calibration has more pixels than this (a 100 Mpixel image is 300 MB as BGR).
MAX_PIXELS = 100_000_000
# deflate's maximum expansion (RFC 1951: 258-byte matches from 2-bit codes), with a margin
_DEFLATE_MAX_RATIO = 1040


def is_compressed(msg) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def decode_image(msg, *, topic: str) -> Image:
    """An Image from a rosbags-deserialized sensor_msgs/Image or CompressedImage.

    pixels: (H,W) uint8/uint16 for mono, (H,W,3) uint8 BGR for colour. ``encoding``
    of the result is the message's encoding (raw) or format string (compressed).
    """
    stamp_ns = stamp_ns_of(msg.header)
    if is_compressed(msg):
        return Image(topic=topic, stamp_ns=stamp_ns, pixels=_decode_compressed(msg, topic),
                     encoding=str(msg.format))
    enc = str(msg.encoding)
    if enc not in _RAW and enc not in _CONVERTED:
        raise DataError(
            f"image on {topic}: unsupported encoding {enc!r} (supported: {', '.join([*_RAW, *_CONVERTED])})"
        )
    nch, kind, perm = _RAW[enc] if enc in _RAW else _CONVERTED[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise DataError(f"image on {topic}: {enc} image of {w}x{h} pixels has no pixels")
    if enc in _CONVERTED and (w < 2 or h < 2 or (nch == 2 and w % 2)):
        raise DataError(f"image on {topic}: {enc} needs at least 2x2 pixels (an even width for YUV), got {w}x{h}")
    dt = np.dtype((">" if msg.is_bigendian else "<") + kind)
    rowbytes = w * nch * dt.itemsize
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < rowbytes or data.size < h * step:
        raise DataError(
            f"image on {topic}: {enc} {w}x{h} needs step >= {rowbytes} and {h}*step bytes; "
            f"got step {step}, {data.size} bytes"
        )
    rows = data[: h * step].reshape(h, step)[:, :rowbytes]
    px = np.ascontiguousarray(rows).view(dt).reshape(h, w, nch)
    px = px.astype(dt.newbyteorder("="), copy=False)
    if enc in _CONVERTED:
        import cv2

        px = cv2.cvtColor(np.ascontiguousarray(px[..., 0] if nch == 1 else px), getattr(cv2, perm))
        if px.dtype == np.uint16:  # colour images are uint8 here; 12-bit data in 16 bits: scale to the max
            px = (px * (255.0 / max(int(px.max()), 1))).astype(np.uint8)
        return Image(topic=topic, stamp_ns=stamp_ns, pixels=np.ascontiguousarray(px), encoding=enc)
    if nch == 1:
        px = px[..., 0]
    elif perm is not None:
        px = px[..., perm]
    return Image(topic=topic, stamp_ns=stamp_ns, pixels=np.ascontiguousarray(px), encoding=enc)


def _decode_compressed(msg, topic: str) -> np.ndarray:
    import cv2

    buf = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    what = f"image on {topic} ({msg.format!r})"
    head = bytes(buf[:8])
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        _check_png(buf, what)
    elif head.startswith(b"\xff\xd8"):
        _check_jpeg_header(buf, what)
        # decode at 1/8 scale first (1/64 of the memory): a header claiming more than the data
        # holds makes libjpeg complain here, before the full-size image is allocated
        with _codec_messages() as said:
            small = cv2.imdecode(buf, cv2.IMREAD_REDUCED_GRAYSCALE_8)
        if small is None or said:
            raise DataError(f"{what}: cannot decode ({said[0] if said else 'the codec refused it'})")
    else:
        raise DataError(f"{what}: compressed data is neither PNG nor JPEG ({buf.size} bytes)")
    with _codec_messages() as said:
        px = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if px is None or said:
        why = said[0] if said else "the codec refused it"
        raise DataError(f"{what}: cannot decode ({why})")
    if px.ndim == 3 and px.shape[2] == 4:
        px = px[..., :3]
    elif px.ndim == 3 and px.shape[2] == 1:
        px = px[..., 0]
    return np.ascontiguousarray(px)


def _check_size(w: int, h: int, what: str, most: int) -> None:
    if w <= 0 or h <= 0:
        raise DataError(f"{what}: header says {w}x{h} pixels")
    if w * h > MAX_PIXELS:
        raise DataError(f"{what}: header says {w}x{h} pixels, more than the {MAX_PIXELS // 1_000_000} Mpixel limit")
    if w * h > most:
        raise DataError(f"{what}: header says {w}x{h} pixels, more than its data can encode (lying header)")


_MAX_PNG_CHUNKS = 100_000
# Adam7 passes: (x0, y0, dx, dy)
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def _check_png(buf: np.ndarray, what: str) -> None:
    """IHDR (the first chunk) gives the size; the image must fit in what the compressed bytes can
    expand to, and the IDAT stream must inflate to exactly as many bytes as the header implies
    (counted in 1 MB pieces, never held): a lying header fails here, not inside libpng's allocation."""
    import zlib

    if buf.size < 33 or bytes(buf[12:16]) != b"IHDR":
        raise DataError(f"{what}: PNG without an IHDR header ({buf.size} bytes)")
    w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", bytes(buf[16:29]))
    bits = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour, 4) * max(depth, 1)
    passes = _ADAM7 if interlace else ((0, 0, 1, 1),)
    raw = 0
    for x0, y0, dx, dy in passes:
        pw, ph = -(-(w - x0) // dx) if w > x0 else 0, -(-(h - y0) // dy) if h > y0 else 0
        raw += ph * (1 + (pw * bits + 7) // 8) if pw else 0
    _check_size(w, h, what, w * h if raw <= _DEFLATE_MAX_RATIO * buf.size else 0)
    data, pos, inflated = buf.tobytes(), 8, 0
    z = zlib.decompressobj()
    for _ in range(_MAX_PNG_CHUNKS):
        if pos + 8 > len(data):
            break
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if kind == b"IEND":
            break
        if kind == b"IDAT":
            chunk = data[pos + 8:pos + 8 + length]
            try:
                while chunk and inflated < raw:
                    inflated += len(z.decompress(chunk, 1 << 20))
                    chunk = z.unconsumed_tail
            except zlib.error as e:
                raise DataError(f"{what}: corrupt PNG data ({e})") from None
        pos += 12 + length
    if inflated < raw:
        raise DataError(f"{what}: PNG data inflates to {inflated} bytes, its header ({w}x{h}) needs {raw} "
                        "(truncated or lying header)")


# SOF markers of Huffman-coded JPEGs (baseline, extended, progressive, lossless; not arithmetic)
_SOF_HUFFMAN = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7}
_SOF_ARITHMETIC = {0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_MAX_JPEG_SEGMENTS = 1000
_JPEG_TAIL_SLACK = 4096


def _check_jpeg_header(buf: np.ndarray, what: str) -> None:
    """The frame header (SOFn) gives the size; the data must end with EOI (not truncated)."""
    data = buf.tobytes() if buf.size < 65536 else bytes(buf[:65536])  # headers come first
    # UVC cameras (MJPEG) may pad a frame after its end marker: look for it near the end
    if b"\xff\xd9" not in bytes(buf[-_JPEG_TAIL_SLACK:]):
        raise DataError(f"{what}: JPEG without its end-of-image marker (truncated?)")
    pos = 2
    for _ in range(_MAX_JPEG_SEGMENTS):
        while pos < len(data) and data[pos] == 0xFF and pos + 1 < len(data) and data[pos + 1] == 0xFF:
            pos += 1  # fill bytes
        if pos + 4 > len(data) or data[pos] != 0xFF:
            break
        marker = data[pos + 1]
        if marker == 0xD8 or 0xD0 <= marker <= 0xD7 or marker == 0x01:
            pos += 2  # no length
            continue
        (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
        if marker in _SOF_HUFFMAN or marker in _SOF_ARITHMETIC:
            if pos + 9 > len(data):
                break
            h, w = struct.unpack(">HH", data[pos + 5:pos + 9])
            # a Huffman-coded block costs >= 1 bit (the DC code): blocks <= 8 x bytes
            most = 64 * 8 * buf.size if marker in _SOF_HUFFMAN else MAX_PIXELS
            _check_size(w, h, what, most)
            return
        if marker in (0xDA, 0xD9) or length < 2:
            break
        pos += 2 + length
    raise DataError(f"{what}: JPEG without a readable frame header (SOF)")


_STDERR_LOCK = threading.Lock()


class _codec_messages:
    """Capture what libpng / libjpeg print on file descriptor 2 while decoding: their warnings
    ("Corrupt JPEG data ...") mean wrong pixels, so they become the DataError's reason instead of
    stray lines on the user's terminal. Returns the captured lines (a list, filled on exit)."""

    def __enter__(self):
        _STDERR_LOCK.acquire()
        self.lines: list[str] = []
        self.tmp = tempfile.TemporaryFile()
        self.saved = os.dup(2)
        os.dup2(self.tmp.fileno(), 2)
        return self.lines

    def __exit__(self, *exc):
        try:
            os.dup2(self.saved, 2)
            os.close(self.saved)
            self.tmp.seek(0)
            text = self.tmp.read(4096).decode("utf-8", "replace")
            self.tmp.close()
            self.lines += [ln.strip() for ln in text.splitlines() if ln.strip()]
        finally:
            _STDERR_LOCK.release()
        return False
