"""Inspect a TriVLA closed loop in Meshcat: the scene live, the hand target as a triad and the
predicted action chunk as a path of orange dots; optionally saved as one self-contained page.

    python examples/meshcat_inspection.py --seconds 5 --record trivla_run.html
"""

import argparse
import sys

import torch

from trivla_drake.eval.closed_loop import make_closed_loop
from trivla_drake.eval.model_loading import load_model
from trivla_drake.station import load_scenario, make_simulator
from trivla_drake.station.meshcat_setup import make_meshcat, save_static_html


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint")
    parser.add_argument("--preset", default=None, help="use an UNTRAINED model of this preset (tiny, cpu) instead of the shipped checkpoint")
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--instruction", default="open the drawer")
    parser.add_argument("--record", help="save the run as a self-contained HTML page")
    args = parser.parse_args()
    torch.set_num_threads(1)

    meshcat = make_meshcat()
    print(f"Open {meshcat.web_url()} to watch.", flush=True)
    scenario = load_scenario()
    loop = make_closed_loop(scenario, load_model(args.checkpoint, preset=args.preset),
                            instruction=args.instruction, meshcat=meshcat)
    simulator = make_simulator(loop.diagram, scenario)
    simulator.Initialize()
    meshcat.StartRecording(frames_per_second=30.0)
    simulator.AdvanceTo(args.seconds)
    meshcat.StopRecording()
    meshcat.PublishRecording()  # the animation slider replays the run
    if args.record:
        print("saved", save_static_html(meshcat, args.record))
    if sys.stdin.isatty():
        input("Press Enter to quit (Meshcat stops with this process).")


if __name__ == "__main__":
    main()
