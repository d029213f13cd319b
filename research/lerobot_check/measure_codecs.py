"""Encode time, file size and fidelity of the three video codecs (`collect`'s video_codec) on a rendered episode:
the first 104 frames of each 224x224 camera of one oracle lift_block episode, each encoded `--repeats` times by
`trivla_drake.data.video.write_video` (median and fastest time; the fastest is the least disturbed by other
processes on a shared machine), decoded `--repeats` times by `read_video` (fastest).

    OMP_NUM_THREADS=1 python research/lerobot_check/measure_codecs.py --out research/lerobot_check/codecs.json
    OMP_NUM_THREADS=1 python research/lerobot_check/measure_codecs.py --keyframe-interval 36 \
        --out research/lerobot_check/codecs_keyframe36.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time

import numpy as np

FRAMES = 104


def rendered_frames(image_size: int) -> dict[str, np.ndarray]:
    """The camera frames of one successful oracle episode (lift_block, collect's seed of attempt 0)."""
    from trivla_drake.eval.episode import derive_seed, run_episode
    from trivla_drake.tasks.oracle import OraclePolicy

    result = run_episode("lift_block", derive_seed(0, "lift_block", 0), OraclePolicy(), image_size=image_size,
                         keep_trajectory=True)
    if not result.success:
        raise RuntimeError("the oracle episode failed; choose another seed")
    frames = {key: np.stack(images) for key, images in result.trajectory.images.items()}
    short = {key: len(v) for key, v in frames.items() if len(v) < FRAMES}
    if short:
        raise RuntimeError(f"the episode has fewer than {FRAMES} frames: {short}")
    return {key: v[:FRAMES] for key, v in frames.items()}


def measure(frames: dict[str, np.ndarray], repeats: int) -> list[dict]:
    from trivla_drake.data.video import VIDEO_CODECS, read_video, write_video

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for codec in VIDEO_CODECS:
            for camera, video in frames.items():
                path = os.path.join(folder, f"{codec}-{camera}.mp4")
                times = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    write_video(path, video, 36.0, codec)
                    times.append(time.perf_counter() - start)
                decodes = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    decoded = read_video(path)
                    decodes.append(time.perf_counter() - start)
                error = decoded.astype(np.float64) - video.astype(np.float64)
                rows.append({"codec": codec, "camera": camera, "encode_s": statistics.median(times),
                             "encode_min_s": min(times), "decode_min_s": min(decodes), "bytes": os.path.getsize(path),
                             "mean_abs_diff": float(np.abs(error).mean()),
                             "psnr_db": float(10 * np.log10(255.0**2 / np.mean(error**2)))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--keyframe-interval", type=int, help="another keyframe interval than data/video.py's "
                        "KEYFRAME_INTERVAL for h264 and av1 (what it costs in size)")
    parser.add_argument("--out", help="write the figures here as JSON")
    args = parser.parse_args()
    if args.keyframe_interval:
        from trivla_drake.data import video

        video.KEYFRAME_INTERVAL = args.keyframe_interval
    rows = measure(rendered_frames(224), args.repeats)
    print("| codec | camera | encode median [s] | encode fastest [s] | decode fastest [s] | size [kB] "
          "| mean abs diff | PSNR [dB] |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['codec']} | {r['camera']} | {r['encode_s']:.3f} | {r['encode_min_s']:.3f} "
              f"| {r['decode_min_s']:.3f} "
              f"| {r['bytes'] / 1000:.1f} | {r['mean_abs_diff']:.2f} | {r['psnr_db']:.1f} |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()
