"""Per-system parameter counts and inference latency, in the shape of the paper's Table 4.

Latencies are medians over `repeats` timed calls after warm-up, in the current process's torch thread
setting (not changed here). The goal for the `cpu` preset is a full inference (Systems 2, 3 and 1,
both views) under 278 ms on 2 cores, so that 10-step chunks sustain 36 Hz control.
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import time
from typing import Any, Callable

import numpy as np
import torch

from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA

CPU_GOAL_MS = 278.0  # 10 actions per chunk at 36 Hz
ABLATIONS = (("1", False, False), ("1+3", False, True), ("1+2+3", True, True))
"""(systems, use_system2, use_system3) rows of Table 4."""

_WARMUP = 2  # first calls pay one-off kernel/primitive set-up costs

PRECISIONS: dict[str, torch.dtype | None] = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}
"""Benchmark precision -> autocast dtype (None: plain float32). Weights stay float32; under autocast the
matrix products and convolutions run in the reduced dtype, as mixed-precision inference on a GPU does."""


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _median_ms(fn: Callable[[], object], repeats: int, device: torch.device) -> float:
    for _ in range(_WARMUP):
        fn()
    times = []
    for _ in range(repeats):
        _synchronize(device)
        start = time.perf_counter()
        fn()
        _synchronize(device)
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def example_observation(image_size: int = 224, state_dim: int = 18, seed: int = 0) -> dict[str, Any]:
    """A random observation with the shapes `predict_action_chunk` takes."""
    rng = np.random.default_rng(seed)
    return {
        "static_rgb": rng.integers(0, 256, (image_size, image_size, 3), dtype=np.uint8),
        "wrist_rgb": rng.integers(0, 256, (image_size, image_size, 3), dtype=np.uint8),
        "instruction": "pick up the red block and place it in the bowl",
        "state": rng.normal(size=state_dim).astype(np.float32),
        "embodiment_id": 0,
    }


def _millions(n: int) -> float:
    return round(n / 1e6, 3)


def _paper_parameter_counts() -> dict[str, float]:
    """Parameter counts of the paper preset, built on the meta device (no memory, no weights)."""
    with torch.device("meta"):
        model = TriVLA(make_config("paper"), load_pretrained=False)
    return {k: _millions(v) for k, v in model.parameter_counts().items()}


def benchmark_model(
    preset: str = "cpu",
    repeats: int = 5,
    seed: int = 0,
    *,
    device: str | torch.device | None = None,
    threads: int | None = None,
    precision: str = "float32",
) -> dict[str, Any]:
    """Per-system parameters (millions) and median latency (ms) of System 2, System 3 (both views),
    System 1 (the whole Euler sampling) and the full inference, plus Table 4's ablation rows.
    `threads` sets torch's intra-op threads for the run (restored afterwards); None keeps the current
    setting. `precision` is one of PRECISIONS ("bfloat16" or "float16": autocast around every timed call).
    The `paper` preset is skipped (with the reason) when no CUDA device is present."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1; got {repeats}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}; got {precision!r}")
    if threads is None:
        return _benchmark(preset, repeats, seed, device, precision)
    if threads < 1:
        raise ValueError(f"threads must be >= 1; got {threads}")
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _benchmark(preset, repeats, seed, device, precision)
    finally:
        torch.set_num_threads(previous)


def _benchmark(
    preset: str, repeats: int, seed: int, device: str | torch.device | None, precision: str
) -> dict[str, Any]:
    config = make_config(preset)
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    result: dict[str, Any] = {
        "preset": preset,
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "precision": precision,
        "torch_threads": torch.get_num_threads(),
        # Other processes busy on the same cores make torch's spinning OpenMP threads stall (seconds
        # per call with 2 threads on 2 shared cores); OMP_WAIT_POLICY=PASSIVE or 1 thread avoids it.
        "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "repeats": repeats,
        "euler_steps": config.policy.num_inference_steps,
        "action_horizon": config.policy.action_horizon,
    }
    if preset == "paper" and device.type != "cuda":
        result.update(
            skipped=True,
            reason="the paper preset (Eagle-2 + SVD, billions of parameters) is only timed on a CUDA GPU; "
            f"device is {device}",
            params_millions=_paper_parameter_counts(),
        )
        return result

    autocast_dtype = PRECISIONS[precision]
    # One autocast context around every timed call: its cache keeps the reduced-precision copies of the
    # weights between calls (as weights converted once would be), so no call pays for casting them.
    with torch.autocast(device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
        timings, full = _time_ablations(config, repeats, seed, device)
    result.update(timings)
    result.update(
        goal_ms=CPU_GOAL_MS if preset == "cpu" else None,
        meets_goal=(full < CPU_GOAL_MS) if preset == "cpu" else None,
    )
    return result


def _time_ablations(config, repeats: int, seed: int, device: torch.device) -> tuple[dict[str, Any], float]:
    """Table 4's rows (one model per row, moved to `device`) and the full model's per-system latencies;
    and the full inference's latency [ms], unrounded."""
    obs = example_observation(config.vision_language.vision.image_size, config.policy.state_dim, seed)
    ablations = []
    per_system: dict[str, float] = {}
    params: dict[str, float] = {}
    for systems, use2, use3 in ABLATIONS:
        variant = dataclasses.replace(config, use_system2=use2, use_system3=use3)
        # Built on the CPU, then moved: the path of a loaded checkpoint (`load_checkpoint(...).to(device)`).
        model = TriVLA(variant).eval().to(device)
        latency = _median_ms(lambda: model.predict_action_chunk(obs, seed=seed), repeats, device)
        ablations.append(
            {
                "systems": systems,
                "system2": use2,
                "system3": use3,
                "params_millions": _millions(model.parameter_counts()["total"]),
                "latency_ms": round(latency, 2),
            }
        )
        if use2 and use3:
            params = {k: _millions(v) for k, v in model.parameter_counts().items()}
            q_vl, q_s = model.encode_vision_language(
                obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"]
            )
            features = model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=seed)
            per_system = {
                "system2": _median_ms(
                    lambda: model.encode_vision_language(
                        obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"]
                    ),
                    repeats,
                    device,
                ),
                "system3": _median_ms(
                    lambda: model.encode_dynamics(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], seed=seed),
                    repeats,
                    device,
                ),
                "system1": _median_ms(lambda: model.sample_actions(q_vl, q_s, features, seed=seed, state=obs["state"]), repeats, device),
                "full": latency,
            }
        del model
    full = per_system["full"]
    return dict(
        skipped=False,
        params_millions=params,
        latency_ms={k: round(v, 2) for k, v in per_system.items()},
        ablations=ablations,
        control_rate_hz=round(config.policy.action_horizon * 1000.0 / full, 1),
    ), full


def format_benchmark_table(result: dict[str, Any]) -> str:
    """Markdown tables of a `benchmark_model` result (per system, then Table 4's ablation rows)."""
    head = f"TriVLA benchmark: preset `{result['preset']}` on {result['device']}"
    if result.get("skipped"):
        lines = [head, "", f"Skipped: {result['reason']}."]
        params = result.get("params_millions")
        if params:
            lines += ["", "| System | Params (M) |", "|---|---:|"]
            lines += [f"| {name} | {params[key]:.1f} |" for key, name in _SYSTEM_NAMES if key in params]
        return "\n".join(lines)
    params, latency = result["params_millions"], result["latency_ms"]
    lines = [
        head + f" ({_device_words(result)}, median of {result['repeats']})",
        "",
        "| System | Params (M) | Latency (ms) |",
        "|---|---:|---:|",
        f"| System 2: vision-language (Q_vl) | {params['system2']:.2f} | {latency['system2']:.1f} |",
        f"| System 3: dynamics perception, both views (F_p) | {params['system3']:.2f} | {latency['system3']:.1f} |",
        f"| System 1: policy, {result['euler_steps']} Euler steps | {params['system1']:.2f} "
        f"| {latency['system1']:.1f} |",
    ]
    if "text_encoder" in params:  # frozen, run once per instruction, and not in the checkpoint
        lines.append(f"| Pretrained text encoder (frozen, once per instruction) | {params['text_encoder']:.2f} | |")
    lines += [
        f"| Full inference | {params['total']:.2f} | {latency['full']:.1f} |",
        "",
        "| VL-M (S2) | DP-M (S3) | PL-M (S1) | Latency (ms) | Params (M) |",
        "|:-:|:-:|:-:|---:|---:|",
    ]
    for row in result["ablations"]:
        mark = lambda on: "✓" if on else ""  # noqa: E731
        lines.append(
            f"| {mark(row['system2'])} | {mark(row['system3'])} | ✓ "
            f"| {row['latency_ms']:.1f} | {row['params_millions']:.2f} |"
        )
    rate = f"{result['control_rate_hz']:.0f} Hz control with {result['action_horizon']}-step chunks"
    goal = ""
    if result.get("goal_ms") is not None:
        verdict = "meets" if result["meets_goal"] else "MISSES"
        goal = f" ({verdict} the < {result['goal_ms']:.0f} ms goal for 36 Hz)"
    lines += ["", f"Full inference {latency['full']:.1f} ms -> {rate}{goal}."]
    load = result.get("load_average_1min")
    passive = (result.get("omp_wait_policy") or "").upper() == "PASSIVE"
    if load is not None and result["device"] == "cpu" and load >= 1.0 and result["torch_threads"] > 1 and not passive:
        lines.append(
            f"Note: the CPU was busy (1-min load {load}); with {result['torch_threads']} spinning OpenMP threads, "
            "other processes can inflate these figures many times over (set OMP_WAIT_POLICY=PASSIVE or use 1 thread)."
        )
    return "\n".join(lines)


def _device_words(result: dict[str, Any]) -> str:
    """'2 threads' on a CPU, the GPU's name on CUDA; the precision when it is not float32."""
    words = result.get("device_name") or f"{result['torch_threads']} threads"
    precision = result.get("precision", "float32")
    return words if precision == "float32" else f"{words}, {precision} autocast"


_SYSTEM_NAMES = (
    ("system2", "System 2: vision-language"),
    ("system3", "System 3: dynamics perception"),
    ("system1", "System 1: policy"),
    ("text_encoder", "Pretrained text encoder (frozen)"),
    ("total", "Total"),
)
