"""results/data_efficiency/learning_curve.py: success against the number of demonstrations, by task group."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest


@pytest.fixture
def script(results_script):
    return results_script("data_efficiency/learning_curve.py")


def _write_arm(prefix: Path, lift: list[int], drawer: list[int]) -> None:
    """Six seeds of two episodes of lift (a block task) and open drawer (a fixed-target task)."""
    for seed, (lifts, drawers) in zip(range(1000, 1006), zip(lift, drawer)):
        tasks = {name: {"success_rate": count / 2, "episodes": 2, "successes": count, "failures": []}
                 for name, count in (("lift_block", lifts), ("open_drawer", drawers))}
        Path(f"{prefix}_seed{seed}.json").write_text(json.dumps({"average_success": 0, "tasks": tasks}))


def test_each_group_is_averaged_over_seeds_and_the_trend_is_log_linear(tmp_path, capsys, script):
    _write_arm(tmp_path / "small", lift=[0] * 6, drawer=[2] * 6)
    _write_arm(tmp_path / "large", lift=[1] * 6, drawer=[2] * 6)
    out = tmp_path / "curve.png"
    script.main([str(out), f"small=100={tmp_path / 'small'}", f"large=400={tmp_path / 'large'}"])
    printed = capsys.readouterr().out
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in printed.splitlines()
            if line.startswith("| small") or line.startswith("| large")}
    assert rows["small"][1:] == ["100", "0.500 ± 0.000", "0.000 ± 0.000", "1.000 ± 0.000 |"]
    assert rows["large"][1:] == ["400", "0.750 ± 0.000", "0.500 ± 0.000", "1.000 ± 0.000 |"]
    # 0.25 over two doublings (all tasks), 0.5 over two (block tasks)
    assert "| 100 and 400 | +0.125 / +0.250 |" in printed
    # from 0.75 at 400 demonstrations, +0.125 a doubling reaches 0.89 after 1.12 doublings
    assert f"at about {400 * 2 ** (0.14 / 0.125):,.0f} demonstrations" in printed
    assert out.stat().st_size > 0


def test_the_goal_rate_gives_avg_len_3_5_over_five_tasks(script):
    rate = script.CHAIN_GOAL_RATE
    assert sum(rate ** k for k in range(1, 6)) >= 3.5 > sum((rate - 0.01) ** k for k in range(1, 6))


def test_a_trend_that_does_not_rise_never_reaches_the_goal(script):
    assert script.demos_for(0.89, (100, 200), (0.5, 0.5)) == math.inf
    assert script.demos_for(0.89, (100, 200), (0.6, 0.5)) == math.inf


def test_bad_arms_name_what_is_wrong(tmp_path, script):
    with pytest.raises(SystemExit, match="LABEL=DEMOS=PREFIX"):
        script.main([str(tmp_path / "x.png"), "small=many=prefix"])
    with pytest.raises(SystemExit, match="rising"):
        script.main([str(tmp_path / "x.png"), f"a=400={tmp_path}/a", f"b=100={tmp_path}/b"])
    with pytest.raises(SystemExit, match="no such evaluation"):
        script.main([str(tmp_path / "x.png"), f"a=100={tmp_path}/missing"])


def test_other_seeds_are_read_with_seeds_and_a_bad_range_names_the_option(tmp_path, capsys, script):
    _write_arm(tmp_path / "small", lift=[0] * 6, drawer=[2] * 6)
    _write_arm(tmp_path / "large", lift=[2, 2, 2, 0, 0, 0], drawer=[2] * 6)
    script.main(["--seeds", "1000-1002", str(tmp_path / "curve.png"), f"small=100={tmp_path / 'small'}",
                 f"large=200={tmp_path / 'large'}"])
    printed = capsys.readouterr().out
    assert "| large | 200 | 1.000 ± 0.000 | 1.000 ± 0.000 | 1.000 ± 0.000 |" in printed
    assert "Seeds 1000-1002" in printed
    with pytest.raises(SystemExit, match="--seeds"):
        script.main(["--seeds", "1002-1000", str(tmp_path / "curve.png")])
