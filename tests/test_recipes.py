"""docs/architecture.md's "Where to add" recipes, each done for a toy case."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from harness.runner import Pipeline


def test_recipe_a_toy_descriptor_in_under_30_lines(
    local_run: tuple, tmp_path: Path, monkeypatch
) -> None:
    # --- the recipe: subclass Descriptor, implement encode, register it, select it by name ---
    from harness.descriptors import REGISTRY, Descriptor

    class MeanColour(Descriptor):
        """The crop's mean RGB and its 2x2 block means (15 dims)."""

        name = "mean_colour"

        def encode(self, crops: np.ndarray) -> np.ndarray:
            c = crops.astype(np.float32) / 255
            h, w = c.shape[1] // 2, c.shape[2] // 2
            blocks = [
                c[:, i * h : (i + 1) * h, j * w : (j + 1) * w].mean((1, 2))
                for i in (0, 1)
                for j in (0, 1)
            ]
            return np.concatenate([c.mean((1, 2)), *blocks], axis=1)

    monkeypatch.setitem(REGISTRY, "mean_colour", MeanColour)
    p, _, out = local_run
    cfg = dataclasses.replace(
        p.cfg, descriptor=dataclasses.replace(p.cfg.descriptor, name="mean_colour")
    )
    # --- end of the recipe (the rest checks it) ---
    shutil.copytree(out / "cache", tmp_path / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    q = Pipeline(cfg, tmp_path)
    rec = q.run()
    assert (
        q.ran.get("proposals", 0) == 0 and q.ran["descriptor_shards"] > 0
    )  # only what depends on it reran
    key = rec["cache_entries"]["descriptors"][0]
    assert np.load(tmp_path / "cache" / "descriptors" / key / "desc.npy").shape[1] == 15
    loc = pd.read_csv(tmp_path / "localization.csv")
    assert (
        loc["subimages"].max() > 0
        and 0 < loc.loc[loc["proposals"] == "all", "recall_at_1"].iloc[0] < 1
    )
    assert (tmp_path / "table1.csv").exists()
