"""results/join_shipped_report.py: the shipped model's tables joined with the arms of the soup it re-fits."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest

RESULTS = Path(__file__).resolve().parents[1] / "results"
FULL, ARMS = "grounding_scenes/tables/report.json", "model_soup/tables/report.json"


@pytest.fixture
def join(results_script):
    return results_script("join_shipped_report.py").join


def _stored(path: str) -> dict:
    return json.loads((RESULTS / path).read_text())


def test_the_stored_report_is_the_shipped_models_rows_with_the_soups_arms(join):
    full, arms = _stored(FULL), _stored(ARMS)
    joined = join(full, arms, {"full": f"results/{FULL}", "arms": f"results/{ARMS}"})
    assert joined == _stored("report.json")  # results/report.json is exactly the join of the two stored runs
    assert joined["main"] == full["main"] and joined["latency"] == full["latency"]
    assert [row["systems"] for row in joined["ablation"]] == ["1", "1+3", "1+2+3"]
    assert joined["ablation"][:2] == arms["ablation"][:2] and joined["ablation"][2] == full["ablation"][0]
    assert joined["config"]["checkpoints"]["full"] == "models/trivla_cpu"
    assert set(joined["config"]["checkpoints"]) == {"full", "system1", "system1_3", "data10"}
    assert joined["data_efficiency"]["10%"] == pytest.approx(arms["data10"]["average_success"])
    assert joined["data100_recipe"]["average_success"] == pytest.approx(arms["main"]["average_success"])


def test_the_script_writes_the_committed_markdown(tmp_path):
    subprocess.run([sys.executable, str(RESULTS / "join_shipped_report.py"), str(RESULTS / FULL), str(RESULTS / ARMS),
                    str(tmp_path)], check=True, capture_output=True)
    markdown = (tmp_path / "report.md").read_text()
    # The paths recorded in joined_from differ (absolute here), the tables do not.
    assert markdown == (RESULTS / "report.md").read_text()
    assert "| 100%, without the grounding re-fit" in markdown and "Notes:" in markdown
    assert (tmp_path / "ablation.png").stat().st_size > 0


def test_reports_that_cannot_be_joined_are_refused_naming_why(join):
    full, arms = _stored(FULL), _stored(ARMS)
    changed = copy.deepcopy(arms)
    changed["config"]["seeds"] = [1000]
    with pytest.raises(ValueError, match="settings: seeds"):
        join(full, changed)
    with pytest.raises(ValueError, match="itself a join"):
        join(full, _stored("report.json"))
    changed = copy.deepcopy(arms)
    changed["ablation"] = [row for row in changed["ablation"] if row["systems"] != "1+3"]
    del changed["data10"]
    with pytest.raises(ValueError, match=r"missing rows: 1\+3, data10 \(arms\)"):
        join(full, changed)
