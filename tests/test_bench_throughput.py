"""`bench --throughput` (eval/throughput.py): each figure is a real run of the product's job, the table names every
worker count, and bad settings are refused naming the field."""

from __future__ import annotations

import pytest

from trivla_drake.eval.throughput import format_throughput, run_throughput
from trivla_drake.eval.throughput_config import ThroughputConfig


def test_collect_and_evaluate_figures_come_from_real_runs():
    config = ThroughputConfig(workers=[1], measure=["collect", "evaluate"], tasks=["turn_on_light"],
                              collect_episodes_per_task=1, policy="oracle", evaluate_episodes=1)
    result = run_throughput(config, progress=False)
    collect, evaluate = result["collect"]["1"], result["evaluate"]["1"]
    assert collect["demonstrations"] == 1 and collect["seconds"] > 0
    assert collect["per_minute"] == pytest.approx(60 / collect["seconds"])
    assert evaluate["episodes"] == 1 and evaluate["average_success"] == 1.0  # the oracle did the task
    table = format_throughput(result)
    assert "| collect: demonstrations / min |" in table and "| evaluate (oracle): episodes / min |" in table
    assert "feature cache" not in table  # not measured, not shown


def test_the_table_shows_the_speed_up_between_worker_counts():
    result = {"workers": [1, 2], "config": {"batch_size": 32, "policy": "trivla"},
              "collect": {"1": {"per_minute": 10.0}, "2": {"per_minute": 19.0}}}
    table = format_throughput(result)
    assert "| figure | 1 worker | 2 workers | 2 / 1 |" in table and "| 10.00 | 19.00 | 1.90x |" in table


@pytest.mark.parametrize("field, value, message", [
    ("workers", [], "pipeline.workers must be a non-empty list of integers >= 1"),
    ("workers", [0, 2], "pipeline.workers must be a non-empty list of integers >= 1"),
    ("measure", ["collect", "render"], "pipeline.measure: ['render']"),
    ("training_steps", 0, "pipeline.training_steps must be an integer >= 1"),
    ("tasks", ["dance"], "dance"),
])
def test_bad_settings_are_refused_naming_the_field(field, value, message):
    config = ThroughputConfig(**{field: value})
    with pytest.raises(ValueError) as error:
        config.validate()
    assert message in str(error.value)


def test_bench_takes_one_benchmark_at_a_time(capsys):
    from trivla_drake.cli import main

    assert main(["bench", "--model", "--throughput"]) == 2
    assert "--model and --throughput are two different benchmarks" in capsys.readouterr().err


def test_bench_throughput_json_carries_the_prelude_figure(capsys):
    import json

    from trivla_drake.cli import main

    assert main(["bench", "--throughput", "--json", "--set", "pipeline.workers=[1]", "--set",
                 "pipeline.measure=[collect_prelude]", "--set", "pipeline.tasks=[turn_off_light]", "--set",
                 "pipeline.collect_episodes_per_task=1"]) == 0
    figures = json.loads(capsys.readouterr().out)  # one JSON object, no progress bar on stdout
    prelude = figures["collect_prelude"]["1"]
    assert prelude["demonstrations"] == 1 and prelude["per_minute"] == pytest.approx(60 / prelude["seconds"])
    assert figures["workers"] == [1] and "collect" not in figures
