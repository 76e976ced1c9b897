"""Tuning sweep for ``magnav-ins demo``: run :func:`magnav_ins.studies.demo.run_demo` with variants of the default
configuration (JSON objects of DemoConfig overrides on the command line) and print one JSON line per variant.

    python bench/demo_sweep.py '{}' '{"line": 5817, "speed_mps": 70}' '{"matcher": {"kind": "mlr"}}'
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace

from magnav_ins.studies.demo import DemoConfig, run_demo

KEYS = (
    "rms_horizontal_m", "free_inertial_rms_horizontal_m", "improvement_factor", "max_horizontal_m",
    "final_horizontal_m", "fixes_issued", "fix_attempts", "fixes_accepted", "fix_error_median_m", "fix_error_rms_m",
    "nees_mean", "duration_s", "aided_run_s", "wall_s",
)  # fmt: skip


def main(argv: list[str]) -> None:
    for arg in argv or ["{}"]:
        over = json.loads(arg)
        cfg = replace(DemoConfig(), **over)
        s = run_demo(cfg).summary
        print(
            json.dumps({"overrides": over, **{k: (round(s[k], 2) if isinstance(s[k], float) else s[k]) for k in KEYS}})
        )
        sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv[1:])
