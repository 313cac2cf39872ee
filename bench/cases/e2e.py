"""Bench case ``e2e``."""

from __future__ import annotations

import json
import shutil

from .common import (
    ROOT,
    STAGES,
    fit_exponent,
    nclt_scale_workload,
    peak_rss_mib,
    reproduce_subprocess,
)


def case_e2e(quick: bool) -> None:
    """End-to-end Table I (``harness reproduce``, nothing cached) on the NCLT-scale workload, at
    several frame counts per session; per-stage times and their growth with the frame count.

    Each run is its own process; its peak RSS comes from ``os.wait4`` (that process and the
    data-loader workers it waited for).
    """

    counts = (24, 48) if quick else (125, 250, 500)
    stage_t: dict[str, list[float]] = {s: [] for s in STAGES}
    totals = []
    for n in counts:
        root = nclt_scale_workload(n)
        out, run, usage, wall = reproduce_subprocess(
            ROOT / "bench" / "nclt_scale.toml", root, "e2e-"
        )
        shutil.rmtree(out)
        t = run["timings_s"]
        for s_ in STAGES:
            stage_t[s_].append(max(float(t.get(s_, 0.0)), 1e-3))
        totals.append(wall)
        c = run["counts"]
        # (query frame, reference session) pairs: one Table I query image each
        q_images = c["pairs"]
        ranked = c["ranked_subimages"]
        eval_s = t.get("samples", 0.0) + t.get("labels_ap_reports", 0.0)
        print(
            json.dumps(
                {
                    "case": f"e2e Table I [{n} frames/session]",
                    "median": wall,
                    "unit": "s",
                    "runs": [wall],
                    "peak_rss_mib": usage.ru_maxrss / 1024,
                    "ms_per_query_image": round(1000 * wall / max(q_images, 1), 1),
                    "ms_per_frame": round(1000 * wall / c["frames"], 1),
                    "fusion_labels_ap_share": round(eval_s / wall, 4),
                    "notes": (
                        f"{c['frames']} frames 1232x1616 JPEG, {q_images} query images "
                        f"({c['annotated_frames']} annotated frames x reference sessions), "
                        f"{ranked} ranked subimages; stages s: "
                        + ", ".join(f"{k} {t.get(k, 0):.1f}" for k in STAGES)
                    ),
                }
            ),
            flush=True,
        )
    for s_ in STAGES:
        print(
            json.dumps(
                {
                    "case": f"scaling: {s_} time vs frames per session",
                    "median": fit_exponent(list(counts), stage_t[s_]),
                    "unit": "exponent",
                    "runs": [],
                    "peak_rss_mib": peak_rss_mib(),
                    "points": {
                        "x": list(counts),
                        "y": stage_t[s_],
                        "xlabel": "frames per session",
                        "ylabel": "s",
                    },
                }
            ),
            flush=True,
        )
    print(
        json.dumps(
            {
                "case": "scaling: end-to-end time vs frames per session",
                "median": fit_exponent(list(counts), totals),
                "unit": "exponent",
                "runs": [],
                "peak_rss_mib": peak_rss_mib(),
                "points": {
                    "x": list(counts),
                    "y": totals,
                    "xlabel": "frames per session",
                    "ylabel": "s",
                },
            }
        ),
        flush=True,
    )
