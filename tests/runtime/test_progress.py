"""Long work shows progress where its output goes: a bar on a terminal, log lines elsewhere."""

from __future__ import annotations

import logging

import pytest

from harness.runtime import progress as pr


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """No terminal, and a clock the test moves by hand (``clock[0]`` seconds)."""
    now = [0.0]
    monkeypatch.setattr(pr, "_terminal", lambda: False)
    monkeypatch.setattr(pr.time, "monotonic", lambda: now[0])
    return now


def test_off_a_terminal_progress_is_a_log_line_every_ten_seconds(
    clock: list[float], caplog: pytest.LogCaptureFixture
) -> None:
    now = clock
    items = list(range(30))
    seen = []
    with caplog.at_level(logging.INFO, logger=pr.__name__):
        for i in pr.progress(items, "proposals grid5", "batch"):
            seen.append(i)
            now[0] += 1.0  # one second per item: a line at 10 s, 20 s and 30 s
    assert seen == items  # the same items, in order
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "proposals grid5: 10/30 batch (33%, 1 batch/s)",
        "proposals grid5: 20/30 batch (67%, 1 batch/s)",
        "proposals grid5: 30/30 batch (100%, 1 batch/s)",
    ]


def test_short_work_logs_nothing_and_a_bar_by_hand_counts_steps(
    clock: list[float], caplog: pytest.LogCaptureFixture
) -> None:
    now = clock
    with caplog.at_level(logging.INFO, logger=pr.__name__):
        list(pr.progress(iter(range(5)), "quick"))  # 0 s: no line; no length: no total
        bar = pr.progress_bar(400, "autoencoder training", "step")
        for _ in range(400):
            now[0] += 0.05
            bar.update(1)
        bar.close()
    assert [r.getMessage() for r in caplog.records] == [
        "autoencoder training: 200/400 step (50%, 20 step/s)",
        "autoencoder training: 400/400 step (100%, 20 step/s)",
    ]
