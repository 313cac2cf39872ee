"""Pairs by sequence as one order-keeping alignment (docs/decisions.md, *Pairs without poses*).

Distance matrices built to hold each failure a per-frame match falls into: a hub (a foggy stretch
whose rows are flat, beside a map frame near everything), a map that is dark where the query is
not, a query run the other way round, a query that covers part of the map, a stop.
"""

from __future__ import annotations

import numpy as np
import pytest

from harness.pairs.retrieval import sequence_frames
from harness.pairs.sequence import UNPAIRED_DARK, align, banded_pairs, path_pairs


def _ride(nq: int = 200, nm: int = 200, seed: int = 0, offset: int = 0) -> np.ndarray:
    """(nq, nm) distances of two runs of one route in step: small where j = i + offset."""
    rng = np.random.default_rng(seed)
    d = 1.0 + 0.2 * rng.random((nq, nm))
    i = np.arange(nq)
    j = i + offset
    ok = (j >= 0) & (j < nm)
    d[i[ok], j[ok]] = 0.3 + 0.05 * rng.random(ok.sum())
    return d


def test_a_flat_foggy_stretch_takes_its_place_from_the_path_not_a_hub() -> None:
    """Query frames 130-170 carry almost no evidence (flat rows), and map frames 172-176 are near
    everything those rows hold: a per-frame match sends the stretch onto them (a hub); the path
    keeps it in step, within 2 frames of its place."""
    d = _ride()
    d[130:171] = 0.95 + 0.02 * np.random.default_rng(1).random((41, 200))
    d[130:171, 172:177] = 0.9
    col = align(d, np.ones(200, bool)).column
    assert np.argmin(d[150]) in range(172, 177)  # what a per-frame match does
    assert np.abs(col - np.arange(200)).max() <= 2
    assert np.bincount(col).max() <= 2


def test_a_map_dark_where_the_query_is_not_leaves_those_query_frames_unpaired() -> None:
    """The map's first 17 frames carry no place; the query's do. Its frames 0-16 fall on them and
    stay unpaired, named; the rest pair in step (never a hundred frames away)."""
    d = _ride()
    d[:21, 100:107] = 0.5  # a wrong place that looks better than nothing for the first frames
    usable = np.ones(200, bool)
    usable[:17] = False
    col = align(d, usable).column
    assert (col[:17] < 17).all() and (col[17:] == np.arange(17, 200)).all()
    # the same through sequence_frames: those 17 named, the others paired
    frame = np.arange(200)  # one descriptor row a frame
    dq, dm = _as_descriptors(d)
    _, bf, _, _, left = sequence_frames(dq, frame, dm, frame, window=5, usable=usable)
    assert sorted(left) == list(range(17)) and set(left.values()) == {UNPAIRED_DARK}
    assert (bf[17:] == np.arange(17, 200)).all()


def _as_descriptors(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors whose squared distances are ``d`` (one row a frame), by classical MDS of the
    query and map frames together (2 within a run: only the distances across matter)."""
    nq, nm = d.shape
    k = nq + nm
    full = np.zeros((k, k))
    full[:nq, nq:] = d
    full[nq:, :nq] = d.T
    full[:nq, :nq] = 2.0
    full[nq:, nq:] = 2.0
    np.fill_diagonal(full, 0.0)
    j = np.eye(k) - 1.0 / k
    b = -0.5 * j @ full @ j
    w, v = np.linalg.eigh(b)
    x = v * np.sqrt(np.maximum(w, 0.0))
    return x[:nq].astype(np.float32), x[nq:].astype(np.float32)


def test_a_query_run_the_other_way_round_pairs_right() -> None:
    """The query drives the route backwards: the map is tried both ways and the path runs back."""
    d = _ride()[::-1]
    al = align(d, np.ones(200, bool))
    assert al.reversed
    assert (al.column == np.arange(199, -1, -1)).all()


def test_a_query_that_covers_part_of_the_map_pairs_right() -> None:
    """80 query frames of the map's 60-139: the path starts and ends where they do."""
    d = _ride(80, 200, offset=60)
    col = align(d, np.ones(200, bool)).column
    assert (col == np.arange(60, 140)).all()


def test_a_stop_and_another_speed_are_the_normal_case() -> None:
    """The query stands still for 12 frames, then runs at half the map's speed."""
    rng = np.random.default_rng(2)
    place = np.r_[np.arange(50), np.full(12, 50), 50 + np.arange(0, 100, 2)]
    d = 1.0 + 0.2 * rng.random((len(place), 200))
    d[np.arange(len(place)), place] = 0.3
    col = align(d, np.ones(200, bool)).column
    assert np.abs(col - place).max() <= 1


def test_a_loop_driven_from_another_start_wraps_from_the_maps_end_to_its_start() -> None:
    """The route is a loop: the query run starts at the map's frame 120 of 200, passes its last
    frame and goes on from its first. Every frame pairs with its place."""
    place = (np.arange(200) + 120) % 200
    rng = np.random.default_rng(4)
    d = 1.0 + 0.2 * rng.random((200, 200))
    d[np.arange(200), place] = 0.3
    col = align(d, np.ones(200, bool)).column
    assert (col == place).all()


@pytest.mark.parametrize("case", ["forward", "backwards", "loop", "dark start", "fog", "part"])
def test_a_long_ride_aligned_in_a_band_gets_the_whole_paths_pairs(case: str) -> None:
    """Over ``[retrieval] memory_mb`` the path is found in a band around a coarse path, the
    distances streamed (``banded_pairs``): on each kind of ride above, the same map frames, the
    same scores and rivals and the same frames left unpaired as the whole path's."""
    n = 600
    place = {"backwards": np.arange(n)[::-1], "loop": (np.arange(n) + 200) % n}.get(
        case, np.arange(n)
    )
    nq = 200 if case == "part" else n
    d = _ride(nq, n) if case != "part" else _ride(nq, n, offset=150)
    if case in ("backwards", "loop"):
        rng = np.random.default_rng(0)
        d = 1.0 + 0.2 * rng.random((n, n))
        d[np.arange(n), place] = 0.3
    usable = np.ones(n, bool)
    if case == "dark start":
        usable[:17] = False
    if case == "fog":
        d[300:340] = 0.95
        d[300:340, 372:377] = 0.9

    def rows(pos: np.ndarray):
        for a in range(0, len(pos), 37):
            yield d[pos[a : a + 37]]

    whole = path_pairs(d, usable, 11, 2)
    band = banded_pairs(rows, d.shape, usable, 11, 2, 2000)
    assert np.array_equal(whole[0], band[0])
    assert np.allclose(whole[1], band[1]) and np.allclose(whole[2], band[2])
    assert whole[3] == band[3]
