"""The localizers' config: ``[[localizers]]`` entries, the local localizer's table, checks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from harness.checks import check_value
from harness.descriptors.config import DescriptorConfig
from harness.retrieval.config import BovwConfig

#: The name of the cross-localizer block (method §11).
ALL_LOCALIZERS = "all localizers"


#: The alignment chain's links, in the order they are usually tried.
ALIGNERS = ("homography", "ecc", "identity")


FEATURE_IMAGES = ("gradient", "gray")


KEYPOINTS = ("orb", "sift")


@dataclass(frozen=True)
class LocalConfig:
    """A ``local`` localizer's options (method §13.3, :mod:`harness.localizers.local`).

    ``[[localizers]] local = {...}`` or ``[detect.local]``.
    """

    # the alignment chain, tried in order; a pair none of them accepts is "not aligned"
    align: tuple[str, ...] = ("homography", "identity")
    # the homography's local features: "orb" (measured as good as SIFT here, and cheaper) or "sift"
    keypoints: str = "orb"
    # keypoints a frame at most for the alignment's feature matching
    max_keypoints: int = 800
    # a homography is accepted with at least this many RANSAC inliers ...
    min_inliers: int = 12
    # ... and a plausible warp: no frame corner moves more than this share of the frame diagonal
    max_corner_shift: float = 0.35
    # ECC's correlation (enhanced correlation coefficient) at which its affine fit is accepted
    ecc_min_cc: float = 0.6
    # identity is accepted where the two work images correlate at least this much (an overlap)
    identity_min_ncc: float = 0.0
    # the image matched: "gradient" (Sobel magnitude, robust to light and season) or "gray"
    image: str = "gradient"
    # the search window: the box grown by this share of its width / height on each side ...
    grow: float = 0.25
    # the least growth of a template, work pixels
    min_grow_px: int = 4
    # ... and the tolerance around the expected position: this share of the frame's diagonal
    # (what alignment leaves scales with the frame), at least min_tolerance_px ...
    tolerance: float = 0.015
    # the least search tolerance, work pixels
    min_tolerance_px: int = 1
    # ... and the window grows at least this many tolerances on each side
    window_over_tolerance: int = 1
    # also match the map's patch in the query frame and keep the worse rank (removed objects)
    both_directions: bool = True
    # frames whose longer side exceeds this are worked on at 1/2, 1/4 or 1/8 of their size
    work_side: int = 400
    # ... and aligned on a pyramid level whose longer side is at most this
    align_side: int = 320
    # a box whose shorter side exceeds this is matched on a coarser pyramid level (halved until
    # it is not): the resolution the box needs, not more
    max_template_px: int = 32
    # query frames per cached unit (the unit a killed run resumes at); not in the key
    frames_per_unit: int = 64


#: Keypoint localization's features and geometry (docs/decisions.md, *Keypoint localization*).
KEYPOINT_FEATURES = ("sift", "orb", "akaze")
GEOMETRIES = ("fundamental", "homography")


@dataclass(frozen=True)
class KeypointConfig:
    """A ``keypoints`` localizer's options (:mod:`harness.localizers.keypoints`).

    ``[[localizers]] keypoints = {...}`` or ``[detect.keypoints]``. Every size is a share of the
    frame's diagonal, so one setting serves every frame size.
    """

    # the local features: "sift" (the measured default), "orb" or "akaze" (cheaper)
    features: str = "sift"
    # keypoints a frame at most (the strongest kept)
    max_keypoints: int = 1500
    # Lowe's ratio test, both ways (query to map and map to query)
    ratio: float = 0.8
    # the pair's geometry a match must agree with: "fundamental" (parallax keeps it) or
    # "homography" (a scene declared planar: aerial tiles, a wall)
    geometry: str = "fundamental"
    # MAGSAC's inlier threshold, a share of the frame's diagonal (at least half a pixel)
    ransac_threshold: float = 0.004
    # fewer ratio-test matches than this: no geometry is fitted and every match localizes
    min_matches: int = 15
    # the share map's Gaussian, sigma a share of the frame's diagonal ...
    sigma: float = 0.03
    # ... and its prior: this many localized keypoints' worth, so a bare box is no change
    prior: float = 1.0
    # also the map's keypoints that do not localize in the query frame (a removed object)
    both_directions: bool = True
    # frames are worked on with this longer side, at most (1/2, 1/4, 1/8 decodes of a JPEG)
    work_side: int = 512
    # query frames per cached unit (the unit a killed run resumes at); not in the key
    frames_per_unit: int = 64
    # the rank list's length: r = rank / L with rank = 1 + round(share * (L - 1))
    levels: int = 1000


def check_keypoints(kc: KeypointConfig, where: str) -> KeypointConfig:
    """A ``keypoints`` table's values (one ``ERROR:`` line naming the key)."""
    c = check_value
    c(
        kc.features in KEYPOINT_FEATURES,
        where,
        "features",
        kc.features,
        ", ".join(KEYPOINT_FEATURES),
    )
    c(kc.geometry in GEOMETRIES, where, "geometry", kc.geometry, " or ".join(GEOMETRIES))
    c(kc.max_keypoints >= 8, where, "max_keypoints", kc.max_keypoints, ">= 8")
    c(0 < kc.ratio <= 1, where, "ratio", kc.ratio, "(0, 1]")
    c(0 < kc.ransac_threshold < 0.1, where, "ransac_threshold", kc.ransac_threshold,
      "(0, 0.1): a share of the frame's diagonal")  # fmt: skip
    c(kc.min_matches >= 8, where, "min_matches", kc.min_matches, ">= 8 (a fundamental matrix)")
    c(0 < kc.sigma < 0.5, where, "sigma", kc.sigma, "(0, 0.5): a share of the frame's diagonal")
    c(kc.prior > 0, where, "prior", kc.prior, "> 0 keypoints")
    c(kc.work_side >= 64, where, "work_side", kc.work_side, ">= 64 pixels")
    c(kc.frames_per_unit >= 1, where, "frames_per_unit", kc.frames_per_unit, ">= 1")
    c(kc.levels >= 2, where, "levels", kc.levels, ">= 2")
    return kc


@dataclass(frozen=True)
class LocalizerImportConfig:
    """A localizer's ``import`` table: ranked lists from a file (method §12)."""

    # the ranked lists: a CSV or parquet file of query subimage, map frame, score
    file: str
    # distance (smaller is more similar) or similarity (in [0, 1])
    score_kind: str = "distance"


@dataclass(frozen=True)
class LocalizerConfig:
    """One ``[[localizers]]`` entry (method §11): a name, proposals and one way to rank.

    ``kind`` names a :data:`harness.localizers.kinds.LOCALIZER_KINDS` record and ``options`` is its
    sub-table (a ``DescriptorConfig``, ``BovwConfig``, ``LocalizerImportConfig`` or a registered
    kind's dataclass); ``proposals`` are the ``[proposals] methods`` it uses (all by default).
    """

    # the localizer's name in Table L and the page
    name: str
    # descriptor, bovw, import, local or keypoints: the sub-table that holds its options
    kind: str
    # the proposal methods whose subimages it ranks
    proposals: tuple[str, ...]
    # the kind's own table (descriptor = {...}, bovw = {...}, ...), below
    options: Any = None

    @property
    def descriptor(self) -> DescriptorConfig | None:
        """The options of a ``descriptor`` localizer, else None."""
        return self.options if self.kind == "descriptor" else None

    @property
    def bovw(self) -> BovwConfig | None:
        """The options of a ``bovw`` localizer, else None."""
        return self.options if self.kind == "bovw" else None

    @property
    def import_(self) -> LocalizerImportConfig | None:
        """The options of an ``import`` localizer, else None."""
        return self.options if self.kind == "import" else None


def check_local(lc: LocalConfig, where: str) -> LocalConfig:
    """``lc`` unchanged, after checking every option (one ConfigError naming the first bad one)."""
    check_value(
        len(lc.align) > 0 and all(a in ALIGNERS for a in lc.align)
        and len(set(lc.align)) == len(lc.align),
        where, "align", list(lc.align), f"a chain of distinct {', '.join(ALIGNERS)}",
    )  # fmt: skip
    check_value(lc.keypoints in KEYPOINTS, where, "keypoints", lc.keypoints, " or ".join(KEYPOINTS))
    check_value(lc.image in FEATURE_IMAGES, where, "image", lc.image, " or ".join(FEATURE_IMAGES))
    check_value(lc.max_keypoints >= 50, where, "max_keypoints", lc.max_keypoints, ">= 50")
    check_value(lc.min_inliers >= 4, where, "min_inliers", lc.min_inliers, ">= 4")
    check_value(
        0 < lc.max_corner_shift <= 1, where, "max_corner_shift", lc.max_corner_shift, "(0, 1]"
    )
    check_value(-1 <= lc.ecc_min_cc <= 1, where, "ecc_min_cc", lc.ecc_min_cc, "[-1, 1]")
    check_value(
        -1 <= lc.identity_min_ncc <= 1, where, "identity_min_ncc", lc.identity_min_ncc, "[-1, 1]"
    )
    check_value(0 <= lc.grow <= 4, where, "grow", lc.grow, "[0, 4]")
    check_value(lc.min_grow_px >= 1, where, "min_grow_px", lc.min_grow_px, ">= 1")
    check_value(0 <= lc.tolerance <= 1, where, "tolerance", lc.tolerance, "[0, 1]")
    check_value(lc.min_tolerance_px >= 0, where, "min_tolerance_px", lc.min_tolerance_px, ">= 0")
    check_value(
        lc.window_over_tolerance >= 1,
        where,
        "window_over_tolerance",
        lc.window_over_tolerance,
        ">= 1",
    )
    check_value(lc.work_side >= 32, where, "work_side", lc.work_side, ">= 32")
    check_value(lc.align_side >= 32, where, "align_side", lc.align_side, ">= 32")
    check_value(lc.max_template_px >= 4, where, "max_template_px", lc.max_template_px, ">= 4")
    check_value(lc.frames_per_unit >= 1, where, "frames_per_unit", lc.frames_per_unit, ">= 1")
    return lc
