"""Where a collected demonstration's time goes: one oracle attempt per task (plain, or with chain preludes) under
cProfile, in this process, its wall time split into the camera renders, the physics and control between frames,
the oracle's planning, the video encoding and the rest.

    python research/throughput/profile_collect.py [--prelude 4] [--out research/throughput/profile_plain.json]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import logging
import pstats
import time

logging.getLogger("drake").setLevel(logging.ERROR)

# (bucket, (file suffix, function name)): a bucket's time is its function's cumulative time; the four are disjoint
# (Drake's AdvanceTo is a compiled method: cProfile files it under "~").
BUCKETS = [
    ("render (two 224-px cameras)", ("eval/env.py", "images")),
    ("video encoding", ("data/video.py", "write_video")),
    ("oracle planning", ("tasks/oracle.py", "act")),
    ("physics + diff-IK between frames (AdvanceTo)", ("~", "AdvanceTo")),
]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--prelude", type=int, default=0, help="prelude_tasks of the collect config (0: plain)")
    parser.add_argument("--attempt", type=int, default=0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    from trivla_drake.eval.collect import _attempt
    from trivla_drake.eval.collect_config import CollectConfig
    from trivla_drake.tasks.suite import TASK_NAMES

    config = CollectConfig(out="unused", prelude_tasks=args.prelude)
    profiler = cProfile.Profile()
    frames = demos = 0
    start = time.perf_counter()
    profiler.enable()
    for task in TASK_NAMES:
        result = _attempt(config, task, args.attempt)
        if result["success"]:
            demos += 1
            frames += len(result["frames"]["action"])
    profiler.disable()
    wall = time.perf_counter() - start
    stats = pstats.Stats(profiler)
    cumulative = {}
    for (filename, _, name), (_, _, _, cum, _) in stats.stats.items():
        for bucket, (suffix, function) in BUCKETS:
            if filename.endswith(suffix) and (name == function or (suffix == "~" and function in name)):
                cumulative[bucket] = cumulative.get(bucket, 0.0) + cum
    # Shares of the wall time (cProfile's own total leaves out time inside compiled calls).
    shares = {**cumulative, "rest (episode bookkeeping, scene set-up, stats)": wall - sum(cumulative.values())}
    report = {"prelude_tasks": args.prelude, "demonstrations": demos, "recorded_frames": frames,
              "wall_seconds": wall, "demonstrations_per_minute": 60 * demos / wall,
              "ms_per_recorded_frame": 1000 * wall / max(frames, 1),
              "seconds": shares, "share": {k: v / wall for k, v in shares.items()}}
    print(f"{demos} demonstrations ({frames} recorded frames) in {wall:.1f} s: "
          f"{report['demonstrations_per_minute']:.1f} / min on one core, {report['ms_per_recorded_frame']:.1f} ms "
          f"per recorded frame")
    for bucket, seconds in sorted(shares.items(), key=lambda kv: -kv[1]):
        print(f"  {bucket:48s} {seconds:7.1f} s  {100 * seconds / wall:5.1f} %")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
