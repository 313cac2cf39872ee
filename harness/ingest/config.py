"""The ingest stage's config: ``[[sessions]]``, ``[ingest]`` and ``[masks]``, and their checks."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from harness.checks import check_value, is_finite
from harness.errors import ConfigError


@dataclass(frozen=True)
class SessionConfig:
    """One season log.

    ``source`` is an NCLT root, a ``.bag``, a ROS2 bag directory or an ``.mcap``.
    """

    # the session's name (letters, digits, - and _), as commands and tables name it
    name: str
    # an NCLT root, a .bag, a ROS2 bag directory, an .mcap or a folder of images
    source: str
    # WI, SP, SU or AU (empty: from the name's month, as NCLT names sessions)
    season: str = ""
    # the log format: auto (by the source), nclt, ros1, ros2, mcap or images
    format: str = "auto"
    # the camera the frames come from (NCLT: Cam0-Cam5; a log: the name its frames carry)
    camera: str = "Cam5"
    # the image topic of a bag or MCAP (unset: the only one there is)
    image_topic: str | None = None
    # the pose or odometry topic (unset: the only one there is, or /tf)
    pose_topic: str | None = None
    tf_child_frame: str | None = None  # older name of camera_frame: the frame whose pose /tf gives
    # /tf: the frame poses are expressed in (default: the tree's root)
    fixed_frame: str | None = None
    # /tf: the camera's frame (default: the images' header.frame_id)
    camera_frame: str | None = None


@dataclass(frozen=True)
class IngestConfig:
    """``[ingest]``: how logs become frames (times in seconds)."""

    # the largest image a header may declare (width x height): larger is a decompression bomb
    max_image_pixels: int = 100_000_000
    # pose topics and fast /tf transforms: a sample at most this before and after an image
    max_pose_gap_s: float = 0.1
    # /tf transforms published more slowly than max_pose_gap_s (map -> odom at 1-10 Hz)
    max_tf_gap_s: float = 1.0
    time_source: str = "header"  # header stamp of the image message, or "log" (bag receive time)
    nclt_rotation: str = "cw"  # how NCLT's stored images are turned upright: cw, ccw, none
    salvage: bool = False  # keep the messages read before a truncated or corrupt part
    # lossless image store for raw images from logs: tiff (fast) or png (smaller)
    store_format: str = "tiff"
    # decode every compressed image in full at ingest; drop and count broken ones
    verify_images: bool = False


@dataclass(frozen=True)
class MasksConfig:
    """``[masks]``: change masks as annotations (method §13.2).

    ``folder``: one 0/255 image per annotated image of a folder session, named like it; its
    8-connected components of at least ``min_mask_area`` pixels are change boxes, an all-zero
    mask a no-change image.
    """

    # change masks as annotations: one 0/255 image per annotated image of a folder session, named
    # like it (harness detect --masks overrides it)
    folder: str | None = None
    # the smallest mask component, pixels, that becomes a change box
    min_mask_area: int = 16


#: A session name is a directory name under ``--out``: letters, digits, ``.``, ``_``, ``-``, not
#: starting with a dot (so never ``..``, never a path).
SESSION_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def check_session_name(name: object, where: str) -> str:
    """A session (or camera) name that is safe as one directory or file name under ``--out``.

    Raises:
        ConfigError: The name is not a string, or holds a path separator, starts with a dot or
            another character outside letters, digits, ``.``, ``_`` and ``-``.
    """
    if not isinstance(name, str) or not SESSION_NAME.match(name):
        raise ConfigError(
            f"{where} = {name!r}: it names a directory or file the harness writes under --out, "
            "so it must be letters, digits, '.', '_' or '-', not start with '.' or '-', and "
            "hold no '/'"
        )
    return name


def check_ingest(ig: Any, where: str, flags: dict[str, str] | None = None) -> None:
    """The ingest options' ranges, for ``[ingest]`` and for ``harness ingest``'s flags alike.

    ``flags`` names each field's command-line flag, so that a flag's error names the flag.
    """
    name = {
        k: (flags or {}).get(k, f"[ingest] {k}")
        for k in ("max_pose_gap_s", "max_tf_gap_s", "max_image_pixels")
    }
    for key in ("max_pose_gap_s", "max_tf_gap_s"):
        v = getattr(ig, key)
        check_value(is_finite(v) and v > 0, where, name[key], v, "> 0 seconds, finite")
    check_value(
        ig.max_image_pixels >= 1,
        where,
        name["max_image_pixels"],
        ig.max_image_pixels,
        ">= 1",
    )


def check_ingest_section(ig: IngestConfig, where: str) -> None:
    """``[ingest]``: the gaps and limits (:func:`check_ingest`), time source, storage, rotation."""
    c = check_value
    check_ingest(ig, where)
    c(
        ig.time_source in ("header", "log"),
        where,
        "[ingest] time_source",
        ig.time_source,
        "'header' or 'log'",
    )
    c(
        ig.store_format in ("tiff", "png"),
        where,
        "[ingest] store_format",
        ig.store_format,
        "'tiff' or 'png'",
    )
    c(
        ig.nclt_rotation in ("cw", "ccw", "none"),
        where,
        "[ingest] nclt_rotation",
        ig.nclt_rotation,
        "cw, ccw or none",
    )


def check_masks(mk: MasksConfig, where: str) -> None:
    """``[masks]``: the smallest change region a mask gives."""
    check_value(
        mk.min_mask_area >= 1, where, "[masks] min_mask_area", mk.min_mask_area, ">= 1 pixel"
    )
