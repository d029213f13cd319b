"""The Panda's joint-level driver: implicit PD actuators in the plant plus gravity compensation.

Like Franka's own joint impedance mode, gravity is cancelled by a feed-forward torque and the
joints track position setpoints with PD gains. The PD runs inside the plant's discrete solver
(implicitly), so stiff gains stay stable at the plant's time step.
"""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import PdControllerGains
from pydrake.systems.controllers import InverseDynamics
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import MatrixGain, Multiplexer

from trivla_drake.robot.panda_description import ARM_JOINTS, FINGER_JOINTS
from trivla_drake.station.scenario import PandaDriverConfig

N_ARM = len(ARM_JOINTS)
N_JOINTS = N_ARM + len(FINGER_JOINTS)
MAX_GRIPPER_WIDTH = 0.08  # [m] both fingers at their 0.04 m limit


def make_panda_only_plant(urdf_path: str, package_map_source: Parser, *,
                          X_WB: RigidTransform | None = None) -> MultibodyPlant:
    """A continuous plant of the Panda alone, its base `panda_link0` welded at X_WB (its pose in the world,
    identity by default), for the driver's dynamics terms: give the same X_WB as in the simulated plant when
    the base is tilted, so gravity compensation pulls the right way (a base only moved or turned about the
    vertical needs none)."""
    plant = MultibodyPlant(time_step=0.0)
    parser = Parser(plant)
    parser.package_map().AddMap(package_map_source.package_map())
    (instance,) = parser.AddModels(urdf_path)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("panda_link0", instance), X_WB or RigidTransform())
    plant.Finalize()
    return plant


def add_panda_driver(
    builder: DiagramBuilder,
    plant: MultibodyPlant,
    panda_instance,
    controller_plant: MultibodyPlant,
    config: PandaDriverConfig,
):
    """Wire the Panda's driver into `builder`; returns (arm setpoint InputPort, gripper width InputPort), to
    connect or export.

    `plant`: the simulated MultibodyPlant, finalized, with the Panda (from `drake_panda_urdf()`) as
    `panda_instance`; `controller_plant`: `make_panda_only_plant(...)`, owned by the diagram from here on;
    `config`: a `PandaDriverConfig` (PD gains; its defaults are the station's).
    Arm setpoint: 7 joint positions [rad]. Gripper width: distance between the fingers [m]
    (each finger tracks half of it). The measured state is the plant's `get_state_output_port(panda_instance)`,
    18-vector [q (7 arm [rad], 2 fingers [m]); v], what the policy's `robot_state` reads.
    """
    if len(config.arm_kp) != N_ARM or len(config.arm_kd) != N_ARM:
        raise ValueError(
            f"panda_driver.arm_kp and panda_driver.arm_kd need {N_ARM} values each, "
            f"got {len(config.arm_kp)} and {len(config.arm_kd)}"
        )
    for field in ("arm_kp", "arm_kd", "finger_kp", "finger_kd"):
        values = getattr(config, field)
        for i, value in enumerate(values if isinstance(values, list) else [values]):
            if not (np.isfinite(value) and value >= 0):  # Drake would abort the process on a negative gain
                where = f"panda_driver.{field}" + (f"[{i}]" if isinstance(values, list) else "")
                raise ValueError(f"{where} must be a finite gain >= 0, got {value}")
    gains = dict(zip(ARM_JOINTS, zip(config.arm_kp, config.arm_kd)))
    gains.update({name: (config.finger_kp, config.finger_kd) for name in FINGER_JOINTS})
    for name, (kp, kd) in gains.items():
        actuator = plant.GetJointActuatorByName(f"{name}_motor", panda_instance)
        actuator.set_controller_gains(PdControllerGains(p=kp, d=kd))

    # Gravity compensation from the Panda-only plant; its velocity order is the actuator order.
    b_matrix = controller_plant.MakeActuationMatrix()
    if not np.array_equal(b_matrix, np.eye(N_JOINTS)):
        raise RuntimeError("the Panda's actuators are not in joint order; the driver needs them so")
    # The diagram must own the controller plant: InverseDynamics keeps only a reference to it.
    builder.AddNamedSystem("panda_controller_plant", controller_plant)
    gravity = builder.AddNamedSystem(
        "panda_gravity_compensation",
        InverseDynamics(controller_plant, InverseDynamics.InverseDynamicsMode.kGravityCompensation),
    )
    builder.Connect(plant.get_state_output_port(panda_instance), gravity.get_input_port_estimated_state())
    builder.Connect(gravity.get_output_port_generalized_force(), plant.get_actuation_input_port(panda_instance))

    # Setpoints [q_arm (7), width (1)] -> desired state [q (9), v (9)] with zero desired velocity.
    mux = builder.AddNamedSystem("panda_setpoint_mux", Multiplexer([N_ARM, 1]))
    to_desired = np.zeros((2 * N_JOINTS, N_ARM + 1))
    to_desired[:N_ARM, :N_ARM] = np.eye(N_ARM)
    to_desired[N_ARM : N_JOINTS, N_ARM] = 0.5
    expand = builder.AddNamedSystem("panda_desired_state", MatrixGain(to_desired))
    builder.Connect(mux.get_output_port(), expand.get_input_port())
    builder.Connect(expand.get_output_port(), plant.get_desired_state_input_port(panda_instance))
    return mux.get_input_port(0), mux.get_input_port(1)
