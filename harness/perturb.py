"""Perturbed copies of a frame: the same scene, nothing changed, as a camera might see it again.

``harness detect``'s no-change null (docs/decisions.md, *Calibrated alarms*) pairs a map frame with
a perturbed copy of itself where the map is no sequence. A copy is one draw of every
perturbation within stated limits: photometric gain and offset, a shift, a rotation and a scale
(one affine warp, borders reflected), a Gaussian blur and a JPEG re-encoding. Sizes are shares
of the frame (the shift of its width and height, the blur of its longer side), so a limit means
the same on a thumbnail and on a full frame.

A drawn copy is named by an image URI fragment, ``#perturb=g1.05,o-3,x0.01,...``, holding the
drawn values themselves (:func:`fragment`), so that :func:`harness.imagestore.read_image` makes
it wherever the frame is read and no file is written.
"""

from __future__ import annotations

import zlib
from dataclasses import astuple, dataclass, fields
from typing import Any

import cv2
import numpy as np

#: The fragment that marks a perturbed copy in an image URI (after any ``#rot=``).
PERTURB = "#perturb="


@dataclass(frozen=True)
class Perturbation:
    """One drawn copy: each value applied as it stands (:func:`apply`)."""

    gain: float = 1.0  # intensity multiplied by it
    offset: float = 0.0  # then this many grey levels added
    dx: float = 0.0  # shift, a share of the width
    dy: float = 0.0  # shift, a share of the height
    rotation_deg: float = 0.0  # about the centre
    scale: float = 1.0  # about the centre
    blur: float = 0.0  # Gaussian sigma, a share of the longer side (0: none)
    jpeg: int = 0  # re-encoded at this JPEG quality (0: not re-encoded)
    # a smooth displacement of this RMS, a share of the diagonal (0: none): the parallax a
    # homography leaves, as a real revisit shows it (its field drawn from the other values)
    wobble: float = 0.0


_TAGS = ("g", "o", "x", "y", "r", "s", "b", "q", "w")


def fragment(p: Perturbation) -> str:
    """The URI fragment naming ``p``: ``#perturb=g1.05,o-3,...`` (values at 6 digits)."""
    parts = [f"{t}{v:.6g}" for t, v in zip(_TAGS, astuple(p), strict=True)]
    # no wobble, no w tag: such a copy keeps its name
    return PERTURB + ",".join(parts if p.wobble else parts[:-1])


def parse(spec: str) -> Perturbation:
    """The :class:`Perturbation` a fragment's value (after ``#perturb=``) names.

    Raises:
        ValueError: a part without a known tag or number.
    """
    values: dict[str, Any] = {}
    names = [f.name for f in fields(Perturbation)]
    for part in spec.split(","):
        if not part or part[0] not in _TAGS:
            raise ValueError(f"perturbation {spec!r}: unknown part {part!r}")
        name = names[_TAGS.index(part[0])]
        try:
            values[name] = int(float(part[1:])) if name == "jpeg" else float(part[1:])
        except ValueError:
            raise ValueError(f"perturbation {spec!r}: {part!r} is not a number") from None
    if values.get("wobble", 0.0) < 0:
        raise ValueError(f"perturbation {spec!r}: wobble {values['wobble']} must be >= 0")
    return Perturbation(**values)


def _wobbled(img: np.ndarray, p: Perturbation) -> np.ndarray:
    """``img`` displaced by a smooth random field of RMS ``p.wobble`` x the diagonal.

    The field: normal draws on a 5 x 7 grid (seeded by the copy's own fragment, so a copy is the
    same wherever it is read), cubic-upsampled to the frame; borders reflected.
    """
    h, w = img.shape[:2]
    rng = np.random.default_rng(zlib.crc32(fragment(p).encode()))
    grid = rng.standard_normal((2, 5, 7)).astype(np.float32)
    fx, fy = (cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC) for g in grid)
    rms = float(np.sqrt((fx * fx + fy * fy).mean())) + 1e-9
    k = p.wobble * float(np.hypot(h, w)) / rms
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(img, xs + k * fx, ys + k * fy, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)  # fmt: skip


def apply(img: np.ndarray, p: Perturbation) -> np.ndarray:
    """``img`` (RGB uint8) perturbed by ``p``: photometric, then the warp, the blur, the JPEG."""
    h, w = img.shape[:2]
    out = np.clip(img.astype(np.float32) * p.gain + p.offset, 0, 255).astype(np.uint8)
    if p.dx or p.dy or p.rotation_deg or p.scale != 1.0:
        m = cv2.getRotationMatrix2D((w / 2.0, h / 2.0), p.rotation_deg, p.scale)
        m[0, 2] += p.dx * w
        m[1, 2] += p.dy * h
        out = cv2.warpAffine(out, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    if p.wobble > 0:
        out = _wobbled(out, p)
    if p.blur > 0:
        out = cv2.GaussianBlur(out, (0, 0), max(p.blur * max(h, w), 1e-3))
    if p.jpeg > 0:
        ok, buf = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(p.jpeg)])
        back = cv2.imdecode(buf, cv2.IMREAD_COLOR) if ok else None
        if back is not None:
            out = np.ascontiguousarray(back[..., ::-1])
    return out
