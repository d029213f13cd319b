"""`TriVLAPolicy`: Systems 2, 3, 1 and the chunk executor as one Diagram to add to any builder.

Ports (stable whatever systems the model keeps):
  inputs
    static_rgb      ImageRgba8U, the third-person camera (model size, 224x224 for `cpu`)
    wrist_rgb       ImageRgba8U, the wrist camera
    instruction     str, the task in natural language (read at each System 2 / 3 update)
    robot_state     18-vector, Panda q (7 arm [rad], 2 fingers [m]) then v [rad/s, m/s]
  outputs
    ee_target       RigidTransform X_WT: pose of `panda_hand_tcp` in the WORLD [m] (X_WB times the commanded
                    pose in the robot's base frame), for DifferentialIKSystem (given the same X_WB)
    gripper_target  1-vector, finger distance [m], for the station's `panda.gripper_width`
    action_chunk    float32 numpy (action_horizon, 7), 10 for the presets: System 1's latest chunk of actions
                    [dx, dy, dz [m], drx, dry, drz [rad], gripper] in the robot's BASE frame (None before the first)
    q_vl            System 2's latest output: float32 numpy (tokens, LLM width), the LLM's middle-layer hidden
                    states; the tokens are the images' and the prompt's, so their number varies with the
                    instruction: (173, 192) for the shipped model and "pick up the red block" (None before the
                    first, and always without System 2)
    q_p             System 3's latest output: dict {"static", "wrist"} of float32 numpy (frames, channels, H_p, W_p),
                    its up-sampling features, (5, 128, 8, 8) each for the shipped model (None before the first,
                    and always without System 3)

The robot's base pose in the world, X_WB (identity by default; `robot_base_pose(plant, instance)` reads it
from a plant), is fixed when the policy is built: the actions and the model's tool-centre point are
robot-centric (base frame), only `ee_target` is expressed in the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import ConstantValueSource, PassThrough
from pydrake.systems.sensors import ImageRgba8U

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.systems.action_chunk_executor import ActionChunkExecutor, covering_chunks
from trivla_drake.systems.action_executor import DEFAULT_ACTION_SPACE, ActionSpace
from trivla_drake.systems.dynamics_perception_system import DynamicsPerceptionSystem
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.policy_system import PolicySystem
from trivla_drake.systems.vision_language_system import VisionLanguageSystem


@dataclass
class PolicyRates:
    """Update periods [s] and latency models of the three systems; defaults follow the paper."""

    # System 2 and System 3 may run slower than System 1; here they match its replanning rate.
    vision_language_period_s: float = 10.0 / 36.0
    dynamics_period_s: float = 10.0 / 36.0
    # System 1 replans once per chunk: 10 actions at 36 Hz.
    policy_period_s: float = 10.0 / 36.0
    latency: LatencyModel = field(default_factory=LatencyModel)
    # ACT-style temporal ensembling of overlapping chunks (weight decay m), or None to play the newest.
    ensemble_decay: float | None = None
    action_space: ActionSpace = DEFAULT_ACTION_SPACE
    # Sense, think, act in one instant: Systems 2 and 3 run this long [s] after each period starts
    # (reading the cameras as rendered then: add_trivla_policy wires the station's `.rgb_image_now`
    # ports, a held `.rgb_image` would be up to 1/fps old), System 1 twice as long (on their
    # fresh features and the robot state of that instant), the chunk executor three times (after
    # System 1's chunk), so a chunk's first action is played at the instant of its observation, as
    # in the evaluation harness and the demonstrations (which also render the images at that instant).
    # Drake computes simultaneous updates from the same pre-update state: with 0, System 1 would read
    # the features of the previous period and the executor the previous chunk.
    stage_offset_s: float = 1e-4

    @classmethod
    def replanning_every(
        cls,
        steps: int,
        *,
        ensemble_decay: float | None = None,
        latency: LatencyModel | None = None,
        action_space: ActionSpace = DEFAULT_ACTION_SPACE,
    ) -> "PolicyRates":
        """Systems 1, 2 and 3 all update every `steps` control steps (steps * dt seconds), as
        `evaluate`'s inference.execute_steps replans (steps above the chunk length would leave ticks uncovered;
        the caller checks that bound, which is the model's)."""
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise ValueError(f"steps must be an integer >= 1 (control steps between replans), got {steps!r}")
        period = int(steps) * action_space.dt
        return cls(vision_language_period_s=period, dynamics_period_s=period, policy_period_s=period,
                   latency=latency or LatencyModel(), ensemble_decay=ensemble_decay, action_space=action_space)

    def validate(self) -> None:
        """ValueError naming the field unless every period is positive and the stages fit within the
        shortest period (the executor checks the ensemble decay)."""
        for name in ("vision_language_period_s", "dynamics_period_s", "policy_period_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"PolicyRates.{name} must be a positive number of seconds, got {value!r}")
        shortest = min(self.vision_language_period_s, self.dynamics_period_s, self.policy_period_s,
                       self.action_space.dt)
        if not 0.0 <= 3 * self.stage_offset_s < shortest:
            raise ValueError(f"PolicyRates.stage_offset_s must be >= 0 and below a third of the shortest period "
                             f"({shortest:g} s), got {self.stage_offset_s}")


# Each system's seed is the policy's seed plus its offset, whichever systems the model keeps.
SEED_OFFSETS = {"policy": 0, "vision_language": 1, "dynamics": 2}


class TriVLAPolicy(Diagram):
    """The whole TriVLA policy as a Drake Diagram (see the module docstring for its ports and frames); `X_WB` is
    the robot base's pose in the world (identity: the base at the origin)."""

    def __init__(self, model: TriVLA, rates: PolicyRates | None = None, *, seed: int = 0,
                 X_WB: RigidTransform | None = None):
        super().__init__()
        rates = rates or PolicyRates()
        rates.validate()
        model.eval()
        builder = DiagramBuilder()
        inputs = {
            "static_rgb": AbstractValue.Make(ImageRgba8U()),
            "wrist_rgb": AbstractValue.Make(ImageRgba8U()),
            "instruction": AbstractValue.Make(""),
        }
        # Pass-throughs give every input a home, so the ports exist in every ablation.
        fan_out = {name: builder.AddNamedSystem(f"{name}_in", PassThrough(value)) for name, value in inputs.items()}
        for name, system in fan_out.items():
            builder.ExportInput(system.get_input_port(), name)
        state_in = builder.AddNamedSystem("robot_state_in", PassThrough(18))
        builder.ExportInput(state_in.get_input_port(), "robot_state")

        policy = builder.AddNamedSystem(
            "system1_policy",
            PolicySystem(model, period_s=rates.policy_period_s, latency=rates.latency,
                         seed=seed + SEED_OFFSETS["policy"],
                         offset_s=2 * rates.stage_offset_s),
        )
        builder.Connect(state_in.get_output_port(), policy.GetInputPort("robot_state"))
        self.systems = {"policy": policy}
        for key, cls, period, port in (
            ("vision_language", VisionLanguageSystem, rates.vision_language_period_s, "q_vl"),
            ("dynamics", DynamicsPerceptionSystem, rates.dynamics_period_s, "q_p"),
        ):
            if getattr(model, key) is None:
                empty = builder.AddNamedSystem(f"no_{port}", ConstantValueSource(AbstractValue.Make(None)))
                builder.Connect(empty.get_output_port(), policy.GetInputPort(port))
                builder.ExportOutput(empty.get_output_port(), port)
                continue
            system = builder.AddNamedSystem(
                f"system{2 if key == 'vision_language' else 3}_{key}",
                cls(model, period_s=period, latency=rates.latency, seed=seed + SEED_OFFSETS[key],
                    offset_s=rates.stage_offset_s),
            )
            for name, source in fan_out.items():
                builder.Connect(source.get_output_port(), system.GetInputPort(name))
            if system.HasInputPort("robot_state"):
                builder.Connect(state_in.get_output_port(), system.GetInputPort("robot_state"))
            builder.Connect(system.GetOutputPort(port), policy.GetInputPort(port))
            builder.ExportOutput(system.GetOutputPort(port), port)
            self.systems[key] = system

        chunk_s = model.config.policy.action_horizon * rates.action_space.dt
        keep_chunks = covering_chunks(chunk_s, rates.policy_period_s)
        executor = builder.AddNamedSystem(
            "action_chunk_executor",
            ActionChunkExecutor(rates.action_space, ensemble_decay=rates.ensemble_decay, keep_chunks=keep_chunks,
                                offset_s=3 * rates.stage_offset_s, X_WB=X_WB),
        )
        builder.Connect(policy.GetOutputPort("action_chunk"), executor.GetInputPort("action_chunk"))
        builder.Connect(policy.GetOutputPort("action_chunk_stamp"), executor.GetInputPort("action_chunk_stamp"))
        builder.Connect(state_in.get_output_port(), executor.GetInputPort("robot_state"))
        builder.ExportOutput(executor.GetOutputPort("ee_target"), "ee_target")
        builder.ExportOutput(executor.GetOutputPort("gripper_target"), "gripper_target")
        builder.ExportOutput(policy.GetOutputPort("action_chunk"), "action_chunk")
        self.systems["executor"] = executor
        builder.BuildInto(self)
        self.set_name("trivla_policy")

    def set_seed(self, root_context, seed: int) -> None:
        """Seed every system's inferences in the root context of the diagram holding this policy."""
        for key, system in self.systems.items():
            if key != "executor":
                system.set_seed(system.GetMyContextFromRoot(root_context), seed + SEED_OFFSETS[key])
