"""`evaluate --seeds` over benchmark chains: every seed runs the same chains, so the pooled Avg. Len's standard error is
taken over the chains (each averaged over its seeds), not over chains x seeds as if they were independent; and an
evaluation with both episodes and chains to run starts one Ray for both."""

import math

from trivla_drake.eval.evaluate import EvalConfig, summarize_seeds


def _chains(completed):
    return [{"seed": 7, "completed": c, "reason": "" if c == 5 else "timeout", "subtasks": [{"task": "lift_block"}]}
            for c in completed]


def test_pooled_chain_stderr_is_over_the_chains_when_seeds_repeat_them():
    per_seed = [0, 1, 2, 3, 4, 5]  # the same outcomes on both seeds: a second seed adds no information
    config = EvalConfig(episodes=0, chains=len(per_seed), seeds=[1000, 1001])
    report = summarize_seeds(config, [], _chains(per_seed + per_seed))
    mean = sum(per_seed) / len(per_seed)
    over_chains = math.sqrt(sum((c - mean) ** 2 for c in per_seed) / (len(per_seed) - 1) / len(per_seed))
    assert report["chain_avg_len"] == mean
    assert math.isclose(report["chain_avg_len_stderr"], over_chains)  # not over_chains / sqrt(2)
    assert report["chains"]["stderr_over"].startswith("benchmark chains")


def test_drawn_chains_of_other_seeds_stay_independent():
    config = EvalConfig(episodes=0, chains=3, seeds=[1000, 1001], chain_source="drawn")
    completed = [0, 2, 4, 1, 3, 5]
    report = summarize_seeds(config, [], _chains(completed))
    mean = sum(completed) / 6
    pooled = math.sqrt(sum((c - mean) ** 2 for c in completed) / 5 / 6)
    assert math.isclose(report["chain_avg_len_stderr"], pooled) and "stderr_over" not in report["chains"]


def test_episodes_and_chains_to_run_share_one_runner(monkeypatch, tmp_path):
    from trivla_drake.eval import evaluate as evaluate_module
    from trivla_drake.eval import rollout_runner

    state = {"open": 0, "entered": 0, "runs_inside": []}

    class Runner:
        def __init__(self, workers, address):
            pass

        def __enter__(self):
            state["open"] += 1
            state["entered"] += 1

        def __exit__(self, *exc):
            state["open"] -= 1

    def run_jobs(config, make_jobs, total, **kwargs):
        state["runs_inside"].append(state["open"] > 0)
        return []

    monkeypatch.setattr(rollout_runner, "RolloutRunner", Runner)
    monkeypatch.setattr(evaluate_module, "run_jobs", run_jobs)
    config = EvalConfig(policy="oracle", tasks=["lift_block"], episodes=1, chains=2, workers=2)
    evaluate_module._evaluate(config, progress=False)
    assert state == {"open": 0, "entered": 1, "runs_inside": [True, True]}

    state.update(entered=0, runs_inside=[])
    evaluate_module._evaluate(EvalConfig(policy="oracle", tasks=["lift_block"], episodes=1, workers=2), progress=False)
    assert state["entered"] == 0  # episodes only: run_jobs starts (or skips) its own


def test_one_benchmark_chain_over_seeds_keeps_the_pooled_stderr_and_lasting_follows():
    config = EvalConfig(episodes=0, chains=1, seeds=[1000, 1001, 1002])
    report = summarize_seeds(config, [], _chains([1, 3, 2]))
    assert report["chain_avg_len_stderr"] > 0 and "stderr_over" not in report["chains"]  # not "± 0.00" from 1 chain

    lasting = _chains([2, 4, 2, 4])
    for chain, held in zip(lasting, [1, 3, 1, 3]):
        chain["completed_lasting"] = held
    report = summarize_seeds(EvalConfig(episodes=0, chains=2, seeds=[1000, 1001]), [], lasting)
    assert report["chain_avg_len_stderr"] == report["chain_avg_len_lasting_stderr"] == 1.0  # both over the 2 chains
