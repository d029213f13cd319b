"""System 3's one-step predictions beside the real future frames (the paper's Fig. 5).

The Panda follows a scripted path; at `--at` seconds System 3 predicts the coming clip from the
current static and wrist frames in ONE UNet pass, and the simulator renders what really happens.
Rows: real static, predicted static, real wrist, predicted wrist. Columns: the clip's frames.

Pictures need a trained video autoencoder: the `paper` preset loads SVD's (`svd_path` / `vae_path`). The `cpu` preset
(the shipped checkpoint) keeps its autoencoder at its random initialisation, as nothing here trains it: its UNet
learns and predicts in that random latent space, which serves System 1 as features, but the decoded rows show colour
noise, not scenes. The script says so when it runs.

    python examples/system3_predictions.py --out system3_predictions.png
"""

import argparse

import cv2
import numpy as np
import torch

from trivla_drake.eval.model_loading import load_model
from trivla_drake.eval.scripted_run import make_scripted_diagram
from trivla_drake.station import load_scenario, make_simulator


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint")
    parser.add_argument("--preset", default=None, help="use an UNTRAINED model of this preset (tiny, cpu) instead of the shipped checkpoint")
    parser.add_argument("--at", type=float, default=1.0, help="sim time of the current frame [s]")
    parser.add_argument("--frame-spacing", type=float, default=0.25, help="time between clip frames [s]")
    parser.add_argument("--instruction", default="move the hand in a circle")
    parser.add_argument("--out", default="system3_predictions.png")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    model = load_model(args.checkpoint, preset=args.preset)

    scenario = load_scenario()
    diagram = make_scripted_diagram(scenario)
    simulator = make_simulator(diagram, scenario)
    station = diagram.GetSubsystemByName("station")
    views = {"static": "static_camera_sensor", "wrist": "wrist_camera_sensor"}
    real = {view: [] for view in views}
    frames = model.dynamics.num_frames if model.dynamics is not None else 0
    if frames == 0:
        raise SystemExit("this model has no System 3 (use_system3 = False)")
    for k in range(frames):
        simulator.AdvanceTo(args.at + k * args.frame_spacing)
        for view, sensor_name in views.items():
            sensor = station.GetSubsystemByName(sensor_name)
            context = sensor.GetMyContextFromRoot(simulator.get_context())
            real[view].append(sensor.color_image_output_port().Eval(context).data[:, :, :3].copy())
    size = 112
    rows = []
    dynamics_config = model.config.dynamics
    if not (dynamics_config.vae_path or dynamics_config.svd_path):
        print("note: this model's video autoencoder was never trained (no svd_path / vae_path, as in the cpu "
              "preset): the predicted rows decode its latents into colour noise; only the paper preset's SVD "
              "autoencoder decodes pictures")
    for view in views:
        predicted = model.predict_video(real[view][0], args.instruction, seed=args.seed)
        rows.append(np.hstack([cv2.resize(f, (size, size), interpolation=cv2.INTER_AREA) for f in real[view]]))
        rows.append(np.hstack([cv2.resize(f, (size, size), interpolation=cv2.INTER_NEAREST) for f in predicted]))
    grid = np.vstack(rows)
    cv2.imwrite(args.out, cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    print(f"saved {args.out}: rows real/predicted static, real/predicted wrist; {frames} frames, "
          f"{args.frame_spacing} s apart from t = {args.at} s")


if __name__ == "__main__":
    main()
