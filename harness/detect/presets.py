"""Whole detectors by name: ``harness detect --preset NAME`` (docs/detect.md, *Presets*).

A preset is a set of ``[detect]`` values; a flag typed beside it wins over the preset's value, and
the preset over the config's. The names are the detectors the manual measures.
"""

from __future__ import annotations

from typing import Any

#: name -> (what it is, the ``[detect]`` values it sets)
PRESETS: dict[str, tuple[str, dict[str, Any]]] = {
    "default": (
        "registration, the plain difference and keypoint localization of Selective Search's "
        "boxes (the defaults, chosen on real revisits)",
        {
            "localizer": "keypoints",
            "proposals": "selective",
            "boxes": "subimages",
            "box_prior": "difference_product",
            "localization_weight": 4.0,
        },
    ),
    "paper": (
        "the paper's detector: each proposal ranked against the whole map by the config's "
        "localizers, the fused qBBs as boxes, scored by their LoC alone",
        {"localizer": "config", "boxes": "fused", "box_prior": "none"},
    ),
    "local": (
        "each colour region ranked inside its paired map frame by NCC, with the area prior",
        {"localizer": "local", "proposals": "segments", "boxes": "subimages", "box_prior": "area"},
    ),
}


def preset_help() -> str:
    """The ``--preset`` flag's help: each name and what it is."""
    return "; ".join(f"{k}: {v[0]}" for k, v in PRESETS.items())
