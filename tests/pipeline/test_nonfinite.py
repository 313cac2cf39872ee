"""Non-finite values and damaged cache entries stop or rebuild, never give silent tables (issue 26).

Grouped by the module they exercise: ``harness.descriptors`` (a diverged training, NaN
descriptors), ``harness.runtime.cache`` (a flipped byte in an entry),
``harness.proposals.proposers`` (a method that proposes nothing for a whole session).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from harness.descriptors.autoencoder import ConvAutoencoder, TrainSettings, train
from harness.errors import ConfigError, HarnessError
from harness.methods import PROPOSERS
from harness.pipeline.chain import Pipeline
from harness.proposals.config import ProposalsConfig
from harness.runtime.cache import StageCache

from ..conftest import no_figures

# ------------------------------------------------------------------ harness.descriptors


def test_a_diverged_training_stops_with_its_step_and_value() -> None:
    data = np.random.default_rng(0).integers(0, 256, (32, 16, 16, 3), dtype=np.uint8)
    with pytest.raises(
        HarnessError, match=r"training loss is (nan|inf) at step \d+: training diverged"
    ):
        train(
            ConvAutoencoder(channels=(4, 4, 4)),
            data,
            50,
            TrainSettings(8, 1e30, 0, torch.device("cpu")),
        )


def test_nan_descriptors_stop_the_descriptor_stage(
    local_run: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from harness.descriptors import REGISTRY, Descriptor

    class Broken(Descriptor):
        name = "broken"

        def encode(self, crops: np.ndarray) -> np.ndarray:
            out = np.ones((len(crops), 4), np.float32)
            out[0] = np.nan
            return out

    monkeypatch.setitem(REGISTRY, "broken", Broken)
    p, _, run = local_run
    cfg = dataclasses.replace(
        p.cfg, descriptor=dataclasses.replace(p.cfg.descriptor, name="broken")
    )
    out = tmp_path / "o"
    shutil.copytree(run / "cache", out / "cache")
    shutil.copy(run / ".dbl-harness.json", out)
    before = sorted(p.name for p in (out / "cache" / "descriptors").iterdir())
    with pytest.raises(HarnessError, match=r"descriptors .*NaN or inf descriptors .*'broken'"):
        Pipeline(cfg, out).run()
    # no descriptor entry of the broken descriptor was finished: the stage's entries are those of
    # the run it started from
    after = sorted(
        p.name for p in (out / "cache" / "descriptors").iterdir() if (p / "manifest.json").exists()
    )
    assert after == before


# ------------------------------------------------------------------ harness.runtime.cache


def test_a_flipped_byte_in_a_cache_entry_rebuilds_it_with_a_warning(
    local_run: tuple, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    p, _, run = local_run
    out = tmp_path / "o"
    shutil.copytree(run / "cache", out / "cache")
    shutil.copy(run / ".dbl-harness.json", out)
    for stage, name in (("samples", "samples.parquet"), ("descriptors", "desc.npy")):
        victim = next((out / "cache" / stage).glob(f"*/{name}"))
        data = bytearray(victim.read_bytes())
        data[len(data) // 2] ^= 0x40  # same size: only a checksum can tell
        victim.write_bytes(bytes(data))
    q = Pipeline(no_figures(p.cfg), out)
    with caplog.at_level(logging.WARNING):
        q.run()
    assert "does not match its checksum" in caplog.text
    assert q.ran.get("samples") == 1 and q.ran.get("descriptors") == 1
    assert q.ran.get("model", 0) == 0 and q.ran.get("ingest", 0) == 0
    for stem in ("table1", "tableS", "tableP"):
        assert (out / f"{stem}.csv").read_bytes() == (run / f"{stem}.csv").read_bytes()
    cache = StageCache(out / "cache")
    entry = next((out / "cache" / "samples").iterdir())
    assert cache.is_done("samples", entry.name)


# ------------------------------------------------------------------ harness.proposals.proposers


def test_a_method_without_any_box_in_a_session_is_an_error(
    local_run: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def none(im: np.ndarray, cfg: ProposalsConfig) -> tuple:
        return np.zeros((0, 4)), np.zeros(0)

    monkeypatch.setitem(PROPOSERS, "edges", dataclasses.replace(PROPOSERS["edges"], run=none))
    p, _, _ = local_run
    with pytest.raises(HarnessError, match=r"method 'edges' gives no box on any of the session"):
        Pipeline(p.cfg, tmp_path / "o").run()


def test_an_opencv_refusal_names_the_method_and_frame(
    local_run: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import cv2

    def refuses(im: np.ndarray, cfg: ProposalsConfig) -> tuple:
        raise cv2.error("OpenCV(5.0) error: (-215:Assertion failed) ksize > 0 in function 'x'")

    monkeypatch.setitem(PROPOSERS, "edges", dataclasses.replace(PROPOSERS["edges"], run=refuses))
    p, _, _ = local_run
    with pytest.raises(ConfigError, match=r"proposal method 'edges' on frame .*OpenCV refused it"):
        Pipeline(p.cfg, tmp_path / "o").run()
