"""``python -m bench.cases NAME [--quick]`` (one case), ``rankjob --args JSON`` (a full-nclt
ranking job in its own process) or ``kerneljob`` (the rated stages' kernels at the process's
``HARNESS_KERNELS`` level)."""

from __future__ import annotations

import argparse
import json

from . import CASES, run


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("case", choices=[*CASES, "rankjob", "kerneljob"])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--args", default="{}", help="rankjob: its arguments as JSON")
    a = ap.parse_args()
    if a.case == "rankjob":
        from .full_nclt import rank_job

        rank_job(**json.loads(a.args))
        return
    if a.case == "kerneljob":
        from .kernel_levels import kernel_job

        kernel_job()
        return
    run(a.case, a.quick)


if __name__ == "__main__":
    main()
