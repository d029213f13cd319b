"""The probe of probe_scale.py again on its saved tokens, fitted longer (5000 steps) on 2112 and 1000 scenes.
`python results/grounding_scenes/probe_steps.py` (in the folder where probe_scale.py saved them)."""
import sys, numpy as np, torch
from trivla_drake.eval.attention_probe import attention_probe
torch.set_num_threads(2)
x, y = np.load("qvl_static.npy"), np.load("targets.npy")
for n, steps in [(2112, 5000), (1000, 5000)]:
    r2, rmse = attention_probe(x[:n], y[:n], positions=True, steps=steps)
    print(n, steps, f"RMSE {100*rmse.mean():.2f} cm", flush=True)
