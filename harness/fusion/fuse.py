"""Fusion of subimage ranks into sample LoC values (method §7).

Also the per-image sample table and pixel-wise LoC maps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from harness.errors import ConfigError
from harness.fusion import rules  # noqa: F401  (attaches the built-in rules' functions)
from harness.fusion.config import FusionConfig
from harness.methods import (
    FUSION_OPTIONS,
    FUSION_RULES,
    FusionRule,
    add_rule,
    is_unfused,
    known_fusion_methods,
    rules_where,
)
from harness.runtime.cache import source_fingerprints

#: Baselines computed from the image rather than the ranks.
IMAGE_BASELINES = rules_where(kind="image")

#: A fused-set method's LoC from the cover matrix: (cover (m, n) bool, r (n,) = rank / L,
#: d (n,) L2 distances, L (n,) list lengths) -> (m,) LoC, higher = more likely changed.
CoverLoc = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def register_fusion_rule(
    name: str,
    loc: CoverLoc,
    label: str,
    *,
    needs_score: bool = False,
    across: bool = True,
    detect: bool = True,
    options: type | None = None,
) -> None:
    """Add a fused-set fusion method, computed and reported when ``[fusion] methods`` lists it.

    It is reported after method §7's methods under ``label``; its source is part of the
    samples' cache key, so editing it recomputes them. The same catalogue record as the paper's
    rules (``harness.methods.FusionRule``): ``needs_score`` (it reads ``d``: a localizer without
    scores does not get it), ``across`` (it is defined on the box list of all localizers) and
    ``detect`` (``harness detect --fusion`` may use it). ``options``, a dataclass, is its
    ``[fusion.<name>]`` table (unknown keys and wrong types rejected at load, part of the
    samples' key); the function then takes it as the keyword ``options``. Register before the
    config loads.

    Raises:
        ValueError: ``name`` is taken (a key of ``[fusion]`` itself too), or ``options`` is not a
            dataclass.
    """
    if name in {f.name for f in dataclasses.fields(FusionConfig)}:
        raise ValueError(f"fusion method {name!r} exists: a key of [fusion] itself")
    if options is not None and not dataclasses.is_dataclass(options):
        raise ValueError(f"fusion method {name!r}: options must be a dataclass")
    kwargs: tuple[str, ...] = ("options",) if options is not None else ()
    add_rule(
        FusionRule(
            name,
            label,
            needs_score=needs_score,
            across=across,
            detect=detect,
            options=kwargs,
            loc=loc,
        )
    )
    if options is not None:
        FUSION_OPTIONS.add(name, options)


known_methods = known_fusion_methods


def rule_fingerprints(methods: Iterable[str]) -> dict[str, str]:
    """The source hash of each listed method registered from outside the package."""
    registry = {n: r.loc for n, r in FUSION_RULES.items() if r.loc is not None}
    return source_fingerprints(registry, methods)


#: Originals up to which :func:`intersection_closure` intersects them one pair at a time in
#: Python: the paper's five fixed boxes close in 0.23 ms this way, 0.43 ms by the bit tables
#: (measured; fusing a frame of them took 1.4 ms in all, 0.85 ms with this).
SMALL_CLOSURE = 8


def _small_closure(ranks: np.ndarray, max_boxes: int | None) -> tuple[np.ndarray, bool]:
    """:func:`intersection_closure`'s rounds on a few originals' ranks (n, 4), box by box.

    The same rounds: each new box of the last round intersected with every original it overlaps
    with positive area, the boxes not seen before kept in order (a cap keeps the first), until a
    round finds none. Returns the ranks of every box found, sorted, and whether it was capped.
    """
    orig = [(int(a), int(b), int(c), int(d)) for a, b, c, d in ranks]
    seen, frontier, capped = set(orig), orig, False
    while frontier:
        new = {
            (max(a, p), max(b, q), min(c, u), min(d, v))
            for a, b, c, d in frontier
            for p, q, u, v in orig
            if max(a, p) < min(c, u) and max(b, q) < min(d, v)
        }
        fresh = sorted(new - seen)
        if max_boxes is not None and len(seen) + len(fresh) > max_boxes:
            fresh, capped = fresh[: max(0, max_boxes - len(seen))], True
        seen.update(fresh)
        frontier = fresh
        if capped:
            break
    return np.array(sorted(seen), np.int64).reshape(-1, 4), capped


def intersection_closure(
    boxes: np.ndarray, max_boxes: int | None = None
) -> tuple[np.ndarray, bool]:
    """The closure of ``boxes`` under pairwise intersection (positive area, duplicates merged).

    Semi-naive fixed point: each round intersects only the boxes found in the previous round
    with the originals, since every intersection of a subset is reachable one original at a
    time. Cost is O(|closure| x n) instead of re-scanning all pairs every round. Each coordinate
    of an intersection is one of the originals' (a max of their x1s, a min of their x2s), so the
    rounds work on ranks: of the x coordinates (x1 and x2 together) and of the y coordinates.
    Which originals overlap a box, and which contain it (their intersection is the box itself),
    are read from bit tables of the originals by rank, so only the new intersections are made;
    a box is one integer key whose order is the boxes' lexicographic order, so duplicates and
    boxes already found are dropped by sorting keys. About 35 ms for the 305 Selective Search
    boxes of a 320 x 240 frame (about 14,000 boxes out).

    Returns:
        (unique boxes sorted lexicographically (m, 4), capped) where ``capped`` says the closure
        was cut at ``max_boxes``.
    """
    orig = np.unique(np.asarray(boxes, np.float64).reshape(-1, 4), axis=0)
    orig = orig[(orig[:, 2] > orig[:, 0]) & (orig[:, 3] > orig[:, 1])]
    xs, ys = np.unique(orig[:, [0, 2]]), np.unique(orig[:, [1, 3]])
    rx, ry = len(xs), len(ys)
    axes = (xs, ys, xs, ys)
    ranks = np.stack([np.searchsorted(axes[k], orig[:, k]) for k in range(4)], 1)
    n = len(ranks)
    if n <= SMALL_CLOSURE:
        found, capped = _small_closure(ranks, max_boxes)
        return np.stack([axes[k][found[:, k]] for k in range(4)], 1).reshape(-1, 4), capped

    def table(col: np.ndarray, size: int, below: bool) -> np.ndarray:
        """Row v: the originals whose rank ``col`` is below v (``below``), else above v."""
        v = np.arange(size + 1)[:, None]
        out: np.ndarray = np.packbits(col[None, :] < v if below else col[None, :] > v, axis=1)
        return out

    lx1, gx2 = table(ranks[:, 0], rx, True), table(ranks[:, 2], rx, False)
    ly1, gy2 = table(ranks[:, 1], ry, True), table(ranks[:, 3], ry, False)

    def key(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
        out: np.ndarray = ((a.astype(np.int64) * ry + b) * rx + c) * ry + d
        return out

    def unkey(k: np.ndarray) -> np.ndarray:
        k, d = np.divmod(k, ry)
        k, c = np.divmod(k, rx)
        a, b = np.divmod(k, ry)
        return np.stack([a, b, c, d], 1)

    seen = key(*ranks.T)  # sorted: the originals are
    parts, frontier, capped = [seen], ranks, False
    while len(frontier):
        a, b, c, d = frontier.T
        bits = lx1[c] & gx2[a] & ly1[d] & gy2[b]  # the originals it overlaps
        bits &= ~(lx1[a + 1] & gx2[c - 1] & ly1[b + 1] & gy2[d - 1])  # less those holding it
        i, j = np.nonzero(np.unpackbits(bits, axis=1, count=n))
        o = ranks[j]
        x1, y1 = np.maximum(a[i], o[:, 0]), np.maximum(b[i], o[:, 1])
        x2, y2 = np.minimum(c[i], o[:, 2]), np.minimum(d[i], o[:, 3])
        keys = np.unique(key(x1, y1, x2, y2))  # each box once
        keys = keys[~np.isin(keys, seen, assume_unique=True)]
        if max_boxes is not None and len(seen) + len(keys) > max_boxes:
            keys, capped = keys[: max(0, max_boxes - len(seen))], True  # the first in order
        seen = np.concatenate([seen, keys])
        parts.append(keys)
        frontier = unkey(keys)
        if capped:
            break
    found = unkey(np.sort(np.concatenate(parts)))
    return np.stack([axes[k][found[:, k]] for k in range(4)], 1).reshape(-1, 4), capped


def rows_of(fused: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """The row of ``fused`` that each of ``boxes`` is.

    ``fused`` is an :func:`intersection_closure` (unique rows, sorted): a binary search on the
    rows as records, whose order is the lexicographic one.

    Raises:
        ValueError: A box is not one of ``fused``'s rows (one of no area is not in a closure).
    """
    row = np.dtype([(c, np.float64) for c in ("x1", "y1", "x2", "y2")])
    f = np.ascontiguousarray(fused, np.float64).reshape(-1, 4)
    b = np.ascontiguousarray(boxes, np.float64).reshape(-1, 4)
    at = np.searchsorted(f.view(row).ravel(), b.view(row).ravel())
    found = at < len(f)
    found[found] = (f[at[found]] == b[found]).all(1)
    if not found.all():
        raise ValueError(f"box {b[~found][0].tolist()} is not in the closure")
    return at


def cover_matrix(fused: np.ndarray, originals: np.ndarray) -> np.ndarray:
    """(m, n) bool: original k contains fused box i."""
    f, o = fused[:, None, :], originals[None, :, :]
    return (
        (o[..., 0] <= f[..., 0])
        & (o[..., 1] <= f[..., 1])
        & (o[..., 2] >= f[..., 2])
        & (o[..., 3] >= f[..., 3])
    )


def loc_from_cover(
    cover: np.ndarray,
    fusion_rule: str,
    *,
    r: np.ndarray,
    d: np.ndarray,
    L: np.ndarray | None = None,
    seed: int = 0,
    rrf_c: float = 60.0,
    options: Any = None,
) -> np.ndarray:
    """LoC of the fused boxes (rows of ``cover``) by the rule ``fusion_rule`` (its catalogue entry).

    Higher is more likely changed. The paper's rules and a user's are looked up alike
    (``harness.methods.FUSION_RULES``; the built-in functions are in :mod:`harness.fusion.rules`).

    Args:
        cover: (m, n) bool: original box k contains fused box i.
        fusion_rule: a ``cover`` rule (not ``rank_no_fusion``, ``size_prior``, ``random``: see
            :func:`image_loc`).
        r: (n,) normalised ranks ``rank / L`` of the originals.
        d: (n,) exact L2 distances of the originals to their ground-truth place.
        L: (n,) rank-list lengths; needed by every rank-fusion method except ``rank_fusion_asc``.
        seed: seeds the random cover subsets of ``rank_fusion_le2`` / ``le3``.
        rrf_c: the constant of ``rrf`` (method §14).
        options: a registered rule's options (its ``[fusion.<rule>]`` table; None: the
            defaults of the dataclass it registered).

    Raises:
        ValueError: not a ``cover`` method, or ``L`` missing where the method needs it.
        ConfigError: a registered method returned other than one finite LoC per fused box.
    """
    spec = FUSION_RULES.get(fusion_rule)
    if spec is None or spec.kind != "cover" or spec.loc is None:
        raise ValueError(
            f"unknown fused-set method {fusion_rule!r}; known: {rules_where(kind='cover')}"
        )
    if spec.needs_lengths and L is None:
        raise ValueError(f"{fusion_rule} needs the rank-list lengths L (r' = (L + 1 - rank) / L)")
    lengths = np.full(len(r), np.nan) if L is None else np.asarray(L, np.float64)
    if options is None and fusion_rule in FUSION_OPTIONS:
        options = FUSION_OPTIONS[fusion_rule]()
    kwargs = {"seed": seed, "rrf_c": rrf_c, "options": options}
    loc = np.asarray(
        spec.loc(
            cover,
            np.asarray(r, np.float64),
            np.asarray(d, np.float64),
            lengths,
            **{k: kwargs[k] for k in spec.options},
        ),
        np.float64,
    )
    if spec.loc.__module__.startswith("harness."):
        return loc
    if loc.shape != (len(cover),) or not np.isfinite(loc).all():
        raise ConfigError(
            f"fusion method {fusion_rule!r} returned LoC of shape {loc.shape}, expected "
            f"({len(cover)},): one finite value per fused box"
        )
    return loc


def image_loc(
    fused: np.ndarray, fusion_rule: str, width: float, height: float, seed: int
) -> np.ndarray:
    """The baselines that need the image rather than ranks: ``size_prior`` (1 - SoB) and ``random``.

    Args:
        fused: (m, 4) sample boxes.
        fusion_rule: ``size_prior`` or ``random``.
        width: the image width in pixels.
        height: the image height in pixels.
        seed: the query image's seed (``random``: uniform in [0, 1), reproducible per image).
    """
    spec = FUSION_RULES.get(fusion_rule)
    if spec is None or spec.kind != "image" or spec.loc is None:
        raise ValueError(f"{fusion_rule!r} is not an image baseline ({', '.join(IMAGE_BASELINES)})")
    return np.asarray(spec.loc(fused, width, height, seed), np.float64)


def fuse(
    boxes: np.ndarray,
    r: np.ndarray,
    d: np.ndarray,
    fusion_rule: str,
    seed: int = 0,
    max_boxes: int | None = None,
    *,
    L: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Samples and their LoC for one query image (method §7).

    Args:
        boxes: (n, 4) original boxes of all proposal methods.
        r: (n,) normalised ranks in (0, 1].
        d: (n,) L2 distances to the ground-truth place.
        fusion_rule: any method id of method §7 except ``size_prior`` and ``random``
            (:func:`image_loc`).
        seed: seeds the random cover subsets of the ``le`` methods.
        max_boxes: cap on the intersection closure (:func:`intersection_closure`); None: none.
        L: (n,) rank-list lengths, for ``r'`` (every rank-fusion method except ``rank_fusion_asc``).

    Returns:
        (sample_boxes (m, 4), loc (m,)).
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    r = np.asarray(r, np.float64)
    d = np.asarray(d, np.float64)
    if is_unfused(fusion_rule):
        return boxes.copy(), r.copy()
    if fusion_rule not in rules_where(kind="cover"):
        raise ValueError(
            f"fuse() computes {[m for m in known_methods() if m not in IMAGE_BASELINES]}, got "
            f"{fusion_rule!r} (size_prior, random: image_loc)"
        )
    fused, _ = intersection_closure(boxes, max_boxes)
    cover = cover_matrix(fused, boxes)
    return fused, loc_from_cover(cover, fusion_rule, r=r, d=d, L=L, seed=seed)


def loc_map(sample_boxes: np.ndarray, loc: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel-wise LoC.

    Each pixel (by its centre) takes the LoC of the smallest sample box holding it.

    For a fused set, the smallest box holding a pixel is the intersection of all boxes covering
    it. Pixels that no box covers are NaN.
    """
    out = np.full((height, width), np.nan, np.float32)
    area = (sample_boxes[:, 2] - sample_boxes[:, 0]) * (sample_boxes[:, 3] - sample_boxes[:, 1])
    for i in np.argsort(-area, kind="stable"):
        x1, y1, x2, y2 = sample_boxes[i]
        # pixel u is inside when x1 <= u + 0.5 < x2
        u0, u1 = int(np.ceil(x1 - 0.5)), int(np.ceil(x2 - 0.5))
        v0, v1 = int(np.ceil(y1 - 0.5)), int(np.ceil(y2 - 0.5))
        out[max(v0, 0) : max(min(v1, height), 0), max(u0, 0) : max(min(u1, width), 0)] = loc[i]
    return out


#: The earlier name (one vocabulary: a fusion rule, a proposer), kept for plugins.
register_method = register_fusion_rule
