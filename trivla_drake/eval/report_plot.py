"""An evaluation report as a picture: `evaluate --out DIR` writes DIR/report.png beside report.json.

Left, when the report has task rows: each task's success rate with its binomial standard error. Right, when it has
chains: CALVIN's "completed at least k of 5" for k = 1..5, and the conditional success at each chain position (of
the chains that reached position k, the fraction that did its task), each with its binomial standard error and the
number of chains behind it, so where a chain breaks is visible at a glance.
"""

from __future__ import annotations

import io
from pathlib import Path

from trivla_drake.data.durable import atomic_write_bytes
from trivla_drake.eval.evaluate import rate_and_stderr


def plot_evaluation(report: dict, out_path: str | Path) -> Path | None:
    """Writes the report's figure (PNG) to `out_path` atomically; None, writing nothing, when the report has neither
    task rows nor chains."""
    tasks = report.get("tasks") or {}
    chains = report.get("chains") if "chain_avg_len" in report else None
    if not tasks and not chains:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = int(bool(tasks)) + int(bool(chains))
    fig, axes = plt.subplots(1, panels, figsize=(6.5 * panels, 4.2), squeeze=False)
    axes = list(axes[0])
    policy = report.get("config", {}).get("policy", report.get("policy", ""))
    if tasks:
        ax = axes.pop(0)
        names = list(tasks)
        ax.bar(range(len(names)), [tasks[n]["success_rate"] for n in names],
               yerr=[tasks[n]["stderr"] for n in names], capsize=2, color="C0")
        ax.set_xticks(range(len(names)), names, rotation=40, ha="right")
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("success rate")
        episodes = sum(tasks[n]["episodes"] for n in names)
        average = report.get("average_success")
        ax.set_title(f"{policy}: {episodes} episodes" + (f", average {average:.3f}" if average is not None else ""))
        ax.grid(True, axis="y", alpha=0.3)
    if chains:
        ax = axes.pop(0)
        n = chains["count"]
        ks = range(1, len(chains["completed_at_least"]) + 1)
        at_least = chains["completed_at_least"]
        ax.bar(ks, at_least, yerr=[rate_and_stderr(round(r * n), n)[1] for r in at_least], capsize=3, color="C1",
               alpha=0.8, label="chains that completed at least k tasks")
        rows = chains.get("by_position", [])
        tried = [(r["position"], *rate_and_stderr(r["succeeded"], r["tried"]), r["tried"])
                 for r in rows if r["tried"]]
        if tried:
            xs, rates, errors, counts = zip(*tried)
            ax.errorbar(xs, rates, yerr=errors, color="C3",
                        marker="o", capsize=3, label="success at position k, of the chains that reached it")
            for x, rate, _, count in tried:
                ax.annotate(f"{count}", (x, rate), textcoords="offset points", xytext=(6, 4), fontsize=7,
                            color="C3")
        ax.set_xticks(list(ks))
        ax.set_xlabel("k (chain position)")
        ax.set_ylim(0, 1.05)
        stderr = report.get("chain_avg_len_stderr", 0.0)
        ax.set_title(f"{policy}: {n} five-task chains, Avg. Len {report['chain_avg_len']:.2f} ± {stderr:.2f}")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=110, format="png")
    plt.close(fig)
    out_path = Path(out_path)
    atomic_write_bytes(out_path, buffer.getvalue())
    return out_path
