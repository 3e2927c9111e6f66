"""Decode sensor_msgs/Image and sensor_msgs/CompressedImage into an Image.

SYNOPSIS
    img = decode_image(msg, topic="/camera/image_raw")
    img.pixels   # (H,W) uint8 / uint16 for mono, (H,W,3) uint8 BGR for colour

Raw encodings: mono8, 8UC1, mono16, 16UC1 (``is_bigendian`` honoured), rgb8, bgr8,
rgba8, bgra8, Bayer mosaics (bayer_rggb8/bggr8/gbrg8/grbg8 and their 16-bit forms, as
machine-vision drivers publish them; demosaiced), yuv422 (UYVY) and yuv422_yuy2 (YUYV, as
usb_cam publishes); ``step`` padding is skipped. Compressed: anything OpenCV's imdecode
reads (jpeg, png); a mono image stays mono, alpha is dropped.
Unknown encodings and short data raise DataError naming the topic and encoding.
"""

from __future__ import annotations

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
    px = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if px is None:
        raise DataError(f"image on {topic}: cannot decode compressed format {msg.format!r}")
    if px.ndim == 3 and px.shape[2] == 4:
        px = px[..., :3]
    elif px.ndim == 3 and px.shape[2] == 1:
        px = px[..., 0]
    return np.ascontiguousarray(px)
