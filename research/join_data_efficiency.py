"""Join the data-efficiency arm's rows (results/data_efficiency/report.json) into the shipped model's
tables (results/report.json) and rewrite results/report.md and its plots.

The two `tables` runs were made on machines that did not hold each other's extra checkpoints (step 29's
ablation arms, step 30's 10% arm). Both read the full model's evaluations from results/evaluations/, so
their full-model rows must agree exactly; the script refuses to join them otherwise, naming the row.
Run from the repository root: `python results/join_data_efficiency.py` (reproduce step 30)."""

import json
import sys
from pathlib import Path

from trivla_drake.eval.paper_tables import write_tables

SHARED = ("main", "paraphrases", "latency")  # the full model's rows, in both reports
ORDER = ("config", "main", "paraphrases", "ablation", "data10", "data_efficiency", "latency")


def join(full: dict, arm: dict) -> dict:
    """`full` with `arm`'s data-efficiency rows; raises ValueError if the full model's rows differ."""
    for key in SHARED:
        if full[key] != arm[key]:
            raise ValueError(f"the reports disagree on the full model's '{key}' rows; rerun one with the other's "
                             "--evaluations store")
    settings = {k: v for k, v in full["config"].items() if k != "checkpoints"}
    if settings != {k: v for k, v in arm["config"].items() if k != "checkpoints"}:
        raise ValueError("the reports were made with different tables settings (config)")
    joined = dict(full, data10=arm["data10"], data_efficiency=arm["data_efficiency"])
    joined["config"] = dict(full["config"], checkpoints={**full["config"]["checkpoints"],
                                                         "data10": arm["config"]["checkpoints"]["data10"]})
    return {k: joined[k] for k in ORDER}


if __name__ == "__main__":
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("results")
    report = join(json.loads((root / "report.json").read_text()),
                  json.loads((root / "data_efficiency" / "report.json").read_text()))
    for path in write_tables(report, root).values():
        print(path)
