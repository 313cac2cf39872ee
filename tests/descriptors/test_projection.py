"""``[projection]``: compact descriptors by PCA / PCA-whitening fitted on the reference sessions."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.descriptors.config import ProjectionConfig
from harness.descriptors.projection import fit_projection, load_projection, project
from harness.errors import ConfigError
from harness.pipeline.chain import Pipeline

from ..conftest import no_figures


def _data(n: int = 400, D: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Rows with standard deviations 5, 2, 0.1, ... along a known rotation of the axes."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((D, D)))
    sd = np.array([5.0, 2.0] + [0.1] * (D - 2))
    return (rng.standard_normal((n, D)) * sd) @ q.T + 3.0, q


@pytest.mark.parametrize("n", [400, 4])  # D x D covariance, and the n x n Gram form (n < D)
def test_the_directions_are_the_principal_axes(tmp_path: Path, n: int) -> None:
    x, q = _data(n=n)
    info = fit_projection(ProjectionConfig(dim=2), x.astype(np.float32).copy(), tmp_path)
    mean, comp, scale = load_projection(tmp_path)
    if n == 400:  # enough rows to pin the axes: |cos| with the true first two axes near 1
        assert np.abs((comp.T @ q[:, :2]).diagonal()).min() > 0.99
        assert info["explained_variance"] > 0.99
    np.testing.assert_allclose(comp.T @ comp, np.eye(2), atol=1e-5)  # orthonormal
    np.testing.assert_allclose(mean, x.mean(0), rtol=1e-5)
    assert np.all(scale == 1) and info == {**info, "fitted_on": n, "input_dim": 6, "dim": 2}
    # each direction's largest coordinate is positive: the sign is fixed, the fit repeatable
    assert np.all(comp[np.abs(comp).argmax(0), [0, 1]] > 0)
    fit_projection(
        ProjectionConfig(dim=2), x.astype(np.float32).copy(), tmp_path / ".." / tmp_path.name
    )
    np.testing.assert_array_equal(load_projection(tmp_path)[1], comp)


def test_whitening_gives_unit_variance_before_the_renormalisation(tmp_path: Path) -> None:
    x, _ = _data()
    fit_projection(ProjectionConfig(dim=2, whiten=True), x.astype(np.float32).copy(), tmp_path)
    mean, comp, scale = load_projection(tmp_path)
    z = ((x - mean) @ comp) * scale
    np.testing.assert_allclose(z.std(0, ddof=1), [1.0, 1.0], rtol=1e-3)
    out = project(x, mean, comp, scale)
    np.testing.assert_allclose(
        np.linalg.norm(out, axis=1), 1.0, rtol=1e-5
    )  # descriptors stay unit vectors


def test_dim_larger_than_the_sample_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(
        ConfigError,
        match=r"\[projection\] dim = 5 exceeds min\(input dim 6, sampled reference rows 4\)",
    ):
        fit_projection(ProjectionConfig(dim=5), _data(n=4)[0].astype(np.float32), tmp_path)


def test_the_config_section_as_a_user_types_it(tmp_path: Path) -> None:
    from harness.config.assemble import load_config

    from ..conftest import ROOT

    text = (ROOT / "datasets" / "fixture.toml").read_text()
    (tmp_path / "c.toml").write_text(
        text + "\n[projection]\ndim = 64\nwhiten = true\nfit_samples = 500\n"
    )
    cfg = load_config(tmp_path / "c.toml")
    assert cfg.projection == ProjectionConfig(dim=64, whiten=True, fit_samples=500)
    (tmp_path / "bad.toml").write_text(text + "\n[projection]\ndim = 64\nfit_samples = 10\n")
    with pytest.raises(ConfigError, match=r"\[projection\] fit_samples.*10"):
        load_config(tmp_path / "bad.toml")


def test_a_projected_run_stores_dim_float16_values_and_keeps_the_model(
    local_run: tuple, tmp_path: Path
) -> None:
    p, _, out = local_run
    shutil.copytree(out / "cache", tmp_path / "cache")
    shutil.copy(out / ".dbl-harness.json", tmp_path / ".dbl-harness.json")
    cfg = dataclasses.replace(p.cfg, projection=ProjectionConfig(dim=64))
    q = Pipeline(no_figures(cfg), tmp_path)
    rec = q.run()
    assert q.ran.get("model", 0) == 0 and q.ran["projection"] == 1  # the model is reused
    for key in rec["cache_entries"]["descriptors"]:
        d = np.load(tmp_path / "cache" / "descriptors" / key / "desc.npy", mmap_mode="r")
        assert d.shape[1] == 64 and d.dtype == np.float16
    fit = q.cache.manifest("projection", rec["cache_entries"]["projection"][0])["info"]
    assert fit["input_dim"] == 1024 and 0.5 < fit["explained_variance"] < 1
    # the price is reported, not hidden: recall@1 of the place drops a little (fixture: 0.278 ->
    # 0.251)
    full = pd.read_csv(out / "localization.csv").set_index(["proposal_method", "season_pair"])
    small = pd.read_csv(tmp_path / "localization.csv").set_index(["proposal_method", "season_pair"])
    assert (
        0.8 * full.loc[("all", "all"), "recall_at_1"]
        < small.loc[("all", "all"), "recall_at_1"]
        <= full.loc[("all", "all"), "recall_at_1"]
    )
    assert rec["config"]["projection"]["dim"] == 64


def test_memory_mb_as_a_user_types_it(tmp_path: Path) -> None:
    """``[retrieval] memory_mb`` is read from the TOML; a non-positive budget is refused."""
    from harness.config.assemble import load_config

    from ..conftest import ROOT

    text = (ROOT / "datasets" / "fixture.toml").read_text()
    (tmp_path / "c.toml").write_text(text + "\n[retrieval]\nmemory_mb = 256\n")
    assert load_config(tmp_path / "c.toml").retrieval.memory_mb == 256
    (tmp_path / "bad.toml").write_text(text + "\n[retrieval]\nmemory_mb = 0\n")
    with pytest.raises(ConfigError, match=r"\[retrieval\] memory_mb.*0.*> 0 MiB"):
        load_config(tmp_path / "bad.toml")
