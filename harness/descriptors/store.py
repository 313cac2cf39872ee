"""Trained models kept for reuse: ``[descriptor] trained_models``, a folder of them.

Training is a function of what it is given: the model's options, the crops it samples (their
bytes, in order), the training code, torch's version, the kernels it runs on and its threads.
:func:`training_digest` hashes exactly these, so a model in the folder under that digest is the
model training would write, bit for bit where the kernels are pinned (``harness.kernels``; the
suite trains the fixture's model once and checks it against the committed one). A run whose
digest is there copies the model instead of training it, and says so in the entry's manifest
(``trained_models``); every trained entry records its digest in ``training.json``, and
``python -m harness.descriptors.store save RUN_DIR FOLDER`` keeps a run's trained models for
other runs (the fixture's are in ``datasets/models/``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

from harness.descriptors.autoencoder_descriptor import pick_device
from harness.descriptors.config import DescriptorConfig
from harness.descriptors.keys import model_options
from harness.runtime.cache import write_json
from harness.runtime.code import code_text

log = logging.getLogger(__name__)

#: The modules whose code trains a model (the network, its loss and optimiser, the loop).
TRAINING_CODE = ("autoencoder.py", "autoencoder_descriptor.py")
#: What a kept model is made of: the files copied, and its record.
MODEL_FILES = ("autoencoder.pt", "loss.csv", "loss.png")
RECORD = "training.json"


def crops_digest(crops: np.ndarray, chunk: int = 256) -> str:
    """SHA-256 of the crops' shape, dtype and bytes, read ``chunk`` crops at a time."""
    h = hashlib.sha256(f"{crops.shape}{crops.dtype}".encode())
    for i in range(0, len(crops), chunk):
        h.update(np.ascontiguousarray(crops[i : i + chunk]).tobytes())
    return h.hexdigest()


def code_digest(paths: list[Path]) -> str:
    """SHA-256 of the modules' code without their docstrings and comments.

    Each module is written back without its docstrings (:func:`harness.runtime.code.code_text`), so
    a change of words (a docstring, a comment, the layout) keeps the kept models; a change of code
    files them under another digest.
    """
    h = hashlib.sha256()
    for path in paths:
        h.update(code_text(path.read_text()).encode())
    return h.hexdigest()


def training_parts(dc: DescriptorConfig, crops: np.ndarray, threads: int) -> dict[str, Any]:
    """Everything the trained weights depend on, as plain values (the record's ``parts``).

    ``threads``: torch's threads while it trains.
    """
    here = Path(__file__).parent
    device = pick_device(dc.device).type
    kernels = str(torch.backends.cpu.get_cpu_capability()) if device == "cpu" else device
    return {
        "options": model_options(dc),
        "crops": crops_digest(crops),
        "training_code": code_digest([here / name for name in TRAINING_CODE]),
        "torch": torch.__version__.split("+")[0],
        "kernels": kernels,
        "threads": threads,
    }


def training_digest(parts: dict[str, Any]) -> str:
    """The digest a kept model is filed under (16 hex digits)."""
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:16]


def load_kept(folder: str, digest: str, dst: Path) -> dict[str, Any] | None:
    """Copy the kept model ``digest`` of ``folder`` into ``dst``: its training record, or None."""
    if not folder:
        return None
    if not Path(folder).is_dir():
        log.warning("[descriptor] trained_models = %s: no such folder, so no kept model: training",
                    folder)  # fmt: skip
        return None
    src = Path(folder) / digest
    if not (src / RECORD).is_file() or not (src / MODEL_FILES[0]).is_file():
        return None
    rec: dict[str, Any] = json.loads((src / RECORD).read_text())
    for name in MODEL_FILES:
        if (src / name).is_file():
            shutil.copyfile(src / name, dst / name)
    return rec


def write_record(dst: Path, digest: str, parts: dict[str, Any], info: dict[str, Any]) -> None:
    """The entry's ``training.json``: the digest, what it hashes, and the training's record."""
    write_json(dst / RECORD, {"digest": digest, "parts": parts, "info": info})


def save(run: Path, folder: Path) -> list[str]:
    """Keep every model a run trained (its ``cache/model`` entries with a record) in ``folder``.

    Returns the digests written; one already there is left as it is.
    """
    written = []
    for rec_path in sorted(Path(run).glob(f"cache/model/*/{RECORD}")):
        rec = json.loads(rec_path.read_text())
        dst = Path(folder) / rec["digest"]
        if dst.exists():
            continue
        tmp = Path(folder) / f".{rec['digest']}.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        for name in (*MODEL_FILES, RECORD):
            if (rec_path.parent / name).is_file():
                shutil.copyfile(rec_path.parent / name, tmp / name)
        tmp.rename(dst)
        written.append(rec["digest"])
    return written


def main(argv: list[str]) -> int:
    """``python -m harness.descriptors.store save RUN_DIR FOLDER``: one line a model kept."""
    if len(argv) != 3 or argv[0] != "save":
        print("ERROR: usage: python -m harness.descriptors.store save RUN_DIR FOLDER",
              file=sys.stderr)  # fmt: skip
        return 1
    run, folder = Path(argv[1]), Path(argv[2])
    if not (run / "cache" / "model").is_dir():
        print(f"ERROR: {run}: no cache/model here: not the output folder of a run that trained",
              file=sys.stderr)  # fmt: skip
        return 1
    records = sorted(run.glob(f"cache/model/*/{RECORD}"))
    written = save(run, folder)
    for d in written:
        print(f"kept {d} in {folder}")
    print(f"{len(written)} model(s) kept, {len(records) - len(written)} already there")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
