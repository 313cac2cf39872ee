"""Figures: precision-recall curves per split and LoC maps like the paper's Fig. 4."""

from __future__ import annotations

from pathlib import Path

import matplotlib

from harness.records import FRAME_KEY, IMAGE_KEY

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from harness.fusion.fuse import loc_map
from harness.imagestore import read_image
from harness.methods import FUSION_METHODS
from harness.runtime.cache import atomic_path

FIG4 = ("rank_fusion", "score_sum", "score_max")


def _save(fig: plt.Figure, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)


def pr_figure(curves: pd.DataFrame, path: Path, title: str) -> Path:
    """One PNG of the PR curves of ``curves`` (columns method, precision, recall)."""
    fig, ax = plt.subplots(figsize=(5, 4))
    cmap = plt.get_cmap("tab10")
    for i, (m, gm) in enumerate(curves.groupby("fusion", sort=False)):
        ax.step(gm["recall"], gm["precision"], where="post", label=m, lw=1.4, color=cmap(i % 10))
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    return path


def pr_plots(curves: pd.DataFrame, out: Path) -> list[Path]:
    """One PNG of PR curves per split; returns the paths written."""
    written = []
    for split, g in curves.groupby("split", sort=True):
        fig, ax = plt.subplots(figsize=(5, 4))
        cmap = plt.get_cmap("tab20")
        for i, (m, gm) in enumerate(g.groupby("fusion", sort=False)):
            extra = m not in FUSION_METHODS  # variants and baselines: dashed
            ax.step(
                gm["recall"],
                gm["precision"],
                where="post",
                label=m,
                lw=1.0 if extra else 1.4,
                ls="--" if extra else "-",
                color=cmap(i % 20),
            )
        ax.set_xlabel("recall")
        ax.set_ylabel("precision")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.set_title(f"PR curves, {split}")
        ax.legend(fontsize=7)
        fig.tight_layout()
        _save(fig, out / f"pr_{split}.png")
        written.append(out / f"pr_{split}.png")
    return written


def locmap_figures(
    samples: pd.DataFrame, frames: pd.DataFrame, ann: pd.DataFrame, out: Path, n: int
) -> list[Path]:
    """LoC-map figures of the ``n`` query images with the largest change.

    Panels: input | rank fusion | score sum | score max (those of them that were computed), with the
    annotated change boxes; LoC arrays saved as ``.npy`` beside the PNG. Returns the paths written.
    """
    written: list[Path] = []
    shown = [m for m in FIG4 if f"loc_{m}" in samples.columns]
    if n <= 0 or not len(samples) or not shown:
        return written
    allp = samples[samples["proposal_method"] == "all"]
    chg = ann[ann["status"] == "change"]
    # the query images with the largest annotated change first (ties: key order)
    area = (
        chg.assign(area=(chg["x2"] - chg["x1"]) * (chg["y2"] - chg["y1"]))
        .groupby(FRAME_KEY, as_index=False)["area"]
        .sum()
    )
    keys = allp[IMAGE_KEY].drop_duplicates()
    keys = keys.merge(
        area.rename(columns={"session": "q_session", "camera": "q_camera", "utime": "q_utime"})
    )
    keys = keys.sort_values(
        ["area", "q_session", "q_utime", "r_session"], ascending=[False, True, True, True]
    )
    fr = frames.set_index(FRAME_KEY)
    for k in keys.head(n).itertuples(index=False):
        g = allp[
            (allp["q_session"] == k.q_session)
            & (allp["q_utime"] == k.q_utime)
            & (allp["r_session"] == k.r_session)
            & (allp["q_camera"] == k.q_camera)
        ]
        f = fr.loc[(k.q_session, k.q_camera, k.q_utime)]
        img = read_image(f["image"])
        w, h = int(f["width"]), int(f["height"])
        fused = g[g[f"loc_{shown[0]}"].notna()]
        boxes = fused[["x1", "y1", "x2", "y2"]].to_numpy()
        name = f"{k.q_session}_{k.q_utime}_vs_{k.r_session}"
        fig, axes = plt.subplots(1, 1 + len(shown), figsize=(2.5 * (1 + len(shown)), 3.6))
        axes[0].imshow(img)
        axes[0].set_title("input", fontsize=9)
        for b in chg[(chg["session"] == k.q_session) & (chg["utime"] == k.q_utime)][
            ["x1", "y1", "x2", "y2"]
        ].to_numpy():
            axes[0].add_patch(
                plt.Rectangle((b[0], b[1]), b[2] - b[0], b[3] - b[1], fill=False, ec="red", lw=1.5)
            )
        for ax, m in zip(axes[1:], shown, strict=True):
            lm = loc_map(boxes, fused[f"loc_{m}"].to_numpy(), w, h)
            out.mkdir(parents=True, exist_ok=True)
            with atomic_path(out / f"{name}_{m}.npy") as tmp, open(tmp, "wb") as fh:
                np.save(fh, lm)
            written.append(out / f"{name}_{m}.npy")
            valid = lm[np.isfinite(lm)]
            # rank the map's values so that the colour scale reads "more changed = brighter" for
            # every method
            ax.imshow(img, alpha=0.35)
            im = ax.imshow(
                lm,
                cmap="inferno",
                alpha=0.75,
                vmin=float(valid.min()) if len(valid) else 0,
                vmax=float(valid.max()) if len(valid) else 1,
            )
            ax.set_title(m.replace("_", " "), fontsize=9)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        for ax in axes:
            ax.set_axis_off()
        fig.suptitle(f"{k.q_session} {k.q_utime} vs {k.r_session}", fontsize=9)
        fig.tight_layout()
        _save(fig, out / f"{name}.png")
        written.append(out / f"{name}.png")
    return written
