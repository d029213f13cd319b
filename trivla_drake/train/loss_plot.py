"""A run's training curve as a PNG: OUT/log.jsonl (loss and its moving average per logged step, the
parts of a loss made of several, such as the flow-matching and grounding losses, and the learning
rate) -> OUT/loss.png, rewritten at the end of every run (also a resumed one)."""

from __future__ import annotations

import json
from pathlib import Path


def read_log(log_path: str | Path) -> list[dict]:
    """The rows of a log.jsonl; a torn last line (a run killed mid-write) is skipped."""
    rows = []
    for line in Path(log_path).read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


def loss_components(rows: list[dict]) -> list[str]:
    """The logged parts of a loss made of several: every "*_loss" key of the log's rows."""
    return sorted({key for row in rows for key in row if key.endswith("_loss")})


def plot_training_curve(log_path: str | Path, out_path: str | Path, *, title: str = "") -> Path | None:
    """Writes loss (log scale) and learning rate against step; None when the log has no rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_log(log_path)
    if not rows:
        return None
    steps = [r["step"] for r in rows]
    fig, (ax_loss, ax_lr) = plt.subplots(2, 1, figsize=(7, 5), sharex=True, height_ratios=(3, 1))
    ax_loss.plot(steps, [r["loss"] for r in rows], color="0.75", lw=0.8, label="loss (logged step)")
    ax_loss.plot(steps, [r["loss_ema"] for r in rows], color="C0", lw=1.6, label="moving average")
    for i, key in enumerate(loss_components(rows)):
        logged = [(r["step"], r[key]) for r in rows if key in r]
        ax_loss.plot(*zip(*logged), color=f"C{i + 2}", lw=0.8, alpha=0.8, label=key.replace("_", " "))
    ax_loss.set_yscale("log")
    ax_loss.set_ylabel("training loss")
    ax_loss.legend(loc="upper right")
    ax_loss.grid(True, which="both", alpha=0.3)
    ax_loss.set_title(title)
    ax_lr.plot(steps, [r["lr"] for r in rows], color="C1")
    ax_lr.set_ylabel("learning rate")
    ax_lr.set_xlabel("optimizer step")
    ax_lr.grid(True, alpha=0.3)
    fig.tight_layout()
    out_path = Path(out_path)
    tmp = out_path.with_name(f".tmp-{out_path.name}")
    fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    tmp.replace(out_path)
    return out_path
