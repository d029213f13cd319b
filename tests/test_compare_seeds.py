"""results/follow_control/compare_seeds.py: models evaluated on the same six seeds, side by side."""

from __future__ import annotations

import json
from pathlib import Path

import pytest


@pytest.fixture
def script(results_script):
    return results_script("follow_control/compare_seeds.py")


def _write_model(prefix: Path, successes_per_seed: list[dict[str, int]], failed_first: bool = False,
                 first_seed: int = 1000) -> None:
    """Two episodes per task and seed (episode seeds 0 and 1): with `count` successes the last 2 - count fail, or
    the first ones where `failed_first`."""
    for seed, successes in zip(range(first_seed, first_seed + 6), successes_per_seed):
        def failures(count):
            return [{"seed": k} for k in (range(2 - count) if failed_first else range(count, 2))]
        tasks = {task: {"success_rate": count / 2, "episodes": 2, "successes": count, "failures": failures(count)}
                 for task, count in successes.items()}
        average = sum(row["success_rate"] for row in tasks.values()) / len(tasks)
        Path(f"{prefix}_seed{seed}.json").write_text(json.dumps({"average_success": average, "tasks": tasks}))


def test_totals_means_and_paired_differences(tmp_path, capsys, script):
    _write_model(tmp_path / "a", [{"lift_block": 1, "open_drawer": 2}] * 6)
    _write_model(tmp_path / "b", [{"lift_block": 2, "open_drawer": 2}] * 3 + [{"lift_block": 0, "open_drawer": 2}] * 3)
    out = tmp_path / "compare.png"
    script.main([str(out), f"first={tmp_path / 'a'}", f"second={tmp_path / 'b'}"])
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| first") or line.startswith("| second")}
    assert rows["first"][1:4] == ["6", "12", "18"] and rows["first"][4] == "0.750 ± 0.000"
    assert rows["first"][5:] == ["-", "- |"]
    # second: lift 2,2,2,0,0,0 -> 6 of 12; seed means 1.0 x3 and 0.5 x3 against 0.75: differences +-0.25
    assert rows["second"][1:4] == ["6", "12", "18"] and rows["second"][4] == "0.750 ± 0.112"
    # won: lift's second episode in seeds 1000-1002; lost: lift's first in seeds 1003-1005
    assert rows["second"][5:] == ["+0.000 ± 0.112", "3 / 3 (1.00) |"]
    assert out.stat().st_size > 0


def test_episodes_won_and_lost_are_counted_episode_by_episode(tmp_path, capsys, script):
    _write_model(tmp_path / "a", [{"lift_block": 1, "open_drawer": 2}] * 6)
    _write_model(tmp_path / "b", [{"lift_block": 1, "open_drawer": 1}] * 6, failed_first=True)
    script.main([str(tmp_path / "x.png"), f"a={tmp_path / 'a'}", f"b={tmp_path / 'a'}", f"c={tmp_path / 'b'}"])
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith(("| b ", "| c "))]
    assert [row[3] for row in rows] == ["18", "12"]
    # c wins lift's second episode and loses lift's first and open_drawer's first, in each of the six seeds
    assert [row[-1] for row in rows] == ["0 / 0 (1.00) |", "6 / 12 (0.24) |"]


def test_a_missing_seed_names_the_file(tmp_path, script):
    _write_model(tmp_path / "a", [{"lift_block": 1}] * 5)  # seed 1005 missing
    with pytest.raises(SystemExit, match="a_seed1005.json: no such evaluation"):
        script.main([str(tmp_path / "x.png"), f"a={tmp_path / 'a'}"])


def test_arguments_without_a_label_print_the_usage(tmp_path, script):
    with pytest.raises(SystemExit, match="LABEL=PREFIX"):
        script.main([str(tmp_path / "x.png"), str(tmp_path / "a")])


def _write_chains(prefix: Path, stopped: dict[int, dict[int, int]], seeds=(1003, 1004)) -> None:
    """Two chains per evaluation seed (chain seeds 1 and 2), five tasks each; `stopped[seed][chain]` = tasks done."""
    for seed in seeds:
        failures = [{"seed": chain, "completed": done} for chain, done in stopped.get(seed, {}).items()]
        Path(f"{prefix}_chains20_seed{seed}.json").write_text(json.dumps(
            {"chains": {"count": 2, "completed_at_least": [0.0] * 5, "failures": failures}}))


def test_chains_are_paired_chain_by_chain_even_when_every_model_completes_one(tmp_path, capsys, script):
    for name in ("a", "b"):
        _write_model(tmp_path / name, [{"lift_block": 1}] * 6)
    # chain (1004, 2) is completed by both models, so it is in neither file's failures
    _write_chains(tmp_path / "a", {1003: {1: 0, 2: 1}, 1004: {1: 2}})
    _write_chains(tmp_path / "b", {1003: {1: 1, 2: 3}, 1004: {1: 2}})
    script.main([str(tmp_path / "x.png"), f"a={tmp_path / 'a'}", f"b={tmp_path / 'b'}"])
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| a |") or line.startswith("| b |")}
    # lengths a: 0 1 2 5 (mean 2), b: 1 3 2 5 (mean 2.75); differences 1 2 0 0
    assert rows["a"][-2] == "2.000 ± 1.080" and rows["b"][-2] == "2.750 ± 0.854"
    assert rows["b"][-1] == "+0.750 ± 0.479 |"


def test_the_mcnemar_p_value_is_the_exact_two_sided_binomial_tail(script):
    mcnemar_p = script.mcnemar_p
    assert mcnemar_p(0, 0) == mcnemar_p(3, 3) == 1.0
    assert mcnemar_p(0, 5) == mcnemar_p(5, 0) == 2 / 32
    assert mcnemar_p(1, 9) == 2 * (1 + 10) / 1024


def test_other_seeds_are_read_with_seeds_and_a_bad_range_names_the_option(tmp_path, capsys, script):
    _write_model(tmp_path / "a", [{"lift_block": 2}] * 6, first_seed=1006)
    _write_model(tmp_path / "b", [{"lift_block": 0}] * 6, first_seed=1006)
    script.main(["--seeds", "1006-1011", str(tmp_path / "x.png"), f"a={tmp_path / 'a'}", f"b={tmp_path / 'b'}"])
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| b "))
    assert row.split(" | ")[2:] == ["0", "0.000 ± 0.000", "-1.000 ± 0.000", "0 / 12 (0.00) |"]
    with pytest.raises(SystemExit, match="a_seed1000.json: no such evaluation"):
        script.main([str(tmp_path / "x.png"), f"a={tmp_path / 'a'}"])
    with pytest.raises(SystemExit, match="--seeds: expected FIRST-LAST"):
        script.main(["--seeds", "1011-1006", str(tmp_path / "x.png"), f"a={tmp_path / 'a'}"])


def test_a_model_can_join_seeds_from_several_prefixes(tmp_path, capsys, script):
    _write_model(tmp_path / "old", [{"lift_block": 1}] * 6)  # seeds 1000-1005
    _write_model(tmp_path / "fresh", [{"lift_block": 2}] * 6, first_seed=1006)
    script.main(["--seeds", "1000-1011", str(tmp_path / "x.png"), f"joined={tmp_path / 'old'}+{tmp_path / 'fresh'}"])
    row = next(line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| joined"))
    assert row[1:3] == ["18", "18"]  # 6 x 1 from the old seeds, 6 x 2 from the fresh ones
    with pytest.raises(SystemExit, match=r"old_seed1012.json or .*fresh_seed1012.json: no such evaluation"):
        script.main(["--seeds", "1000-1012", str(tmp_path / "x.png"), f"joined={tmp_path / 'old'}+{tmp_path / 'fresh'}"])


def test_chain_seeds_reads_other_chain_files_and_a_bad_range_names_the_option(tmp_path, capsys, script):
    for name in ("a", "b"):
        _write_model(tmp_path / name, [{"lift_block": 1}] * 6)
    _write_chains(tmp_path / "a", {1003: {1: 0}, 1005: {1: 0, 2: 0}}, seeds=(1003, 1004, 1005, 1006))
    _write_chains(tmp_path / "b", {1003: {1: 1}, 1005: {1: 4, 2: 4}}, seeds=(1003, 1004, 1005, 1006))
    script.main(["--chain-seeds", "1003-1006", str(tmp_path / "x.png"), f"a={tmp_path / 'a'}", f"b={tmp_path / 'b'}"])
    out = capsys.readouterr().out
    assert "Avg. Len, 8 chains (seeds 1003, 1004, 1005, 1006)" in out
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in out.splitlines()
            if line.startswith("| a |") or line.startswith("| b |")}
    # a: 0, 0, 0 and five chains of 5 (mean 25/8); b: 1, 4, 4 and five of 5 (mean 34/8); differences 1, 4, 4
    assert rows["a"][-2].startswith("3.125") and rows["b"][-2].startswith("4.250")
    assert rows["b"][-1].startswith("+1.125")
    with pytest.raises(SystemExit, match="--chain-seeds: expected FIRST-LAST"):
        script.main(["--chain-seeds", "1006", str(tmp_path / "x.png"), f"a={tmp_path / 'a'}"])
