"""Diagnostic (results/grounding_scenes/, run from the repository root): how precisely the static view's Q_vl
tokens of a checkpoint place the three blocks (attention probe with token positions, 20% held out) as the probe
sees more scenes: the VQA set's scenes with every block on the table and away from the bowl (2112 of 5000).
Saves the tokens and targets (qvl_static.npy, targets.npy in the working folder) for probe_steps.py.
`python results/grounding_scenes/probe_scale.py CHECKPOINT VQA_FOLDER OUT.json STEPS`"""
import sys, json, time
import numpy as np, torch
from trivla_drake.nn import load_checkpoint
from trivla_drake.tasks.scene import Layout, BLOCK_COLORS
from trivla_drake.train.vqa import sample_vqa_scene
from trivla_drake.eval.attention_probe import attention_probe
torch.set_num_threads(2)
ckpt, folder, out = sys.argv[1], sys.argv[2], sys.argv[3]
meta = json.load(open(f"{folder}/meta.json"))
layout = Layout.default()
keep, targets = [], []
for i in range(meta["scenes"]):
    spec = sample_vqa_scene(np.random.default_rng([int(meta["seed"]), i]), layout)
    pos = np.array([spec.blocks[c].position for c in BLOCK_COLORS])
    if (pos[:, 2] < 0.05).all() and np.hypot(*(pos[:, :2] - np.array(layout.bowl[:2, 3])).T).min() > 0.08:
        keep.append(i); targets.append(pos[:, :2].reshape(-1))
targets = np.asarray(targets)
print("table-only scenes", len(keep), flush=True)
static = np.load(f"{folder}/static.npy", mmap_mode="r"); wrist = np.load(f"{folder}/wrist.npy", mmap_mode="r")
model = load_checkpoint(ckpt).eval()
vl = model.vision_language
pieces = vl.build_prompts([[]], 2)[0].text_pieces
head, k = len(pieces[0]), vl.num_image_tokens
feats = []
t0 = time.time()
with torch.inference_mode():
    for s0 in range(0, len(keep), 32):
        idx = keep[s0:s0+32]
        q, _ = model.encode_vision_language_batch(torch.from_numpy(np.stack([static[i] for i in idx])),
                                                 torch.from_numpy(np.stack([wrist[i] for i in idx])),
                                                 ["lift the red block"] * len(idx))
        feats.append(q[:, head:head+k].float().numpy())
x = np.concatenate(feats); print("features", x.shape, f"{time.time()-t0:.0f}s", flush=True)
np.save("qvl_static.npy", x); np.save("targets.npy", targets)
res = {}
for n in (360, 1000, len(x)):
    r2, rmse = attention_probe(x[:n], targets[:n], positions=True, steps=int(sys.argv[4]))
    res[n] = float(100 * rmse.mean()); print(n, f"RMSE {res[n]:.2f} cm  R2 {r2.mean():.3f}", flush=True)
json.dump(res, open(out, "w"), indent=1)
