"""`TriVLAPolicyConfig` and `ApplyTriVLAPolicyConfig`: the policy as a Drake-style config, loaded from YAML with
`pydrake.common.yaml.yaml_load_typed` (alone, or as a field of a scenario dataclass of one's own) and applied
to a builder, as Drake's `hardware_sim` applies its configs.

    config = yaml_load_typed(schema=TriVLAPolicyConfig, data="seed: 3\\nbase_frame: panda::panda_link0")
    policy = ApplyTriVLAPolicyConfig(config, builder, station=station, plant=plant)
"""

# No `from __future__ import annotations` here: Drake's YAML loader reads the field types themselves.
import dataclasses as dc
from typing import Optional

from pydrake.common.schema import Transform
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import ScopedName
from pydrake.systems.framework import DiagramBuilder, InputPort, OutputPort, System

from trivla_drake.nn.trivla import TriVLA
from trivla_drake.robot.osqp_diffik import DiffIKParams
from trivla_drake.systems.latency import LatencyModel
from trivla_drake.systems.policy_wiring import add_trivla_policy
from trivla_drake.systems.robot_base import BASE_FRAME, robot_base_pose
from trivla_drake.systems.trivla_policy import PolicyRates, TriVLAPolicy


@dc.dataclass
class TriVLAPolicyConfig:
    """Which model, how often each system runs, and where the policy plugs in; every default is the shipped
    model's with make_station's port names and the robot's base at the world origin."""

    # The checkpoint folder (config.json + weights) to load; None: the shipped model, models/trivla_cpu.
    checkpoint: Optional[str] = None
    # Update periods [s] of System 2 (vision-language), System 3 (dynamics) and System 1 (which replans once
    # per period); the defaults replan once per chunk of 10 actions at 36 Hz.
    vision_language_period_s: float = PolicyRates.vision_language_period_s
    dynamics_period_s: float = PolicyRates.dynamics_period_s
    policy_period_s: float = PolicyRates.policy_period_s
    # When an inference's result becomes visible in sim time: "zero" (at once), "fixed" (latency_seconds
    # after its observation) or "measured" (the inference's wall time after it); a busy system skips ticks.
    latency_mode: str = "zero"
    # The delay [s] of latency_mode "fixed".
    latency_seconds: float = 0.0
    # ACT-style temporal ensembling of overlapping chunks (weight decay m >= 0), or None to play the newest chunk.
    ensemble_decay: Optional[float] = None
    # Seed of the systems' inferences (System 1's flow-matching noise, System 3's feature noise).
    seed: int = 0
    # The ports of `station` the policy reads and drives, by name (make_station's). Port objects given to
    # ApplyTriVLAPolicyConfig replace these, as in add_trivla_policy.
    # ImageRgba8U of the third-person camera, model size (224x224 for the shipped model).
    static_camera: str = "static_camera.rgb_image_now"
    # ImageRgba8U of the camera on the hand.
    wrist_camera: str = "wrist_camera.rgb_image_now"
    # 18-vector Panda state: q (7 arm [rad], 2 fingers [m]) then v.
    robot_state: str = "panda.state"
    # Input for the 7 arm joint setpoints [rad].
    arm_position: str = "panda.position"
    # Input for the distance between the fingers [m].
    gripper_width: str = "panda.gripper_width"
    # X_WB: the pose of the robot's base (`panda_link0`) in the world (default: at the origin, unrotated).
    X_WB: Transform = dc.field(default_factory=Transform)
    # Or the base frame's scoped name in the plant given to ApplyTriVLAPolicyConfig, e.g. "panda::panda_link0":
    # X_WB is then read from the plant's weld (leave X_WB out).
    base_frame: Optional[str] = None
    # Name of the policy in the diagram; its diff-IK is `{name}_diffik`.
    name: str = "trivla_policy"

    def policy_rates(self) -> PolicyRates:
        """The PolicyRates these fields give; ValueError naming the field for a bad value."""
        try:
            latency = LatencyModel(self.latency_mode, self.latency_seconds)
        except ValueError as error:
            raise ValueError(f"TriVLAPolicyConfig.latency_mode / latency_seconds: {error}") from None
        rates = PolicyRates(vision_language_period_s=self.vision_language_period_s,
                            dynamics_period_s=self.dynamics_period_s, policy_period_s=self.policy_period_s,
                            latency=latency, ensemble_decay=self.ensemble_decay)
        try:
            rates.validate()
        except ValueError as error:
            raise ValueError(str(error).replace("PolicyRates.", "TriVLAPolicyConfig.")) from None
        return rates

    def base_pose(self, plant: MultibodyPlant | None) -> RigidTransform:
        """X_WB from `X_WB` or, with `base_frame`, from `plant`; ValueError naming the field otherwise."""
        if self.X_WB.base_frame not in (None, "world"):
            raise ValueError(f"TriVLAPolicyConfig.X_WB.base_frame must be 'world' (or left out): X_WB is the base's "
                             f"pose in the world; got {self.X_WB.base_frame!r}")
        try:
            X_WB = self.X_WB.GetDeterministicValue()
        except Exception as error:
            raise ValueError(f"TriVLAPolicyConfig.X_WB must be a fixed pose (no random distributions): {error}") \
                from None
        if self.base_frame is None:
            return X_WB
        if not X_WB.IsExactlyIdentity():
            raise ValueError("TriVLAPolicyConfig: give X_WB or base_frame, not both")
        if plant is None:
            raise ValueError(f"TriVLAPolicyConfig.base_frame {self.base_frame!r} is read from a plant: pass "
                             "plant= to ApplyTriVLAPolicyConfig (or give X_WB instead)")
        scoped = ScopedName.Parse(self.base_frame)
        instance_name, frame_name = scoped.get_namespace(), scoped.get_element() or BASE_FRAME
        if not instance_name or not plant.HasModelInstanceNamed(instance_name):
            raise ValueError(f"TriVLAPolicyConfig.base_frame {self.base_frame!r}: no model instance "
                             f"{instance_name!r} in the plant (write it as 'instance::frame', e.g. "
                             f"'panda::{BASE_FRAME}')")
        try:
            return robot_base_pose(plant, plant.GetModelInstanceByName(instance_name), frame_name)
        except ValueError as error:
            raise ValueError(f"TriVLAPolicyConfig.base_frame {self.base_frame!r}: {error}") from None


def ApplyTriVLAPolicyConfig(
    config: TriVLAPolicyConfig,
    builder: DiagramBuilder,
    *,
    station: System | None = None,
    plant: MultibodyPlant | None = None,
    model: TriVLA | None = None,
    static_camera: OutputPort | None = None,
    wrist_camera: OutputPort | None = None,
    robot_state: OutputPort | None = None,
    arm_position: InputPort | None = None,
    gripper_width: InputPort | None = None,
    diffik_params: DiffIKParams | None = None,
) -> TriVLAPolicy:
    """Load the model `config.checkpoint` names (unless `model` is given) and add the policy and its diff-IK to
    `builder`, wired to `station`'s ports named in `config` or to the port objects given here (then `station`
    may be None). `plant` is needed only for `config.base_frame`. Returns the TriVLAPolicy, whose
    `instruction` input is left for the caller."""
    if not isinstance(config, TriVLAPolicyConfig):
        raise TypeError(f"ApplyTriVLAPolicyConfig needs a TriVLAPolicyConfig, got {type(config).__name__}")
    if model is not None and config.checkpoint is not None:
        raise ValueError(f"ApplyTriVLAPolicyConfig: TriVLAPolicyConfig.checkpoint ({config.checkpoint!r}) and "
                         "model= both say which model to use: give one")
    rates = config.policy_rates()
    X_WB = config.base_pose(plant)
    if model is None:
        # load_model lives with the jobs that pick a model (eval/); it needs only nn/ and the models folder.
        from trivla_drake.eval.model_loading import load_model

        model = load_model(config.checkpoint)
    given = dict(static_camera=static_camera, wrist_camera=wrist_camera, robot_state=robot_state,
                 arm_position=arm_position, gripper_width=gripper_width)
    ports = {key: getattr(config, key) if port is None else port for key, port in given.items()}
    return add_trivla_policy(builder, station, model, rates=rates, seed=config.seed, X_WB=X_WB,
                             diffik_params=diffik_params, name=config.name, **ports)
