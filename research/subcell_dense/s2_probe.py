"""Diagnostic (results/subcell_dense/, run from the repository root): how well a checkpoint's System 2
places the blocks on the first frames of a dataset's episodes without preludes (preludes move blocks
before the first frame). Attention probe with token positions (held-out 20%) and 5-fold ridge, on the
static view's projected image tokens and Q_vl tokens, and on both views' Q_vl tokens; with `patches`,
on the static view's SigLIP patches before pixel shuffle instead.
`python results/subcell_dense/s2_probe.py CHECKPOINT DATA EPISODES STEPS OUT.json [patches]`."""
import sys, time, json
import numpy as np, torch
from trivla_drake.data.lerobot import LeRobotReader
from trivla_drake.eval.feature_probe import first_frame_block_positions, first_frames, ridge_probe
from trivla_drake.eval.attention_probe import attention_probe
from trivla_drake.nn import load_checkpoint
from trivla_drake.nn.vision_language import images_to_siglip_input
from trivla_drake.train.datasets import resize_frames

torch.set_num_threads(2)
ckpt, data, n, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
model = load_checkpoint(ckpt).eval()
reader = LeRobotReader(data)
clean = [e for e in range(reader.num_episodes) if not reader.episodes[e].get('trivla/prelude')]  # preludes move blocks first
eps = clean[:: max(1, len(clean) // n)][:n]
targets = first_frame_block_positions(reader, eps)
static, wrist = first_frames(reader, eps)
vl = model.vision_language
pieces = vl.build_prompts([[]], 2)[0].text_pieces
head, sep, k = len(pieces[0]), len(pieces[1]), vl.num_image_tokens
feats = {"projector_static": [], "qvl_static": [], "qvl_both": []}
patches = len(sys.argv) > 6 and sys.argv[6] == "patches"
if patches:
    feats = {"siglip_patches_static": []}
with torch.inference_mode():
    for s0 in range(0, len(eps), 16):
        s = torch.from_numpy(resize_frames(static[s0:s0+16], model.image_size))
        w = torch.from_numpy(resize_frames(wrist[s0:s0+16], model.image_size))
        q, _ = model.encode_vision_language_batch(s, w, [reader.task_of(e) for e in eps[s0:s0+16]])
        qs, qw = q[:, head:head+k], q[:, head+k+sep:head+2*k+sep]
        if patches:
            feats["siglip_patches_static"].append(vl.vision_encoder(pixel_values=images_to_siglip_input(s, torch.float32)).last_hidden_state)
            continue
        feats["projector_static"].append(vl.encode_images(s))
        feats["qvl_static"].append(qs); feats["qvl_both"].append(torch.cat([qs, qw], 1))
out = {}
for name, v in feats.items():
    x = torch.cat(v).float().numpy()
    r2, rmse = attention_probe(x, targets, positions=True, steps=steps)
    out[f"{name} attention"] = (float(r2.mean()), float(100 * rmse.mean()))
    if name not in ("qvl_both", "siglip_patches_static"):
        r2r, rmser, _ = ridge_probe(x.reshape(len(x), -1), targets, folds=5)
        out[f"{name} ridge"] = (float(r2r.mean()), float(100 * rmser.mean()))
    for key in [kk for kk in out if kk.startswith(name)]:
        print(f"{key:28s} R2 {out[key][0]:.3f}  RMSE {out[key][1]:.2f} cm", flush=True)
json.dump({"checkpoint": ckpt, "episodes": len(eps), "steps": steps, "results": out}, open(sys.argv[5], "w"), indent=1)
