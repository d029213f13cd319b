"""Plot (results/system2_scenes/, run from the repository root): the block-position probes of the shipped System 2
and of step 45's two runs side by side, RMSE per axis in cm for each feature set (lower is better).
`python results/system2_scenes/plot_probes.py` reads probe_{shipped,s2more,s2sub7}.json beside it, writes probes.png."""
import json
from pathlib import Path

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

HERE = Path(__file__).parent
RUNS = {"shipped": "shipped (500 scenes)", "s2more": "5000 scenes, 4x4 sub-cells", "s2sub7": "5000 scenes, 7x7 sub-cells"}
probes = {name: json.loads((HERE / f"probe_{name}.json").read_text())["results"] for name in RUNS
          if (HERE / f"probe_{name}.json").exists()}
features = list(next(iter(probes.values())))
width = 0.8 / len(probes)
fig, ax = plt.subplots(figsize=(9, 4))
for i, (name, results) in enumerate(probes.items()):
    x = np.arange(len(features)) + (i - (len(probes) - 1) / 2) * width
    rmse = [results[f][1] for f in features]
    ax.bar(x, rmse, width, label=RUNS[name])
    for xi, r in zip(x, rmse):
        ax.text(xi, r + 0.03, f"{r:.2f}", ha="center", fontsize=7)
ax.set_xticks(np.arange(len(features)), [f.replace("_", " ").replace(" attention", "\nattention")
                                         .replace(" ridge", "\nridge") for f in features], fontsize=8)
ax.set_ylabel("block (x, y) RMSE per axis [cm]")
ax.set_title("Where System 2's tokens place the blocks (360 first frames; lower is better)")
ax.set_ylim(0, 1.2 * max(r[1] for res in probes.values() for r in res.values()))
ax.legend(fontsize=8, ncol=3, loc="upper center")
fig.tight_layout()
fig.savefig(HERE / "probes.png", dpi=120)
print(f"wrote {HERE / 'probes.png'}")
