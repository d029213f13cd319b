"""The paper's tables for our suite from one call: success over seeds, chains, the sub-system
ablation (Table 4), data efficiency (Table 1 bottom), paraphrases and latency-aware simulation.

Checkpoints by role (only `full` is required; a missing role leaves its rows out):
  full        Systems 1+2+3 trained on 100% of the demonstrations
  system1_3   trained without System 2            system1   trained without Systems 2 and 3
  data10      Systems 1+2+3 trained on 10% of the demonstrations

With `evaluations_dir()` set (by default OUT/evaluations/), each evaluation (one checkpoint, one seed,
one setting) is stored there as JSON, named by a hash of the checkpoint's files and the settings, and
written atomically: a killed run, or a later run with another checkpoint added, redoes only what is
missing, and a retrained checkpoint never reuses stale results.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import json
import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from trivla_drake.data.durable import atomic_write_text
from trivla_drake.eval.evaluate import EvalConfig, evaluate
from trivla_drake.eval.tables_config import ROLES, TablesConfig  # noqa: F401  (read from here too)

# What `write_tables` names the config that made a report.
CONFIG_FILE = "tables_config.yaml"
ABLATION_ROWS = (("system1", "1"), ("system1_3", "1+3"), ("full", "1+2+3"))


def _mean_stderr(values: list[float]) -> tuple[float, float]:
    """Mean and standard error (ddof 1) over the seeds' values; NaN error for one seed (it has none)."""
    array = np.asarray(values, dtype=float)
    if len(array) < 2:
        return float(array.mean()), float("nan")
    return float(array.mean()), float(array.std(ddof=1) / math.sqrt(len(array)))


def _pm(mean: float, stderr: float) -> str:
    """'0.81 ± 0.06', or '0.81 (one seed)' where there is no standard error."""
    return f"{mean:.2f} (one seed)" if math.isnan(stderr) else f"{mean:.2f} ± {stderr:.2f}"


@functools.lru_cache(maxsize=None)
def _checkpoint_fingerprint(checkpoint: str) -> str:
    """`checkpoint_digest` of a checkpoint (computed once per path and process)."""
    from trivla_drake.nn.checkpoint import checkpoint_digest

    return checkpoint_digest(checkpoint)


def stored_evaluation_path(results_dir: str | Path, checkpoint: str, settings: dict) -> Path:
    """Where `tables` keeps the evaluation of `checkpoint`'s present contents with `settings` (as stored in the file):
    RESULTS_DIR/<24 hex digits of the key's sha256>.json."""
    key = json.dumps({"checkpoint": _checkpoint_fingerprint(checkpoint), **settings}, sort_keys=True)
    return Path(results_dir) / f"{hashlib.sha256(key.encode()).hexdigest()[:24]}.json"


def _stored(config: TablesConfig, checkpoint: str, settings: dict, compute) -> dict:
    """compute() once per (checkpoint contents, settings) when evaluations are stored, else every call."""
    results_dir = config.evaluations_dir()
    if results_dir is None:
        return compute()
    # Settings added later are keyed only when they differ from the default, so results stored before
    # they existed still match.
    inference = config.inference
    if inference.noise_scale is not None:
        settings = {**settings, "noise_scale": float(inference.noise_scale)}
    if inference.execute_steps is not None:
        settings = {**settings, "execute_steps": int(inference.execute_steps)}
    if inference.ensemble_decay is not None:
        settings = {**settings, "ensemble_decay": float(inference.ensemble_decay)}
    if config.threads != 1:  # TriVLA's results depend on torch's thread count (reduction order)
        settings = {**settings, "threads": config.threads}
    path = stored_evaluation_path(results_dir, checkpoint, settings)
    if path.exists():
        try:
            return json.loads(path.read_text())["result"]
        except (json.JSONDecodeError, KeyError):
            pass  # unreadable: compute it again
    result = compute()
    atomic_write_text(path, json.dumps({"checkpoint": checkpoint, "settings": settings, "result": result}))
    return result


def _over_seeds(config: TablesConfig, checkpoint: str, *, paraphrases: bool = False, chains: int = 0) -> dict:
    def one_seed(seed: int) -> dict:
        eval_config = EvalConfig(policy=checkpoint, tasks=config.tasks, episodes=config.episodes, seed=seed,
                                 chains=chains, paraphrases=paraphrases, workers=config.workers,
                                 ray_address=config.ray_address, chain_source=config.chain_source,
                                 max_steps=config.max_steps, inference=copy.deepcopy(config.inference),
                                 threads=config.threads)
        settings = {"kind": "evaluate", "tasks": list(config.tasks), "episodes": config.episodes, "seed": seed,
                    "chains": chains, "paraphrases": paraphrases, "max_steps": config.max_steps}
        # Chains drawn from the seed keep the key of evaluations stored before the fixed benchmark existed.
        if chains and eval_config.chain_source != "drawn":
            from trivla_drake.tasks.chain_benchmark import BENCHMARK_SHA256

            # the benchmark's chains themselves: a regenerated benchmark never reads evaluations of the old one
            settings["chain_source"] = eval_config.chain_source
            settings["benchmark_sha256"] = BENCHMARK_SHA256
        return _stored(config, checkpoint, settings, lambda: evaluate(eval_config, progress=False))

    reports = [one_seed(seed) for seed in config.seeds]
    tasks = {name: dict(zip(("success_rate", "stderr"), _mean_stderr([r["tasks"][name]["success_rate"] for r in reports])))
             for name in config.tasks}
    result = {"tasks": tasks}
    result["average_success"], result["average_stderr"] = _mean_stderr([r["average_success"] for r in reports])
    if chains:
        result["chain_avg_len"], result["chain_avg_len_stderr"] = _mean_stderr([r["chain_avg_len"] for r in reports])
    return result


def _model_figures(checkpoint: str, repeats: int = 5) -> dict:
    """Parameters [M] and median latency [ms] of one full inference of a checkpoint's model."""
    from trivla_drake.nn import load_checkpoint
    from trivla_drake.nn.benchmark import example_observation

    model = load_checkpoint(checkpoint).eval()
    observation = example_observation(model.image_size, model.config.policy.state_dim)
    times = []
    for i in range(repeats + 1):
        start = time.perf_counter()
        model.predict_action_chunk(observation, seed=i)
        times.append(time.perf_counter() - start)
    return {"params_millions": model.parameter_counts()["total"] / 1e6,
            "latency_ms": 1e3 * float(np.median(times[1:]))}


def _latency_rows(config: TablesConfig, checkpoint: str) -> dict:
    from trivla_drake.eval.demo import run_trivla_demo
    from trivla_drake.nn import load_checkpoint
    from trivla_drake.systems.latency import LatencyModel
    from trivla_drake.systems.trivla_policy import PolicyRates

    model = load_checkpoint(checkpoint).eval()
    inference = config.inference
    if inference.noise_scale is not None:
        model.set_initial_noise_scale(inference.noise_scale)
    rows = {}
    for label, latency in (("latency off", LatencyModel("zero")), ("latency measured", LatencyModel("measured"))):
        successes, control = [], []
        for task in config.latency_tasks:
            max_seconds = config.max_steps / 36.0 if config.max_steps else None
            # The stage offset keys the Drake pipeline: rows stored before its stages ran in order are
            # recomputed; so does `camera_frames` (rows from before the policy read the cameras as rendered at
            # its tick, session 65); a later change of the pipeline's behaviour needs a key of its own.
            settings = {"kind": "demo", "task": task, "episodes": config.latency_episodes, "seed": config.seeds[0],
                        "latency": label, "max_seconds": max_seconds, "stage_offset_s": PolicyRates.stage_offset_s,
                        "camera_frames": "rendered_at_tick"}
            report = _stored(config, checkpoint, settings, lambda: run_trivla_demo(
                model, task, episodes=config.latency_episodes, seed=config.seeds[0], latency=latency,
                max_seconds=max_seconds, execute_steps=inference.execute_steps,
                ensemble_decay=inference.ensemble_decay).as_dict())
            successes.append(report["success_rate"])
            control.append(report["control_hz"])
        rows[label] = {"success_rate": float(np.mean(successes)), "control_hz": float(np.mean(control))}
    return rows


def make_tables(config: TablesConfig) -> dict:
    """Run every evaluation the checkpoints allow; returns the JSON-able report."""
    config.validate()
    from trivla_drake.eval.rollout_runner import RolloutRunner

    ckpt = config.checkpoints
    # Timed first, with no Ray workers alive beside them: each model's size and inference latency.
    figures = {role: _model_figures(ckpt[role]) for role, _ in ABLATION_ROWS if role in ckpt}
    report: dict = {"config": asdict(config)}
    # One local Ray (or one connection to the cluster) for all the evaluations: each joins it instead of starting and
    # stopping its own, twice per checkpoint and seed.
    with RolloutRunner(config.workers, config.ray_address):
        report["main"] = _over_seeds(config, ckpt["full"], chains=config.chains)
        report["paraphrases"] = _over_seeds(config, ckpt["full"], paraphrases=True)
        report["ablation"] = []
        for role, label in ABLATION_ROWS:
            if role not in ckpt:
                continue
            row = {"systems": label, **figures[role]}
            row.update(_over_seeds(config, ckpt[role], chains=config.chains) if role != "full" else report["main"])
            report["ablation"].append({k: row[k] for k in ("systems", "params_millions", "latency_ms",
                                                          "average_success", "chain_avg_len", "chain_avg_len_stderr")
                                       if k in row})
        if "data10" in ckpt:
            report["data10"] = _over_seeds(config, ckpt["data10"])
            report["data_efficiency"] = {"100%": report["main"]["average_success"],
                                         "10%": report["data10"]["average_success"]}
    report["latency"] = _latency_rows(config, ckpt["full"])  # the Drake systems, timed after Ray has stopped
    return report


def format_tables(report: dict) -> str:
    """The report as Markdown tables."""
    main = report["main"]
    cfg = report.get("config", {})
    inference = cfg.get("inference", cfg)  # reports before issue 74 kept these settings at the top
    lines = []
    if cfg:
        lines += [f"Settings: {cfg['episodes']} episodes per task and seed, seeds {', '.join(map(str, cfg['seeds']))} "
                  f"(each seed's mean is one sample of the stderr), {cfg['chains']} five-task chains per seed, "
                  f"latency rows {cfg['latency_episodes']} episodes on each of {', '.join(cfg['latency_tasks'])}"
                  + (f", System 1 sampling noise scale {inference['noise_scale']:g}"
                     if inference.get("noise_scale") is not None else "")
                  + (f", replanning every {inference['execute_steps']} control steps"
                     if inference.get("execute_steps") is not None else "")
                  + (f", chunks ensembled with decay {inference['ensemble_decay']:g}"
                     if inference.get("ensemble_decay") is not None else "") + ".", ""]
    data10 = report.get("data10")
    lines += ["## Per-task success (mean ± stderr over seeds)", "",
              "| task | success | held-out paraphrases |" + (" 10% of the demonstrations |" if data10 else ""),
              "| --- | --- | --- |" + (" --- |" if data10 else "")]
    for name, row in main["tasks"].items():
        para = report["paraphrases"]["tasks"][name]
        lines.append(f"| {name} | {_pm(row['success_rate'], row['stderr'])} | "
                     f"{_pm(para['success_rate'], para['stderr'])} |"
                     + (f" {_pm(data10['tasks'][name]['success_rate'], data10['tasks'][name]['stderr'])} |"
                        if data10 else ""))
    lines.append(f"| **average** | **{_pm(main['average_success'], main['average_stderr'])}** | "
                 f"{_pm(report['paraphrases']['average_success'], report['paraphrases']['average_stderr'])} |"
                 + (f" {_pm(data10['average_success'], data10['average_stderr'])} |" if data10 else ""))
    if "chain_avg_len" in main:
        lines += ["", f"5-task chains: Avg. Len {_pm(main['chain_avg_len'], main['chain_avg_len_stderr'])}"]
    if report["ablation"]:
        lines += ["", "## Sub-system ablation (Table 4)", "", "| systems | Avg. Len | success | latency [ms] | params [M] |",
                  "| --- | --- | --- | --- | --- |"]
        for row in report["ablation"]:
            lines.append(f"| {row['systems']} | {row.get('chain_avg_len', float('nan')):.2f} | "
                         f"{row['average_success']:.2f} | {row['latency_ms']:.1f} | {row['params_millions']:.2f} |")
    if data10:
        lines += ["", "## Data efficiency (Table 1 bottom)", "", "| demonstrations | success |", "| --- | --- |"]
        lines += [f"| {share} | {_pm(result['average_success'], result['average_stderr'])} |"
                  for share, result in (("100%", main), ("10%", data10))]
        recipe = report.get("data100_recipe")  # a joined report: the 100% row of the 10% arm's own recipe
        if recipe:
            lines.append(f"| {recipe['label']} | {_pm(recipe['average_success'], recipe['average_stderr'])} |")
    lines += ["", "## Latency-aware simulation", "", "| simulation | success | control Hz (sim time) |", "| --- | --- | --- |"]
    for label, row in report["latency"].items():
        lines.append(f"| {label} | {row['success_rate']:.2f} | {row['control_hz']:.1f} |")
    if report.get("notes"):
        lines += ["", "Notes:", ""] + [f"- {note}" for note in report["notes"]]
    return "\n".join(lines)


def plot_tables(report: dict, out_dir: Path) -> list[Path]:
    """Bar charts: per-task success, and the ablation; returns the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    names = list(report["main"]["tasks"])
    fig, ax = plt.subplots(figsize=(10, 4))
    x = np.arange(len(names))
    series = [("main", "training instructions"), ("paraphrases", "held-out paraphrases")]
    if "data10" in report:
        series.append(("data10", "10% of the demonstrations"))
    width = 0.76 / len(series)
    for offset, (key, label) in enumerate(series):
        rows = report[key]["tasks"]
        ax.bar(x + (offset - (len(series) - 1) / 2) * width, [rows[n]["success_rate"] for n in names], width,
               yerr=[np.nan_to_num(rows[n]["stderr"]) for n in names], label=label, capsize=2)
    ax.set_xticks(x, names, rotation=40, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate")
    ax.legend()
    fig.tight_layout()
    paths.append(out_dir / "per_task_success.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    if report["ablation"]:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        rows = report["ablation"]
        ax.bar([r["systems"] for r in rows], [r.get("chain_avg_len", 0.0) for r in rows],
               yerr=[np.nan_to_num(r.get("chain_avg_len_stderr", 0.0)) for r in rows], capsize=3, color="tab:orange")
        for i, r in enumerate(rows):
            ax.text(i, 0.05, f"{r['latency_ms']:.0f} ms\n{r['params_millions']:.1f} M", ha="center", fontsize=8)
        ax.set_ylabel("Avg. Len (5-task chains)")
        ax.set_ylim(0, 5)
        ax.set_title("Sub-system ablation")
        fig.tight_layout()
        paths.append(out_dir / "ablation.png")
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    return paths


def write_tables(report: dict, out_dir: str | Path, config: TablesConfig | None = None) -> dict[str, Path]:
    """Write report.json, report.md, the plots and (given the `config` that made the report) tables_config.yaml
    into `out_dir`."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"json": out_dir / "report.json", "markdown": out_dir / "report.md"}
    if config is not None:
        from trivla_drake.config_io import save_config

        files["config"] = out_dir / CONFIG_FILE
        save_config(config, files["config"])
    files["json"].write_text(json.dumps(report, indent=2))
    files["markdown"].write_text(format_tables(report) + "\n")
    for path in plot_tables(report, out_dir):
        files[path.stem] = path
    return files
