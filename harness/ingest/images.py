"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` messages into image-store files."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image as PILImage

from harness.errors import IngestError
from harness.imagestore import check_pixels, header_size

# : ROS bayer encodings -> OpenCV conversion (OpenCV names the pattern by the second row; as
# cv_bridge does).
BAYER = {
    "bayer_rggb8": cv2.COLOR_BayerBG2BGR,
    "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg8": cv2.COLOR_BayerGR2BGR,
    "bayer_grbg8": cv2.COLOR_BayerGB2BGR,
    "bayer_rggb16": cv2.COLOR_BayerBG2BGR,
    "bayer_bggr16": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg16": cv2.COLOR_BayerGR2BGR,
    "bayer_grbg16": cv2.COLOR_BayerGB2BGR,
}
ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", *BAYER)


def raw_to_array(msg: Any, where: str) -> np.ndarray:
    """Decode a ``sensor_msgs/Image`` into an OpenCV-layout array.

    BGR, BGRA or gray; uint8 or uint16.

    Bayer images are demosaiced. Row padding (``step``) and big-endian 16-bit data are handled.

    Raises:
        IngestError: Unknown encoding or a data size that does not match width, height and step.
    """
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if enc not in ENCODINGS:
        raise IngestError(
            f"{where}: unsupported image encoding {msg.encoding!r}; supported: "
            f"{', '.join(ENCODINGS)}"
        )
    if h <= 0 or w <= 0:
        raise IngestError(f"{where}: image has zero size ({w}x{h})")
    check_pixels(w, h, where)
    if data.size < h * step:
        raise IngestError(
            f"{where}: image data has {data.size} bytes, expected height*step = {h}*{step}"
        )
    chans = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "mono16": 1}.get(enc, 1)
    bpc = 2 if enc.endswith("16") else 1
    if step < w * chans * bpc:
        raise IngestError(
            f"{where}: step {step} is smaller than width*channels*bytes = {w * chans * bpc}"
        )
    rows = data[: h * step].reshape(h, step)[:, : w * chans * bpc]
    arr: np.ndarray
    if bpc == 2:
        dt = ">u2" if int(msg.is_bigendian) else "<u2"
        arr = np.ascontiguousarray(rows).view(dt).astype(np.uint16).reshape(h, w, chans)
    else:
        arr = np.ascontiguousarray(rows).reshape(h, w, chans)
    if enc == "rgb8":
        return cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    if enc == "rgba8":
        return cv2.cvtColor(arr, cv2.COLOR_RGBA2BGRA)
    if enc in ("bgr8", "bgra8"):
        return arr
    if enc in BAYER:
        return cv2.cvtColor(arr[..., 0], BAYER[enc])
    return arr[..., 0]


def compressed_kind(msg: Any, where: str) -> str:
    """``jpg`` or ``png`` from a CompressedImage's ``format`` string (checked against the bytes)."""
    fmt = str(msg.format).lower()
    data = bytes(np.asarray(msg.data, dtype=np.uint8)[:8])
    if data.startswith(b"\xff\xd8"):
        kind = "jpg"
    elif data.startswith(b"\x89PNG"):
        kind = "png"
    else:
        raise IngestError(
            f"{where}: compressed image format {fmt!r} is neither JPEG nor PNG (first bytes "
            f"{data!r})"
        )
    return kind


def compressed_size(data: bytes, where: str) -> tuple[int, int]:
    """(width, height) from a JPEG or PNG header, without decoding the pixels.

    Raises:
        IngestError: An unreadable header, or a declared size over ``max_image_pixels``.
    """
    return header_size(io.BytesIO(data), where)


def decode_problem(data: bytes) -> str | None:
    """Why a JPEG or PNG does not decode in full (truncated body, bad data), or None when it does.

    The header alone (all that ingest reads by default) says nothing about the body; this decodes
    every pixel, with truncated images treated as errors.
    """
    if data.startswith(b"\xff\xd8") and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        return "JPEG body is truncated (no end-of-image marker)"
    try:
        with PILImage.open(io.BytesIO(data)) as im:
            im.load()
    except (OSError, ValueError, SyntaxError, PILImage.DecompressionBombError) as err:
        return f"image does not decode: {err}"
    return None


STORE_FORMATS = {
    # uncompressed TIFF: ~1 ms per 640x480 frame to write, 0.5 ms to read; PNG: 1.5x smaller, ~16x
    # slower
    "tiff": (".tiff", [cv2.IMWRITE_TIFF_COMPRESSION, 1]),
    "png": (".png", [cv2.IMWRITE_PNG_COMPRESSION, 1]),
}


def write_raw(path: Path, arr: np.ndarray, fmt: str = "tiff") -> Path:
    """Write a decoded raw image losslessly (16-bit gray stays 16-bit).

    Returns the path with its suffix.
    """
    ext, params = STORE_FORMATS[fmt]
    path = path.with_suffix(ext)
    if not cv2.imwrite(str(path), arr, params):
        raise IngestError(f"{path}: could not write image")
    return path
