"""Run `datasets_gen.generate_dataset` in-process for several cases, in one Blender session.

Run as `python generate_cases.py CASES.json` with a Python that has the bpy module.  CASES.json
holds [{"name": ..., "kwargs": {...}}, ...]; each case's keyword arguments go to
generate_dataset unchanged (one process saves Blender's start-up per case).  Writes
CASES.json's folder / results.json: {name: "ok" or the DatasetGenError message}.
"""

from __future__ import annotations

import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from datasets_gen import DatasetGenError, generate_dataset  # noqa: E402


def main() -> None:
    cases_path = sys.argv[-1]
    with open(cases_path) as handle:
        cases = json.load(handle)
    results = {}
    for case in cases:
        try:
            generate_dataset(**case["kwargs"], progress=False)
            results[case["name"]] = "ok"
        except DatasetGenError as error:
            results[case["name"]] = str(error)
    with open(os.path.join(os.path.dirname(cases_path), "results.json"), "w") as handle:
        json.dump(results, handle, indent=2)


if __name__ == "__main__":
    main()
