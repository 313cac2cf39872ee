"""The vendor rule of the regression records (``tests/cpu_vendor.py``)."""

from __future__ import annotations

import pandas as pd

from ..cpu_vendor import CROSS_VENDOR_ATOL, differ_before_descriptors, other_vendor, vendor
from ..stage_digests import frame_differs


def test_a_recorded_model_name_gives_its_vendor_and_this_cpu_has_one() -> None:
    assert vendor("AMD EPYC (AVX2 and FMA, no AVX-512)") == "amd"
    assert vendor("Intel(R) Xeon(R) Processor (family 6, model 207)") == "intel"
    assert vendor("Neoverse-V2") == "other"
    assert vendor() in ("intel", "amd", "other")
    assert not other_vendor(None) and not other_vendor({})
    here = {"intel": "Intel(R) Xeon(R)", "amd": "AMD EPYC", "other": "Neoverse"}[vendor()]
    assert not other_vendor({"model": here})
    assert other_vendor({"model": "Intel(R) Xeon(R)" if vendor() != "intel" else "AMD EPYC"})


def test_the_cross_vendor_rule_still_catches_a_real_change() -> None:
    """Another vendor's summary may move by one step of two decimals, no more; the stages before
    the descriptors may not move at all."""
    want = pd.DataFrame({"ap": [0.1690], "verdict": ["above"]}).astype({"ap": str})
    moved = pd.DataFrame({"ap": [0.1690 + CROSS_VENDOR_ATOL / 2], "verdict": ["above"]})
    assert frame_differs(moved, want, CROSS_VENDOR_ATOL) == []
    assert frame_differs(moved, want)  # on the recording vendor: last bits only
    far = pd.DataFrame({"ap": [0.1690 + 2 * CROSS_VENDOR_ATOL], "verdict": ["above"]})
    assert frame_differs(far, want, CROSS_VENDOR_ATOL)
    flipped = pd.DataFrame({"ap": [0.1690], "verdict": ["chance"]})
    assert frame_differs(flipped, want, CROSS_VENDOR_ATOL) == ["verdict: differs"]
    rec = {"cache/proposals/*/proposals.parquet": ["a"], "cache/descriptors/*/desc.npy": ["b"]}
    assert differ_before_descriptors({**rec, "cache/descriptors/*/desc.npy": ["c"]}, rec) == []
    got = {**rec, "cache/proposals/*/proposals.parquet": ["z"]}
    assert differ_before_descriptors(got, rec) == ["cache/proposals/*/proposals.parquet"]
