"""A proposer with an option: one box, the image's central share ``frac``.

A plugin: then ``[proposals] methods`` may list ``centre`` and ``[proposals.centre]`` set ``frac``.
"""

from dataclasses import dataclass

import numpy as np

from harness.proposals import register_proposer


@dataclass(frozen=True)
class Centre:
    """``[proposals.centre]``."""

    frac: float = 0.25  # the box's side, as a share of the image's


def centre(rgb, cfg):
    """One box (x1, y1, x2, y2 pixels of the upright image), score 1."""
    h, w = rgb.shape[:2]
    f = cfg.options_of("centre").frac
    box = [w * (1 - f) / 2, h * (1 - f) / 2, w * (1 + f) / 2, h * (1 + f) / 2]
    return np.array([box]), np.ones(1)


register_proposer("centre", centre, options=Centre)
