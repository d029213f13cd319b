"""The shipped model's tables with ablation and data-efficiency arms: results/report.{json,md} and its plots.

The shipped model is the soup of results/model_soup/ with its instruction grounding's read-out re-fitted on rendered
scenes (results/grounding_scenes/). Its own `tables` run (results/grounding_scenes/tables/report.json) has no arms:
their checkpoints were not on the machine that made it. The soup's run (results/model_soup/tables/report.json)
has them, and they stand for the shipped model's as they are:
- the System 1 and System 1+3 arms have no System 2, hence no instruction grounding, so the re-fit (which changes
  only the grounding's read-out of System 2's tokens) has nothing to change in them;
- the 10%-data arm was trained with the soup's recipe, without the re-fit, so the soup's own 100% row is shown
  beside it as the like-for-like comparison.
Both runs evaluate the same seeds and settings; the script refuses reports whose settings differ, naming them.
Latencies come from two runs on a shared machine, which the report's notes say.

Run from the repository root: `python results/join_shipped_report.py [FULL_REPORT ARMS_REPORT OUT_DIR]`
(reproduce step 48; defaults: results/grounding_scenes/tables/report.json results/model_soup/tables/report.json
results)."""

import json
import sys
from pathlib import Path

from trivla_drake.eval.paper_tables import write_tables

ARM_ROWS = ("1", "1+3")
RECIPE_LABEL = "100%, without the grounding re-fit (the soup: the 10% arm's recipe)"


def join(full: dict, arms: dict, sources: dict[str, str] | None = None) -> dict:
    """`full`'s rows with `arms`' System 1 / 1+3 ablation rows and 10%-data arm; ValueError when they cannot be
    joined (different settings, a missing row, or an arms report that is itself a join)."""
    if "joined_from" in arms["config"]:
        raise ValueError("the arms' report is itself a join; give the report of the run that evaluated the arms")
    differ = sorted(k for k in set(full["config"]) | set(arms["config"])
                    if k != "checkpoints" and full["config"].get(k) != arms["config"].get(k))
    if differ:
        raise ValueError(f"the reports were made with different tables settings: {', '.join(differ)}")
    arm_rows = {row["systems"]: row for row in arms["ablation"]}
    full_rows = {row["systems"]: row for row in full["ablation"]}
    missing = [s for s in ARM_ROWS if s not in arm_rows] + (["1+2+3 (full)"] if "1+2+3" not in full_rows else [])
    if missing or "data10" not in arms:
        raise ValueError(f"missing rows: {', '.join(missing + ([] if 'data10' in arms else ['data10 (arms)']))}")
    checkpoints = {k: v for k, v in arms["config"]["checkpoints"].items() if k != "full"}
    config = dict(full["config"], checkpoints={"full": full["config"]["checkpoints"]["full"], **checkpoints},
                  joined_from=sources or {})
    recipe = {"label": RECIPE_LABEL, "average_success": arms["main"]["average_success"],
              "average_stderr": arms["main"]["average_stderr"]}
    return {
        "config": config,
        "main": full["main"],
        "paraphrases": full["paraphrases"],
        "ablation": [arm_rows[s] for s in ARM_ROWS] + [full_rows["1+2+3"]],
        "data10": arms["data10"],
        "data_efficiency": {"100%": full["main"]["average_success"], "10%": arms["data10"]["average_success"],
                            RECIPE_LABEL: arms["main"]["average_success"]},
        "data100_recipe": recipe,
        "latency": full["latency"],
        "notes": [
            "The System 1 and 1+3 rows are the arms of the soup this model re-fits (results/model_soup/tables/): "
            "they have no System 2, so the re-fit leaves them as they are. Their latencies were timed in that run "
            f"(its 1+2+3 row: {arm_rows.get('1+2+3', {}).get('latency_ms', float('nan')):.1f} ms), the 1+2+3 row's "
            "in this model's run, on a shared 2-core machine.",
            "The 10% arm was trained with the soup's recipe, without the grounding re-fit; the soup's own 100% row "
            "is the like-for-like comparison.",
        ],
    }


def main(argv: list[str]) -> None:
    if len(argv) not in (0, 3):
        sys.exit(__doc__)
    full_path, arms_path, out = argv or ["results/grounding_scenes/tables/report.json",
                                         "results/model_soup/tables/report.json", "results"]
    report = join(json.loads(Path(full_path).read_text()), json.loads(Path(arms_path).read_text()),
                  {"full": full_path, "arms": arms_path})
    for path in write_tables(report, out).values():
        print(path)


if __name__ == "__main__":
    main(sys.argv[1:])
