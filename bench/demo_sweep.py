"""Tuning sweep for ``magnav-ins demo``: run :func:`magnav_ins.studies.demo.run_demo` with variants of the default
configuration (JSON objects of DemoConfig overrides on the command line) and print one JSON line per variant.

    python bench/demo_sweep.py '{}' '{"line": 5817, "speed_mps": 70}' '{"matcher": {"kind": "mlr"}}'
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import numpy as np

from magnav_ins.studies.demo import DemoConfig, run_demo

KEYS = (
    "rms_horizontal_m", "free_inertial_rms_horizontal_m", "improvement_factor", "max_horizontal_m",
    "final_horizontal_m", "fixes_issued", "fix_attempts", "fixes_accepted", "fix_error_median_m", "fix_error_rms_m",
    "nees_mean", "fix_nees_mean", "hpl_median_m", "hpl_exceedance", "duration_s", "aided_run_s", "wall_s",
)  # fmt: skip


def main(argv: list[str]) -> None:
    """Each argument: DemoConfig overrides as JSON; ``"seeds": [..]`` runs each seed and adds the spread."""
    for arg in argv or ["{}"]:
        over = json.loads(arg)
        seeds = over.pop("seeds", None)
        runs = []
        for sd in seeds if seeds is not None else [None]:
            o = dict(over) if sd is None else {**over, "seed": sd}
            s = run_demo(replace(DemoConfig(), **o)).summary
            row = {k: (round(s[k], 2) if isinstance(s[k], float) else s[k]) for k in KEYS}
            row.update(no_fix=s["no_fix_reasons"], rejected=s["rejected_fix_reasons"])
            print(json.dumps({"overrides": o, **row}))
            sys.stdout.flush()
            runs.append(s)
        if len(runs) > 1:
            f = np.array([r["improvement_factor"] for r in runs])
            a = np.array([r["rms_horizontal_m"] for r in runs])
            summary = {
                "overrides": over,
                "seeds": seeds,
                "improvement_min": round(float(f.min()), 2),
                "improvement_median": round(float(np.median(f)), 2),
                "aided_rms_median_m": round(float(np.median(a)), 1),
                "all_at_least_3x": bool((f >= 3).all()),
            }
            print(json.dumps(summary))
            sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv[1:])
