"""Issue 76's throughput question: how much faster are collect and evaluate than before Ray (commit c27a062)?

Runs each command of the old tree (a git worktree of c27a062, put first on PYTHONPATH) and of this one, alternating,
in fresh processes timed by wall clock from start to exit (imports, Ray start-up and all), and prints the rates and
their ratios measured in this one run (the machine is shared: only ratios of one run compare).

    git worktree add /tmp/old c27a062
    python research/throughput/compare.py --old /tmp/old --out research/throughput/figures.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

# (name, command after `trivla-drake`, what one run produces: demonstrations or episodes)
JOBS = {
    "collect": (["collect", "--episodes-per-task", "{n}", "--no-progress", "--json"], "demonstrations"),
    "collect_prelude": (["collect", "--episodes-per-task", "{n}", "--no-progress", "--json",
                         "--set", "prelude_tasks=4"], "demonstrations"),
    "evaluate": (["evaluate", "--policy", "trivla", "--episodes", "{n}", "--no-progress", "--json"], "episodes"),
    # not a CLI command: cache_run.py, the shipped model's features of the first 12 episodes of --dataset
    "feature_cache": ([], "episodes"),
}
HERE = os.path.dirname(os.path.abspath(__file__))


def run(tree: str | None, job: str, workers: int, n: int, dataset: str | None = None) -> dict:
    """One timed run of `job` with `workers` from `tree` (None: this checkout, as installed)."""
    argv, unit = JOBS[job]
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = tree + os.pathsep + env.get("PYTHONPATH", "")
    if job == "feature_cache":
        done = subprocess.run([sys.executable, os.path.join(HERE, "cache_run.py"), dataset, str(workers), "12"],
                              env=env, capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(f"cache_run.py failed:\n{done.stderr[-2000:]}")
        return json.loads(done.stdout.strip().splitlines()[-1])
    with tempfile.TemporaryDirectory() as out:
        command = [sys.executable, "-m", "trivla_drake.cli", *[a.format(n=n) for a in argv], "--workers", str(workers)]
        if job.startswith("collect"):
            command += ["--out", os.path.join(out, "data")]
        start = time.perf_counter()
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - start
    if done.returncode not in (0, 1):
        raise RuntimeError(f"{command} failed:\n{done.stderr[-2000:]}")
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    count = summary["episodes"] if job.startswith("collect") else sum(
        row["episodes"] for row in summary["tasks"].values())
    return {"seconds": seconds, unit: count, "per_minute": 60 * count / seconds}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--old", required=True, help="a worktree of the commit before Ray (c27a062)")
    parser.add_argument("--jobs", default="collect,collect_prelude,evaluate")
    parser.add_argument("--n", type=int, default=2, help="episodes per task of every run")
    parser.add_argument("--out", default=None, help="JSON file for the figures")
    parser.add_argument("--dataset", default=None, help="a collected dataset of at least 12 episodes (feature_cache)")
    args = parser.parse_args()
    figures: dict = {"cpu": _cpu(), "n": args.n}
    for job in args.jobs.split(","):
        for workers in (1, 2):
            for label, tree in (("before", args.old), ("after", None)):
                figure = run(tree, job, workers, args.n, args.dataset)
                figures.setdefault(job, {}).setdefault(label, {})[str(workers)] = figure
                print(f"{job:16s} {label:6s} {workers} worker(s): {figure['per_minute']:6.2f} / min "
                      f"({figure['seconds']:.0f} s)", flush=True)
    print("\n| figure | before, 1 worker | before, 2 | after, 1 | after, 2 | after 2 / before 1 | after 2 / before 2 |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for job in args.jobs.split(","):
        b, a = figures[job]["before"], figures[job]["after"]
        print(f"| {job} / min | {b['1']['per_minute']:.2f} | {b['2']['per_minute']:.2f} | {a['1']['per_minute']:.2f} | "
              f"{a['2']['per_minute']:.2f} | {a['2']['per_minute'] / b['1']['per_minute']:.2f}x | "
              f"{a['2']['per_minute'] / b['2']['per_minute']:.2f}x |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(figures, f, indent=2)
    return 0


def _cpu() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        return f"{names[0]} x {len(names)}" if names else "unknown"
    except OSError:
        return "unknown"


if __name__ == "__main__":
    sys.exit(main())
