"""results/join_data_efficiency.py: the 10%-data arm's rows joined into the shipped model's tables."""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

RESULTS = Path(__file__).resolve().parents[1] / "results"


@pytest.fixture
def script(results_script):
    return results_script("join_data_efficiency.py")


def _stored(path: str) -> dict:
    return json.loads((RESULTS / path).read_text())


def test_the_stored_report_is_the_join_of_its_two_runs(script):
    """The soup's tables (results/model_soup/tables/report.json, results/report.json until session 46) are what the
    script makes, and they keep the ablation and add the 10% arm."""
    join = script.join
    full, arm = _stored("model_soup/tables/report.json"), _stored("data_efficiency/report.json")
    joined = join(full, arm)
    assert joined == full  # the committed report is already joined: joining again changes nothing
    assert [row["systems"] for row in joined["ablation"]] == ["1", "1+3", "1+2+3"]
    assert joined["data10"] == arm["data10"] and set(joined["config"]["checkpoints"]) == {
        "full", "system1", "system1_3", "data10"}
    assert joined["data_efficiency"]["10%"] == pytest.approx(arm["data10"]["average_success"])


def test_reports_that_disagree_on_the_full_model_are_not_joined(script):
    join = script.join
    full, arm = _stored("model_soup/tables/report.json"), _stored("data_efficiency/report.json")
    changed = copy.deepcopy(arm)
    changed["main"]["average_success"] += 0.01
    with pytest.raises(ValueError, match="'main'"):
        join(full, changed)
    changed = copy.deepcopy(arm)
    changed["config"]["seeds"] = [1000]
    with pytest.raises(ValueError, match="config"):
        join(full, changed)


def test_the_script_rewrites_the_markdown_and_plots_from_the_two_reports(tmp_path):
    """The command reproduce step 30 runs, on copies: it writes the committed report.md again."""
    (tmp_path / "data_efficiency").mkdir()
    shutil.copy(RESULTS / "model_soup" / "tables" / "report.json", tmp_path / "report.json")
    shutil.copy(RESULTS / "data_efficiency" / "report.json", tmp_path / "data_efficiency" / "report.json")
    subprocess.run([sys.executable, str(RESULTS / "join_data_efficiency.py"), str(tmp_path)], check=True,
                   capture_output=True)
    markdown = (tmp_path / "report.md").read_text()
    assert "## Sub-system ablation" in markdown and "## Data efficiency" in markdown
    assert markdown == (RESULTS / "model_soup" / "tables" / "report.md").read_text()
    assert (tmp_path / "per_task_success.png").is_file() and (tmp_path / "ablation.png").is_file()
