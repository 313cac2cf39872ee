"""The report page's sections that say what a run is: facts, paired comparisons, protocol."""

from __future__ import annotations

from typing import Any

import pandas as pd

from harness.localizers.kinds import kind_summary
from harness.methods import METHOD_LABELS
from harness.reports.change import CHANGE_TABLES, change_table
from harness.reports.html.cells import (
    change_html,
    diff_colour,
    esc,
)
from harness.reports.render import HOLM_MARK, holm_sentence


def rank_counts_table(rank_counts: object) -> str:
    """The ranking counts of run.json as a small table.

    A row per session (per localizer and session in a run of several), a column per count:
    ``{session: {count: n}}`` or ``{localizer: {session: {count: n}}}``.
    """
    if not isinstance(rank_counts, dict) or not rank_counts:
        return "-"
    rows: list[tuple[str, dict]] = []
    for name, c in rank_counts.items():
        if isinstance(c, dict) and c and all(isinstance(v, dict) for v in c.values()):
            rows += [(f"{name} / {s}", cc) for s, cc in c.items()]  # per localizer
        elif isinstance(c, dict):
            rows.append((str(name), c))
    cols = list(dict.fromkeys(k for _, c in rows for k in c))
    head = "".join(f"<th>{esc(k.replace('_', ' '))}</th>" for k in ["session", *cols])
    body = "".join(
        f"<tr><td>{esc(who)}</td>"
        + "".join(f"<td>{esc(c.get(k, ''))}</td>" for k in cols)
        + "</tr>"
        for who, c in rows
    )
    return f'<table class="counts" data-table="rank-counts"><tr>{head}</tr>{body}</table>'


def run_facts(run: dict[str, Any], cfg: dict[str, Any]) -> tuple[str, str]:
    """The localizers' names and the rows of the page's *Run* table (config, versions, counts)."""
    counts = run["counts"]
    locs = [x for x in run.get("localizers") or [] if isinstance(x, dict)] or [
        {"name": cfg.get("descriptor", {}).get("name", "?"), "kind": "descriptor"}
    ]
    loc_name = ", ".join(str(x.get("name")) for x in locs)
    localizer_facts = "; ".join(
        f"{x.get('name')}: "
        + kind_summary(x, cfg)
        + (f", proposals {', '.join(x['proposals'])}" if x.get("proposals") else "")
        for x in locs
    )
    drops = {
        s: ", ".join(f"{k} {v}" for k, v in d.get("dropped", {}).items() if v)
        for s, d in run.get("ingest", {}).items()
    }
    facts = [
        ("config", f"{cfg['name']} ({len(cfg['sessions'])} sessions)"),
        ("data root", cfg["data_root"]),
        ("annotations", cfg["annotations"]),
        ("versions", ", ".join(f"{k} {v}" for k, v in run["versions"].items() if k != "platform")),
        ("platform", run["versions"].get("platform", "")),
        ("executor", ", ".join(f"{k} {v}" for k, v in run.get("executor", {}).items())),
        (
            "time",
            f"{run['total_s']:.1f} s: "
            + ", ".join(f"{k} {v:.1f}" for k, v in run["timings_s"].items()),
        ),
        (
            "counts",
            (
                f"{counts['frames']} frames, {counts['annotated_frames']} annotated frames, "
                f"{counts['pairs']} pairs (query images), "
                f"{counts['ranked_subimages']} ranked subimages, {counts['samples']} samples"
            ),
        ),
        ("dropped at ingest", "; ".join(f"{s}: {d}" for s, d in drops.items() if d) or "nothing"),
        ("localizer", localizer_facts),
    ]
    fact_rows = "".join(f"<tr><td>{esc(k)}</td><td>{esc(v)}</td></tr>" for k, v in facts)
    fact_rows += f"<tr><td>ranking</td><td>{rank_counts_table(counts.get('rank_counts'))}</td></tr>"
    return loc_name, fact_rows


def comparisons_html(summ: pd.DataFrame, methods: tuple[str, ...]) -> str:
    """The section of paired comparisons: AP(method) - AP(rank fusion), per table and split.

    Each difference with its bootstrap interval, coloured by it, and Holm's mark where it holds.
    """
    cmp_rows = summ[
        (summ["proposal_method"] == "all") & (summ["season_pair"] == "all") & summ["diff"].notna()
    ]
    cmp_html = ""
    for table in ("S", "P", "I"):  # the fair tables first, the paper's protocol last
        t = cmp_rows[cmp_rows["table"] == table]
        if not len(t):
            continue
        d = t.pivot(index="fusion", columns="split", values="diff").reindex(
            [m for m in methods if m in set(t["fusion"])]
        )
        lo = t.pivot(index="fusion", columns="split", values="diff_ci_low").reindex(d.index)
        hi = t.pivot(index="fusion", columns="split", values="diff_ci_high").reindex(d.index)
        kept = (
            t.pivot(index="fusion", columns="split", values="holm_survives")
            .reindex(d.index)
            .fillna(False)
            .astype(bool)
            if "holm_survives" in t.columns
            else d.notna() & False
        )
        cols = [c for c in t["split"].drop_duplicates()]
        head = "".join(f"<th>{esc(c)}</th>" for c in cols)
        diffs = "".join(
            f"<tr><td>{esc(METHOD_LABELS[m])} &minus; rank fusion</td>"
            + "".join(
                f'<td style="background:{diff_colour(lo.loc[m, c], hi.loc[m, c])}"'
                + (' data-holm="1"' if kept.loc[m, c] else "")
                + f">{d.loc[m, c]:+.2f} "
                f'<span class="ci">[{lo.loc[m, c]:+.2f}, {hi.loc[m, c]:+.2f}]</span>'
                + (f" <b>{esc(HOLM_MARK)}</b>" if kept.loc[m, c] else "")
                + "</td>"
                for c in cols
            )
            + "</tr>"
            for m in d.index
        )
        cmp_html += (
            f"<h3>{esc(CHANGE_TABLES[table].title)}</h3>"
            f'<p class="note">{esc(holm_sentence(t, CHANGE_TABLES[table].title))}</p><table '
            f'data-table="cmp{table}"><tr><th>difference</th>{head}</tr>{diffs}</table>'
        )
    return (
        '<h2 id="comparisons">Paired comparisons with rank fusion</h2><p '
        'class="note">AP(method) &minus; AP(rank fusion) over the same '
        "bootstrap resamples of query images, with its 95% interval; green: better than "
        "rank fusion, red: worse, white: cannot be told apart "
        "on this data.</p>" + cmp_html
    )


def protocol_section(
    summ: pd.DataFrame,
    methods: tuple[str, ...],
    lines: list[str],
    who: str,
    heat: str,
    pr_i: str,
    gallery_i: str,
) -> str:
    """The paper's protocol (Table I) at the end of the page, collapsed, with its warnings."""
    confound = [w for w in lines if w.startswith("WARNING")]
    notes_i = [w for w in lines if not w.startswith("WARNING")]
    protocol = (
        '<h2 id="protocol">The paper\'s protocol (Table I): read it last</h2>'
        "<p class='note'>Table I labels a box positive when it is at least 90% inside a change "
        "<i>and</i> at most 40% of the image, negative when it is at most RoC-max changed "
        "<i>and</i> at least 40% of the image: box size alone can separate the labels, so its "
        "APs measure box size as much as change. It is here to compare with the paper's "
        "numbers, not to compare detectors (Table S does that).</p>"
        + "".join(f'<div class="warn">{esc(w)}</div>' for w in confound)
        + "<details><summary>Table I, its PR curve, AP per season pair and worst cases "
        "under its labels</summary>"
        + change_html(change_table(summ, "I", methods, notes_i), who)
        + f'<div class="grid pr" id="prI">{pr_i}</div>'
        + heat
        + gallery_i
        + "</details>"
    )
    return protocol
