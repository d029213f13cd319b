"""Our OSQP diff-IK tick against Drake's DoDifferentialInverseKinematics on the same problems."""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsParameters,
    DoDifferentialInverseKinematics,
)
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant

from trivla_drake.robot.osqp_diffik import DiffIKParams, OsqpDifferentialIK
from trivla_drake.robot.panda_assets import drake_panda_dir
from trivla_drake.robot.panda_description import EE_FRAME
from trivla_drake.robot.panda_kinematics import PandaKinematics


def _arm_only_urdf() -> str:
    """The converted Panda's URDF text without its fingers, so both solvers see the same 7 joints."""
    package = drake_panda_dir()
    tree = ET.parse(package / "panda.urdf")
    robot = tree.getroot()
    for mesh in robot.iter("mesh"):
        mesh.set("filename", str(package / mesh.get("filename")))
    fingers = {"panda_leftfinger", "panda_rightfinger"}
    for element in list(robot):
        if element.tag == "link" and element.get("name") in fingers:
            robot.remove(element)
        elif element.tag == "joint" and element.find("child").get("link") in fingers:
            robot.remove(element)
        elif element.tag == "transmission" and "finger" in element.get("name"):
            robot.remove(element)
    return ET.tostring(robot, encoding="unicode")


def _drake_arm(params: DiffIKParams):
    plant = MultibodyPlant(time_step=0.0)
    parser = Parser(plant)
    (instance,) = parser.AddModelsFromString(_arm_only_urdf(), "urdf")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("panda_link0", instance))
    plant.Finalize()
    kinematics = PandaKinematics()
    drake_params = DifferentialInverseKinematicsParameters(7, 7)
    drake_params.set_time_step(params.dt)
    drake_params.set_nominal_joint_position(np.asarray(params.q_nominal))
    drake_params.set_joint_position_limits((kinematics.q_lower, kinematics.q_upper))
    v_limit = params.velocity_scale * kinematics.v_max
    drake_params.set_joint_velocity_limits((-v_limit, v_limit))
    return plant, plant.CreateDefaultContext(), plant.GetFrameByName(EE_FRAME), drake_params


def benchmark_diffik(num_problems: int = 2000, seed: int = 0) -> dict:
    """Median per-tick time [us] of both solvers over the same random (q, reachable target) pairs."""
    rng = np.random.default_rng(seed)
    params = DiffIKParams()
    kinematics = PandaKinematics()
    ours = OsqpDifferentialIK(kinematics, params)
    plant, context, frame, drake_params = _drake_arm(params)
    span = kinematics.q_upper - kinematics.q_lower
    problems = []
    for _ in range(num_problems):
        q = kinematics.q_lower + span * rng.uniform(0.1, 0.9, size=7)
        nearby = np.clip(q + rng.normal(scale=0.05, size=7), kinematics.q_lower, kinematics.q_upper)
        problems.append((q, kinematics.ee_pose(nearby)))

    our_times, drake_times = [], []
    for q, target in problems:
        start = time.perf_counter()
        ours.solve(q, target)
        our_times.append(time.perf_counter() - start)
    for q, target in problems:
        start = time.perf_counter()
        plant.SetPositions(context, q)
        DoDifferentialInverseKinematics(plant, context, RigidTransform(target), frame, drake_params)
        drake_times.append(time.perf_counter() - start)
    ours_us = 1e6 * float(np.median(our_times))
    drake_us = 1e6 * float(np.median(drake_times))
    return {
        "diffik_median_us": ours_us,
        "drake_diffik_median_us": drake_us,
        "diffik_speedup_vs_drake": drake_us / ours_us,
        "diffik_problems": num_problems,
    }
