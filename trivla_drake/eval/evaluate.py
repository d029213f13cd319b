"""The closed-loop evaluation harness: per-task success rates (with standard errors) and CALVIN's
Avg. Len over chains of five tasks, for the oracle, the random baseline or a learned policy.

Episode i of task T uses the seed `derive_seed(seed, T, i)` and chain j `derive_seed(seed, "chain", j)`,
so a run with `workers` processes gives exactly the results of a serial run with the same seed.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict
from pathlib import Path

from trivla_drake.tasks.chains import CHAIN_LENGTH

from trivla_drake.eval.evaluate_config import (  # noqa: F401  (EvalConfig & co. are read from here too)
    EVAL_BASE_SEED,
    MAX_EPISODES,
    EvalConfig,
    check_episode_count,
)

_POLICY_CACHE: dict[tuple, object] = {}

# With a prelude: how many times an episode's scene is redrawn when the oracle's prelude fails or leaves the
# task no way to start (then the episode counts as a failure with the prelude's reason).
PRELUDE_REDRAWS = 10
# What `evaluate` writes into `EvalConfig.out`.
REPORT_FILE = "report.json"
CONFIG_FILE = "eval_config.yaml"


def _policy(spec: str, noise_scale: float | None = None, execute_steps: int | None = None,
            ensemble_decay: float | None = None, wrappers: tuple[tuple, ...] = ()):
    """The policy `spec` with these TriVLA inference settings inside the registered policy `wrappers` (each
    `PluginConfig.key()`), loaded once per process."""
    from trivla_drake.eval.plugin_config import PluginConfig
    from trivla_drake.eval.policies import load_policy
    from trivla_drake.eval.policy_wrappers import wrap_policy

    key = (spec, noise_scale, execute_steps, ensemble_decay, tuple(wrappers))
    if key not in _POLICY_CACHE:
        policy = load_policy(spec, noise_scale, execute_steps=execute_steps, ensemble_decay=ensemble_decay)
        _POLICY_CACHE[key] = wrap_policy(policy, [PluginConfig(name, dict(settings)) for name, settings in wrappers])
    return _POLICY_CACHE[key]


@functools.lru_cache(maxsize=None)
def _chain_prelude(tasks: int):
    """The episode start "chain_prelude" of `tasks` tasks (eval/episode_starts.py), made once per process."""
    from trivla_drake.eval.episode_starts import make_episode_start

    return make_episode_start("chain_prelude", tasks=tasks)


def _run_job(config: EvalConfig, job: tuple) -> dict:
    """One episode or chain, job = (kind, task name, index, base seed); top level so that workers can run it."""
    from trivla_drake.eval.episode import derive_seed, run_chain, run_episode

    policy = _policy(*config.policy_key())
    kind, name, index, base_seed = job
    video = _video_path(config, job) if config.record_dir is not None else None
    if kind == "episode":
        seed = derive_seed(base_seed, name, index)
        for redraw in range(PRELUDE_REDRAWS + 1):
            result = run_episode(
                name,
                seed if redraw == 0 else derive_seed(base_seed, name, index, "prelude", redraw),
                policy,
                paraphrase=config.paraphrases,
                image_size=config.image_size,
                video_path=video,
                max_steps=config.max_steps,
                start=_chain_prelude(config.prelude) if config.prelude else None,
                hold_check=config.hold_check,
            )
            if not result.start_failed:
                break
        return result.to_dict()
    return run_chain(
        derive_seed(base_seed, "chain", index),
        policy,
        paraphrase=config.paraphrases,
        image_size=config.image_size,
        video_path=video,
        max_steps=config.max_steps,
        hold_check=config.hold_check,
        **_benchmark_chain(config, index),
    ).to_dict()


def _video_path(config: EvalConfig, job: tuple) -> Path:
    """Where a job's video goes in `config.record_dir`."""
    kind, name, index, base_seed = job
    stem = f"{name}-{index:03d}" if kind == "episode" else f"chain-{index:03d}"
    return Path(config.record_dir) / (f"{stem}.mp4" if base_seed == config.seed else f"{stem}-seed{base_seed}.mp4")


@functools.lru_cache(maxsize=1)
def _benchmark_chains() -> tuple:
    """The fixed benchmark's chains, read once per process."""
    from trivla_drake.tasks.chain_benchmark import load_benchmark_chains

    return tuple(load_benchmark_chains())


def _benchmark_chain(config: EvalConfig, index: int) -> dict:
    """run_chain's keyword for chain `index` of `config`'s chain source: the fixed benchmark's chain, or none (drawn)."""
    return {"chain": _benchmark_chains()[index]} if config.chain_source == "benchmark" else {}


def _describe_job(job: tuple) -> str:
    kind, name, index, base_seed = job
    return f"{name} episode {index} (seed {base_seed})" if kind == "episode" else f"chain {index} (seed {base_seed})"


def run_jobs(config: EvalConfig, make_jobs: Callable[[], Iterable[tuple]], total: int, *, progress: bool,
             description: str, journal=None, unit: str = "episode") -> list[dict]:
    """Results of the `total` jobs `make_jobs()` yields, in order, drawn as they run (never listed up front), run in
    this process (`config.workers` 1), on a local Ray with `config.workers` processes, or on `config.ray_address`'s
    cluster. With a `journal` (eval/evaluation_journal.py), jobs it holds are not run again (unless their video is
    asked for and missing) and each new result is stored in it as it comes."""
    from tqdm import tqdm

    from trivla_drake.eval.rollout_runner import RolloutRunner

    def stored(job: tuple) -> dict | None:
        result = journal.result(job) if journal is not None else None
        if result is not None and config.record_dir is not None and not _video_path(config, job).exists():
            return None  # its video is wanted: run it again (the same result)
        return result

    reused = sum(stored(job) is not None for job in make_jobs()) if journal is not None else 0
    pending = total - reused
    bar = tqdm(total=total, initial=reused, desc=description, disable=not progress, unit=unit)
    if reused and progress:
        bar.write(f"{description}: {reused} of {total} results taken from {journal.path}")
    results: list[dict] = []
    ready: dict[int, dict] = {}  # results (stored, or run) waiting for those of the jobs before them
    running: deque = deque()  # (index, job) of the jobs sent to run, in order

    def draw() -> Iterator[tuple]:
        for index, job in enumerate(make_jobs()):
            result = stored(job)
            if result is None:
                running.append((index, job))
                yield job
            else:
                ready[index] = result

    def take_ready() -> None:
        while len(results) in ready:
            results.append(ready.pop(len(results)))

    try:
        if pending:
            with RolloutRunner(config.workers if pending > 1 else 1, config.ray_address) as runner:
                for result in runner.map_ordered(_run_job, config, draw(), describe=_describe_job):
                    index, job = running.popleft()
                    result = json.loads(json.dumps(result))  # as a stored one reads back
                    if journal is not None:
                        journal.append(job, result)
                    ready[index] = result
                    take_ready()
                    bar.update(1)
        else:
            for _ in draw():
                pass
        take_ready()
    finally:
        bar.close()
    return results


def summarize(config: EvalConfig, episodes: list[dict], chains: list[dict]) -> dict:
    """The JSON-able report: per-task rates with standard errors, their average, chain Avg. Len."""
    tasks: dict[str, dict] = {}
    for name in config.tasks if config.episodes else ():  # --episodes 0: chains only, no task rows
        mine = [e for e in episodes if e["task"] == name]
        n = len(mine)
        successes = sum(e["success"] for e in mine)
        rate, stderr = rate_and_stderr(successes, n)
        tasks[name] = {
            "success_rate": rate,
            "stderr": stderr,
            "episodes": n,
            "successes": successes,
            **(_lasting_counts(mine) if config.hold_check is not None else {}),
            "failures": [
                {"seed": e["seed"], "instruction": e["instruction"], "reason": e["reason"],
                 **({"prelude": e["prelude"]} if e.get("prelude") else {})}
                for e in mine
                if not e["success"]
            ],
        }
    report: dict = {
        "policy": config.policy,
        "seed": config.seed,
        "paraphrases": config.paraphrases,
        "episodes_per_task": config.episodes if config.tasks else 0,
        "average_success": (sum(t["success_rate"] for t in tasks.values()) / len(tasks)) if tasks else None,
        "tasks": tasks,
    }
    if config.hold_check is not None and tasks:
        report["average_lasting_success"] = sum(t["lasting_rate"] for t in tasks.values()) / len(tasks)
    if config.prelude and episodes:
        report["after_prelude_task"] = success_after_prelude_task(episodes)
    if chains:
        report.update(summarize_chains(chains))
    report["config"] = report_config(config)
    return report


# Where a run is placed (its workers, its Ray cluster, its folder): never a result, so not in the report, which is then
# byte-identical whoever runs it (eval_config.yaml beside it keeps them).
PLACEMENT_FIELDS = ("workers", "ray_address", "out")


def report_config(config: EvalConfig) -> dict:
    """The "config" of `config`'s report: its fields but the tasks (the report's rows name them) and its placement
    (PLACEMENT_FIELDS)."""
    return {k: v for k, v in asdict(config).items() if k not in ("tasks", *PLACEMENT_FIELDS)}


def write_report(config: EvalConfig, report: dict) -> dict[str, Path]:
    """Writes `report` as OUT/report.json, OUT/report.md (what the command prints) and OUT/report.png (its figure,
    eval/report_plot.py), and `config` as OUT/eval_config.yaml (OUT = `config.out`); their paths."""
    from trivla_drake.config_io import save_config
    from trivla_drake.data.durable import atomic_write_text
    from trivla_drake.eval.report_plot import plot_evaluation

    out = Path(config.out)
    files = {"config": out / CONFIG_FILE, "json": out / REPORT_FILE, "markdown": out / "report.md"}
    save_config(config, files["config"])
    atomic_write_text(files["json"], json.dumps(report, indent=2) + "\n")
    atomic_write_text(files["markdown"], format_markdown(report) + "\n")
    plot = plot_evaluation(report, out / "report.png")
    if plot is not None:
        files["plot"] = plot
    return files


def is_reported(config: EvalConfig) -> bool:
    """True when `config.out` holds the report of this very config (what `write_report` wrote)."""
    return bool(config.out) and report_has_config(Path(config.out) / REPORT_FILE, report_config(config))


def report_has_config(path: Path, expected: dict) -> bool:
    """True when the JSON report at `path` exists, reads, and its "config" is `expected` (as JSON reads it back)."""
    if not path.is_file():
        return False

    def settled(config: dict) -> dict:  # placement never decides a result (reports before it was left out have it)
        return {k: v for k, v in config.items() if k not in PLACEMENT_FIELDS}

    try:
        stored = settled(json.loads(path.read_text()).get("config"))
    except (OSError, ValueError, AttributeError):
        return False
    return stored == json.loads(json.dumps(settled(expected)))


def rate_and_stderr(count: int, n: int) -> tuple[float, float]:
    """A success rate over n episodes and its binomial standard error (0, 0 for no episodes)."""
    rate = count / n if n else 0.0
    return rate, math.sqrt(rate * (1 - rate) / n) if n else 0.0


def _lasting_counts(episodes: list[dict]) -> dict:
    """A task row's hold-check figures: successes that still held after the hold, their rate and its standard error."""
    lasting = sum(bool(e.get("lasted")) for e in episodes)
    rate, stderr = rate_and_stderr(lasting, len(episodes))
    return {"lasting_successes": lasting, "lasting_rate": rate, "lasting_stderr": stderr}


def _mean_and_stderr(values: list[int]) -> tuple[float, float]:
    """The mean and its standard error (sample variance, ddof 1; 0 for one value)."""
    n = len(values)
    mean = sum(values) / n
    var = sum((v - mean) ** 2 for v in values) / (n - 1) if n > 1 else 0.0
    return mean, math.sqrt(var / n)


def summarize_chains(chains: list[dict]) -> dict:
    """Avg. Len with its standard error and the `chains` summary of chain results (each a dict with `seed`,
    `completed`, `reason` and `subtasks`, a list of dicts with `task`), as `evaluate --chains` and
    `demo --chains` report them."""
    completed = [c["completed"] for c in chains]
    n = len(completed)
    mean, stderr = _mean_and_stderr(completed)
    summary = {
        "count": n,
        # CALVIN's table: the fraction of chains that completed at least k tasks, k = 1..5.
        "completed_at_least": [sum(c >= k for c in completed) / n for k in range(1, CHAIN_LENGTH + 1)],
        "failures": [
            {"seed": c["seed"], "completed": c["completed"], "reason": c["reason"]} for c in chains if c["reason"]
        ],
        # Each chain's tasks in order, up to and including the one that failed (older reports lack it).
        "tasks": [[s["task"] for s in c.get("subtasks", ())] for c in chains],
        # Each chain's tasks done, in chain order (reports before session 66 lack it).
        "completed": completed,
    }
    summary["by_position"] = chain_success_by_position(summary["tasks"], completed)
    out = {"chain_avg_len": mean, "chain_avg_len_stderr": stderr, "chains": summary}
    if all("completed_lasting" in c for c in chains):  # chains run with a hold check
        summary["completed_lasting"] = [c["completed_lasting"] for c in chains]
        out["chain_avg_len_lasting"], out["chain_avg_len_lasting_stderr"] = _mean_and_stderr(
            summary["completed_lasting"])
    return out


def chain_success_by_position(tasks: list[list[str]], completed: list[int]) -> list[dict]:
    """Per chain position k = 1..5: how many chains tried a k-th task, how many did it, and which failed.

    The k-th task is tried only after k - 1 successes, so this is CALVIN's "completed at least k" table
    taken apart into conditional rates: where along a chain the policy breaks, and on what.
    """
    rows = []
    for k in range(CHAIN_LENGTH):
        tried = [(t, c) for t, c in zip(tasks, completed) if len(t) > k]
        failed = sorted(t[k] for t, c in tried if c == k)
        rows.append({"position": k + 1, "tried": len(tried), "succeeded": len(tried) - len(failed), "failed_tasks": failed})
    return rows


def success_after_prelude_task(episodes: list[dict]) -> dict[str, dict]:
    """Per task the prelude ended with (the one just before the episode's): episodes tried and succeeded,
    sorted by name; episodes whose prelude never completed are left out (they have no such task)."""
    rows: dict[str, dict] = {}
    for e in episodes:
        if e.get("prelude"):
            row = rows.setdefault(e["prelude"][-1], {"tried": 0, "succeeded": 0})
            row["tried"] += 1
            row["succeeded"] += int(bool(e["success"]))
    return dict(sorted(rows.items()))


def evaluate(config: EvalConfig, *, progress: bool = True) -> dict:
    """Run the episodes and chains of `config` and return the report (see `summarize`), also written into
    `config.out` when set (`write_report`)."""
    config.validate()
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(config.rollout_threads())  # a serial run's threads; with Ray, each worker's 1
    try:
        report = _evaluate(config, progress)
    finally:
        torch.set_num_threads(threads)
    if config.out is not None:
        write_report(config, report)
    return report


def _evaluate(config: EvalConfig, progress: bool) -> dict:
    """`evaluate`'s runs and report, in this process's thread setting."""
    from trivla_drake.eval.rollout_runner import RolloutRunner

    _policy(*config.policy_key())  # fail early (unknown policy, no checkpoint loader) before any work
    journal = None
    if config.out is not None:
        from trivla_drake.eval.evaluation_journal import EvaluationJournal, journal_key

        journal = EvaluationJournal(config.out, journal_key(config))
    seeds = config.seed_list()
    # Drawn as they run, never listed up front: for each seed, episode i of every task, then i + 1, ...
    def episode_jobs():
        return (("episode", name, i, seed) for seed in seeds for i in range(config.episodes) for name in config.tasks)

    def chain_jobs():
        return (("chain", "chain", j, seed) for seed in seeds for j in range(config.chains))

    def pending(jobs) -> bool:
        return journal is None or any(journal.result(job) is None for job in jobs)

    count = config.episodes * len(config.tasks) * len(seeds)
    # Episodes and chains both to run: one Ray for both (each run_jobs joins it), not one started after the other.
    both = bool(count and config.chains) and pending(episode_jobs()) and pending(chain_jobs())
    with RolloutRunner(config.workers, config.ray_address) if both else contextlib.nullcontext():
        episodes = run_jobs(config, episode_jobs, count, progress=progress, description=f"evaluate {config.policy}",
                            journal=journal) if count else []
        chains = run_jobs(config, chain_jobs, config.chains * len(seeds), progress=progress, description="chains",
                          journal=journal, unit="chain") if config.chains else []
    if config.seeds is None:
        return summarize(config, episodes, chains)
    return summarize_seeds(config, episodes, chains)


def summarize_seeds(config: EvalConfig, episodes: list[dict], chains: list[dict]) -> dict:
    """The report of a run over several base seeds: `summarize` of all of them pooled (rates over every episode,
    binomial standard errors), plus `per_seed` (each seed's average success and Avg. Len) and the spread across seeds
    (`across_seeds`: the mean of the per-seed figures and its standard error, the figure to compare models by when
    their seeds are paired)."""
    import dataclasses

    seeds = config.seed_list()
    per_episode = config.episodes * len(config.tasks)
    per_seed = []
    for k, seed in enumerate(seeds):
        one = summarize(dataclasses.replace(config, seed=seed, seeds=None),
                        episodes[k * per_episode:(k + 1) * per_episode],
                        chains[k * config.chains:(k + 1) * config.chains])
        per_seed.append({"seed": seed, "average_success": one["average_success"],
                         **({"chain_avg_len": one["chain_avg_len"]} if "chain_avg_len" in one else {})})
    report = summarize(config, episodes, chains)
    if chains and config.chain_source == "benchmark" and len(seeds) > 1 and config.chains > 1:
        # Every seed runs the same benchmark chains (other policy noise), so the pooled chains are not independent:
        # the standard error is over the chains, each chain's tasks done averaged over the seeds.
        def over_chains(field: str) -> float:
            per_chain = [sum(chains[k * config.chains + j][field] for k in range(len(seeds))) / len(seeds)
                         for j in range(config.chains)]
            return _mean_and_stderr(per_chain)[1]

        report["chain_avg_len_stderr"] = over_chains("completed")
        if "chain_avg_len_lasting_stderr" in report:
            report["chain_avg_len_lasting_stderr"] = over_chains("completed_lasting")
        report["chains"]["stderr_over"] = "benchmark chains, each averaged over the seeds"
    report["seed"] = None
    report["seeds"] = seeds
    report["per_seed"] = per_seed
    across = {}
    for figure in ("average_success", "chain_avg_len"):
        values = [row[figure] for row in per_seed if row.get(figure) is not None]
        if values:
            across[figure], across[f"{figure}_stderr"] = _mean_and_stderr(values)
    report["across_seeds"] = across
    report["config"] = report_config(config)
    return report


def format_chain_markdown(report: dict) -> list[str]:
    """The Markdown lines of a report's chains (CALVIN's table, Avg. Len, success by position); none without."""
    if "chain_avg_len" not in report:
        return []
    c = report["chains"]
    lines = [
        "",
        "| chains | 1/5 | 2/5 | 3/5 | 4/5 | 5/5 | Avg. Len |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        f"| {c['count']} | " + " | ".join(f"{x:.2f}" for x in c["completed_at_least"])
        + f" | {report['chain_avg_len']:.2f}"
        + (f" ± {report['chain_avg_len_stderr']:.2f} |" if c["count"] > 1 else " (one chain) |"),
    ]
    if "chain_avg_len_lasting" in report:
        hold = report.get("config", {}).get("hold_check")
        held = f" {hold:g} s" if hold is not None else ""
        lines += ["", f"Every success was followed by a{held} hold of the hand, and the next task started after it: "
                  "the Avg. Len above counts the successes as the predicates first held, in these chains.",
                  f"Avg. Len counting only successes that still held after the hand was held still{held}: "
                  f"{report['chain_avg_len_lasting']:.2f}"
                  + (f" ± {report['chain_avg_len_lasting_stderr']:.2f}" if c["count"] > 1 else "")]
    if "by_position" in c:
        lines += [
            "",
            "| chain position | 1 | 2 | 3 | 4 | 5 |",
            "| --- | --- | --- | --- | --- | --- |",
            "| succeeded / tried | " + " | ".join(f"{r['succeeded']} / {r['tried']}" for r in c["by_position"]) + " |",
            "| success rate | " + " | ".join(f"{r['succeeded'] / r['tried']:.2f}" if r["tried"] else "-"
                                             for r in c["by_position"]) + " |",
        ]
    return lines


def format_seeds_markdown(report: dict) -> list[str]:
    """The Markdown lines of a several-seed report's per-seed figures and their mean and standard error."""
    chains = any("chain_avg_len" in row for row in report["per_seed"])
    lines = ["", "| seed | average success |" + (" Avg. Len |" if chains else ""),
             "| --- | --- |" + (" --- |" if chains else "")]
    for row in report["per_seed"]:
        success = "" if row["average_success"] is None else f"{row['average_success']:.3f}"
        lines.append(f"| {row['seed']} | {success} |" + (f" {row['chain_avg_len']:.2f} |" if chains else ""))
    across = report["across_seeds"]
    cells = [f"{across[k]:.3f} ± {across[k + '_stderr']:.3f}" if k in across else ""
             for k in ("average_success", "chain_avg_len")]
    lines.append(f"| **mean ± s.e. across seeds** | {cells[0]} |" + (f" {cells[1]} |" if chains else ""))
    return lines


def format_markdown(report: dict) -> str:
    """The report as a Markdown table (one row per task, then the average and chains)."""
    seeds = report.get("seeds")
    lines = [
        f"policy: {report['policy']}, " + (f"seed {report['seed']}" if not seeds else
                                           f"seeds {', '.join(map(str, seeds))} (pooled)")
        + (", held-out paraphrases" if report["paraphrases"] else ""),
    ]
    if report["tasks"]:
        lasting = "average_lasting_success" in report  # a run with a hold check: two more columns
        held = f" still a success after {report['config']['hold_check']:g} s held | std. error |" if lasting else ""
        lines += ["", f"| task | success | std. error |{held} episodes |", "| --- |" + " --- |" * (5 if lasting else 3)]
        for name, row in report["tasks"].items():
            cells = f" {row['lasting_rate']:.3f} | {row['lasting_stderr']:.3f} |" if lasting else ""
            lines.append(f"| {name} | {row['success_rate']:.3f} | {row['stderr']:.3f} |{cells} {row['episodes']} |")
        cells = f" **{report['average_lasting_success']:.3f}** | |" if lasting else ""
        lines.append(f"| **average** | **{report['average_success']:.3f}** | |{cells} |")
    lines += format_chain_markdown(report)
    if seeds:
        lines += format_seeds_markdown(report)
    if report.get("after_prelude_task"):
        rows = report["after_prelude_task"]
        lines += ["", "| after the prelude's last task | " + " | ".join(rows) + " |",
                  "| --- |" + " --- |" * len(rows),
                  "| succeeded / tried | " + " | ".join(f"{r['succeeded']} / {r['tried']}" for r in rows.values()) + " |"]
    failures = [(name, f) for name, row in report["tasks"].items() for f in row["failures"]]
    failures += [(f"chain ({f['completed']}/5 done)", f) for f in report.get("chains", {}).get("failures", [])]
    if failures:
        lines += ["", "failures:"]
        for name, f in failures[:20]:
            after = f" after {', '.join(f['prelude'])}" if f.get("prelude") else ""
            lines.append(f"- {name} (seed {f['seed']}{after}): {f['reason']}")
        if len(failures) > 20:
            lines.append(f"- ... {len(failures) - 20} more")
    return "\n".join(lines)
