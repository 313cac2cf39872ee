"""Reading frame images by URI.

A frame's ``image`` is a path (absolute, or relative to the directory of the frame table that
holds it) with an optional fragment that says how to turn the stored image upright:
``#rot=cw``, ``#rot=ccw`` or ``#rot=180``. NCLT's rotated TIFFs are referenced in place this way;
images from logs live in the ingest output's image store (PNG for raw images, the original JPEG
or PNG bytes for compressed ones).
"""

from __future__ import annotations

import contextlib
import io
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from harness.errors import IngestError
from harness.perturb import PERTURB, Perturbation
from harness.perturb import apply as apply_perturbation
from harness.perturb import parse as parse_perturbation

_ROT = {"cw": cv2.ROTATE_90_CLOCKWISE, "ccw": cv2.ROTATE_90_COUNTERCLOCKWISE, "180": cv2.ROTATE_180}


ROTATIONS = ("cw", "ccw", "180")
_ROT_MARK = "#rot="


@dataclass(frozen=True)
class ImageRef:
    """A frame's image as a URI names it: ``PATH[#rot=R][#perturb=...]``, read and written here.

    ``path``: the file (any characters, a ``#`` and spaces included); ``rotation``: how to turn
    the stored image upright (``none``, ``cw``, ``ccw``, ``180``); ``perturbation``: a perturbed
    copy's values as its fragment spells them (:func:`harness.perturb.fragment`; None: the
    image itself). Only those two trailing fragments are fragments: a ``#`` anywhere else
    belongs to the path.
    """

    path: str
    rotation: str = "none"
    perturbation: str | None = None

    @classmethod
    def parse(cls, uri: str | Path) -> ImageRef:
        """The reference a URI names (its inverse: :attr:`uri`)."""
        text = str(uri)
        base, sep, spec = text.rpartition(PERTURB)
        if not sep:
            base = text
        path, mark, rot = base.rpartition(_ROT_MARK)
        if not (mark and rot in ROTATIONS):
            path, rot = base, "none"
        return cls(path, rot, spec if sep else None)

    @property
    def fragment(self) -> str:
        """What follows the path: the rotation's and the perturbation's fragments."""
        rot = "" if self.rotation in ("none", "") else f"{_ROT_MARK}{self.rotation}"
        return rot + (f"{PERTURB}{self.perturbation}" if self.perturbation is not None else "")

    @property
    def uri(self) -> str:
        """The URI, as frame tables hold it."""
        return self.path + self.fragment

    @property
    def name(self) -> str:
        """The file's name (what a folder's frame is named by)."""
        return Path(self.path).name

    @property
    def perturbed(self) -> Perturbation | None:
        """The perturbed copy's values (None: the image itself).

        Raises:
            ValueError: the fragment names no values (an unknown part, no number, none at all).
        """
        return None if self.perturbation is None else parse_perturbation(self.perturbation)


def make_uri(path: str | Path, rotation: str = "none") -> str:
    """An image URI from a path and a turn-upright rotation (``none``, ``cw``, ``ccw``, ``180``)."""
    return ImageRef(str(path), rotation or "none").uri


def split_uri(uri: str) -> tuple[str, str]:
    """(path, rotation) of a URI (:class:`ImageRef`); a perturbed copy's whole URI is its path."""
    ref = ImageRef.parse(uri)
    return (str(uri), "none") if ref.perturbation is not None else (ref.path, ref.rotation)


#: Prefixes of the image URIs that cached frame tables hold, so a run directory or a data root
#: can move: ``{out}/...`` is relative to the run directory, ``{data_root}/...`` to the data.
OUT_PREFIX, DATA_PREFIX = "{out}/", "{data_root}/"


def portable_uri(uri: str, out: Path, data_root: Path) -> str:
    """An absolute URI made relative to ``out`` or ``data_root`` where it lies under one of them."""
    path, rot = split_uri(uri)
    p = Path(path)
    for base, prefix in (
        (Path(out).resolve(), OUT_PREFIX),
        (Path(data_root).resolve(), DATA_PREFIX),
    ):
        if p.is_relative_to(base):
            return make_uri(prefix + p.relative_to(base).as_posix(), rot)
    return uri


def local_uri(uri: str, out: Path, data_root: Path) -> str:
    """The inverse of :func:`portable_uri` for this run's ``out`` and ``data_root``."""
    if uri.startswith(OUT_PREFIX):
        return str(Path(out).resolve()) + "/" + uri[len(OUT_PREFIX) :]
    if uri.startswith(DATA_PREFIX):
        return str(Path(data_root).resolve()) + "/" + uri[len(DATA_PREFIX) :]
    return uri


def resolve(uri: str, base: Path) -> str:
    """Make a relative URI absolute against ``base`` (the frame table's directory)."""
    path, rot = split_uri(uri)
    p = Path(path)
    if not p.is_absolute():
        p = (base / p).resolve()
    return make_uri(p, rot)


def upright_size(stored_w: int, stored_h: int, rotation: str) -> tuple[int, int]:
    """(width, height) of the upright image, pixels, from the stored size and its rotation."""
    return (stored_h, stored_w) if rotation in ("cw", "ccw") else (stored_w, stored_h)


#: The largest image (width x height) a header may declare: a larger one is a decompression bomb
#: (a few bytes that would decode to gigabytes). ``[ingest] max_image_pixels`` sets it.
MAX_IMAGE_PIXELS = 100_000_000


@contextlib.contextmanager
def pixel_limit(limit: int) -> Iterator[None]:
    """:data:`MAX_IMAGE_PIXELS` set to ``limit`` for the block (an ingest, from its config)."""
    global MAX_IMAGE_PIXELS
    saved, MAX_IMAGE_PIXELS = MAX_IMAGE_PIXELS, int(limit)
    try:
        yield
    finally:
        MAX_IMAGE_PIXELS = saved


def check_pixels(w: int, h: int, where: str) -> tuple[int, int]:
    """``(w, h)`` when the declared size is within :data:`MAX_IMAGE_PIXELS`.

    Raises:
        IngestError: Naming the image, the declared size and the limit.
    """
    if int(w) * int(h) > MAX_IMAGE_PIXELS:
        raise IngestError(
            f"{where}: the image declares {w} x {h} = {int(w) * int(h):,} pixels, over "
            f"[ingest] max_image_pixels = {MAX_IMAGE_PIXELS:,} (a decompression bomb, or a real "
            "image that large: raise the limit)"
        )
    return int(w), int(h)


def header_size(source: str | Path | io.BytesIO, where: str) -> tuple[int, int]:
    """(width, height) from an image header (a file or bytes), never decoding the pixels.

    Raises:
        IngestError: The header is unreadable, or declares more than :data:`MAX_IMAGE_PIXELS`.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                with Image.open(source) as im:
                    w, h = im.size
            finally:
                Image.MAX_IMAGE_PIXELS = saved
    except PermissionError:
        raise IngestError(f"{where}: not readable (permission denied)") from None
    except (OSError, ValueError, SyntaxError) as err:
        raise IngestError(f"{where}: cannot read image header: {err}") from None
    return check_pixels(w, h, where)


def stored_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    return header_size(path, str(path))


def to_rgb8(img: np.ndarray) -> np.ndarray:
    """Any decoded OpenCV image (gray, BGR, BGRA; 8 or 16 bit) to RGB uint8."""
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


#: Reduced JPEG decoding: libjpeg's DCT scaling gives 1/2, 1/4 or 1/8 of the frame for less work.
_REDUCED = {  # EXIF orientation ignored, as IMREAD_UNCHANGED does
    f: flag | cv2.IMREAD_IGNORE_ORIENTATION
    for f, flag in (
        (2, cv2.IMREAD_REDUCED_COLOR_2),
        (4, cv2.IMREAD_REDUCED_COLOR_4),
        (8, cv2.IMREAD_REDUCED_COLOR_8),
    )
}


def read_image(uri: str, reduce: int = 1) -> np.ndarray:
    """Decode an image URI to an upright RGB uint8 array ``(H, W, 3)``.

    ``reduce`` (1, 2, 4 or 8): the image at that fraction of its size, ``ceil(H / reduce)`` x
    ``ceil(W / reduce)``: a JPEG decoded at that scale (less work than the full frame), any other
    file decoded whole and shrunk once with area interpolation.

    A URI that ends in ``#perturb=...`` is a perturbed copy of the image before it
    (:mod:`harness.perturb`), made as it is read.

    Raises:
        IngestError: The file is missing or cannot be decoded.
    """
    ref = ImageRef.parse(uri)
    if ref.perturbation is not None:
        try:
            perturbation = parse_perturbation(ref.perturbation)
        except ValueError as err:  # a path whose name holds "#perturb=" and no drawn values
            raise IngestError(f"{uri}: {err}") from None
        original = ImageRef(ref.path, ref.rotation).uri
        return apply_perturbation(read_image(original, reduce), perturbation)
    path, rot = ref.path, ref.rotation
    jpeg = reduce > 1 and path.lower().endswith((".jpg", ".jpeg"))
    img = cv2.imread(path, _REDUCED[reduce] if jpeg else cv2.IMREAD_UNCHANGED)
    if img is None:
        raise IngestError(f"{path}: missing or not a decodable image")
    rgb = to_rgb8(img)
    if reduce > 1 and not jpeg:
        h, w = rgb.shape[:2]
        size = (-(-w // reduce), -(-h // reduce))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    if rot in _ROT:
        rgb = cv2.rotate(rgb, _ROT[rot])
    return np.ascontiguousarray(rgb)
