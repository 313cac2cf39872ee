"""The localizer kinds' records: what the page says of each kind, and a kind it does not know."""

from __future__ import annotations

from harness.localizers.kinds import LOCALIZER_KINDS, kind_summary


def test_the_page_says_what_each_kind_is_from_its_run_record() -> None:
    """A ``local`` localizer was called a built-in descriptor on the page before its kind's record
    said what it is (issue 51); every built-in kind now has its own words."""
    cfg = {"descriptor": {"name": "autoencoder"}}
    assert kind_summary({"kind": "descriptor"}, cfg) == "built-in descriptor autoencoder"
    assert kind_summary({"kind": "descriptor", "descriptor": "thumb"}, cfg).endswith("thumb")
    bovw = {"kind": "bovw", "bovw": {"features": "rootsift", "k": 256}}
    assert kind_summary(bovw, cfg) == "bag of visual words (rootsift, k = 256)"
    imp = {"kind": "import", "file": "/x/r.csv", "sha256": "ab", "score_kind": "distance"}
    assert kind_summary(imp, cfg) == "imported from /x/r.csv (sha256 ab, scores as distance)"
    local = {"kind": "local", "local": {"keypoints": "orb", "image": "gradient"}}
    text = kind_summary(local, cfg)
    assert "descriptor" not in text and "paired map frame (orb keypoints, gradient image)" in text
    assert "descriptor" not in kind_summary({"kind": "local"}, cfg)
    assert kind_summary({"kind": "colour"}, cfg) == "localizer kind colour"  # a plugin's, unloaded
    assert all(LOCALIZER_KINDS[k].summary for k in ("descriptor", "bovw", "import", "local"))
