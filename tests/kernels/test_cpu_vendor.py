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


def test_the_digests_table_text_is_what_pandas_writes() -> None:
    """The digests write a table's text column by column: the bytes of ``to_csv(index=False,
    float_format="%r")`` (which the recorded digests hold), for plain values and, through pandas,
    for values that need quoting or are not plain (empty strings, commas, arrays, float32)."""
    import numpy as np
    import pandas as pd

    from ..stage_digests import _column_text, _csv

    nan = float("nan")
    plain = pd.DataFrame({"s": pd.array(["a", "b", None], dtype="str"), "f": [0.1, nan, 1e-300],
                          "i": np.array([1, -2, 3], np.int32), "b": [True, False, True],
                          "o": ["x", nan, "y"]})  # fmt: skip
    tricky = [
        plain.assign(s=["a,b", "c", "d"]),
        plain.assign(o=["", "e", "f"]),
        plain.assign(o=[np.zeros(2), np.ones(1), np.zeros(0)]),
        plain.assign(f=np.array([0.1, nan, 2.5], np.float32)),
        plain[["f"]],
        plain.head(0),
    ]
    assert all(_column_text(plain[c]) is not None for c in plain)  # written column by column
    for df in (plain, *tricky):
        assert _csv(df) == df.to_csv(index=False, float_format="%r"), df
