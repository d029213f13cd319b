"""results/prelude_reset/compare_preludes.py: the README's tables from the stored evaluations. The episodes must be
paired by their seeds (a wrong derivation would make the won / lost counts up), and each chain's length must be
the stored reports' (their Avg. Len agrees only if every chain's seed is derived as evaluate derives it)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

RESULTS = Path(__file__).resolve().parents[1] / "results"


@pytest.fixture
def script(results_script):
    return results_script("prelude_reset/compare_preludes.py")


def test_the_paired_outcomes_add_up_to_each_stored_reports_successes(script):
    for _, prefix in script.PRELUDE_ROWS:
        outcomes = script.episode_outcomes(RESULTS, prefix)
        assert len(outcomes) == 72
        stored = sum(json.loads((RESULTS / f"{prefix}_seed{s}.json").read_text())["tasks"][t]["successes"]
                     for s in script.SEEDS for t in script.TASKS)
        assert sum(outcomes.values()) == stored


def test_the_chain_lengths_give_the_stored_avg_len_and_the_table_says_so(script):
    for _, prefix in script.CHAIN_ROWS:
        lengths = script.chain_lengths(RESULTS, prefix)
        stored = [json.loads((RESULTS / f"{prefix}_seed{s}.json").read_text())["chain_avg_len"] for s in script.CHAIN_SEEDS]
        assert len(lengths) == 80 and sum(lengths) / 80 == pytest.approx(sum(stored) / len(stored))
    text = script.tables(RESULTS)
    assert "| with `--home-first` | 1.86 ± 0.19 | 56 / 43 / 23 / 15 / 12 |" in text
    assert "**46**" in text and "**60** | 20 / 6 (p 0.009)" in text
