"""What the regression records promise on a CPU of another vendor than the one that recorded them.

The harness caps every numeric library at AVX2 (``harness/kernels.py``), and on the two AMD EPYCs
measured that gives the same bytes at every stage. On an Intel Xeon (family 6, model 207, AVX-512
and AMX) under the same caps it does not, from the descriptors on:

- the descriptors' last bits (the kept model, the same crops): at most one float16 step apart,
  553 to 643 of a session's 0.9 M values on the fixture; the fixture's Table S moves by 0.01 in
  one cell, the summary's floats by at most 0.005 (a sign-flip share of 200 resamples; the
  largest AP by 0.0002), no verdict changes;
- the model trained from nothing: ``2df436b7a8d01699``, not the kept ``978dd804b216655a``;
- BoVW's SIFT features (OpenCV), and so its vocabulary, words and ranks.

MKL's vector maths (VML), which torch calls for ``torch.sqrt`` and ``exp`` (the batch-norm
folding, Adam's step), choose their code path by the CPU's vendor as well as its instructions:
on that Xeon ``MKL_CBWR`` changes the encoder's output, and none of the paths it selects
(``COMPATIBLE``, ``SSE2`` ... ``AVX512``) gives the AMD machines' descriptors. So the cause is
not isolated to one library, and the records here promise on a CPU of another vendor: every
stage before the descriptors the same bytes (ingest, frames, pairs, proposals, the kept model),
the summary's floats within :data:`CROSS_VENDOR_ATOL`, one step of the tables' two decimals.
``docs/decisions.md``, *One answer on every CPU*, says the same to users.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

#: The first stage whose bytes may differ on a CPU of another vendor (see the module docstring).
CROSS_VENDOR_FIRST = "descriptors"
#: How far the summary's floats may move on a CPU of another vendor: one step of two decimals.
CROSS_VENDOR_ATOL = 0.01


def vendor(model: str | None = None) -> str:
    """``intel``, ``amd`` or ``other``: of this CPU (``/proc/cpuinfo``), or of a recorded model
    name (the ``cpu`` record's ``model``, which starts with the vendor's name)."""
    if model is None:
        info = Path("/proc/cpuinfo")
        text = info.read_text() if info.exists() else ""
        ids = [x.partition(":")[2].strip() for x in text.splitlines() if x.startswith("vendor_id")]
        model = {"GenuineIntel": "Intel", "AuthenticAMD": "AMD"}.get(ids[0] if ids else "", "")
    low = model.lower()
    return "intel" if low.startswith("intel") else "amd" if low.startswith("amd") else "other"


def other_vendor(recorded_on: dict[str, Any] | None) -> bool:
    """Whether this CPU's vendor differs from the one that recorded ``recorded_on`` (a record's
    ``cpu``); a record that names no CPU counts as this vendor's."""
    if not recorded_on or "model" not in recorded_on:
        return False
    return vendor() != vendor(str(recorded_on["model"]))


def differ_before_descriptors(got: dict[str, list[str]], want: dict[str, list[str]]) -> list[str]:
    """The files (names as ``stage_digests.digests`` gives them) of the stages before
    :data:`CROSS_VENDOR_FIRST` whose digests differ from the record: none may, on any CPU."""
    from .stage_digests import STAGES, stage_order

    limit = [s for s, _ in STAGES].index(CROSS_VENDOR_FIRST)
    bad = (k for k in set(got) | set(want) if got.get(k) != want.get(k))
    return sorted((k for k in bad if stage_order(k)[0] < limit), key=stage_order)
