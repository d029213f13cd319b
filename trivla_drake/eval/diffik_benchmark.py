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


def _random_problems(kinematics: PandaKinematics, rng, count: int) -> list:
    """Random q inside the limits, each with a reachable target a few centimetres away."""
    span = kinematics.q_upper - kinematics.q_lower
    problems = []
    for _ in range(count):
        q = kinematics.q_lower + span * rng.uniform(0.1, 0.9, size=7)
        nearby = np.clip(q + rng.normal(scale=0.05, size=7), kinematics.q_lower, kinematics.q_upper)
        problems.append((q, kinematics.ee_pose(nearby)))
    return problems


def _tracking_problems(kinematics: PandaKinematics, params: DiffIKParams, count: int) -> list:
    """The controller's real workload: consecutive ticks following a moving target (a 10 cm circle)."""
    solver = OsqpDifferentialIK(kinematics, params)
    q = np.asarray(params.q_nominal, dtype=float)
    start = kinematics.ee_pose(q)
    problems = []
    for tick in range(count):
        angle = 2 * np.pi * tick * params.dt / 4.0
        target = start.copy()
        target[:3, 3] += 0.1 * np.array([np.cos(angle) - 1.0, np.sin(angle), 0.0])
        problems.append((q.copy(), target))
        q = solver.solve(q, target).q_next
    return problems


def _median_us(solve, problems) -> float:
    times = []
    for q, target in problems:
        start = time.perf_counter()
        solve(q, target)
        times.append(time.perf_counter() - start)
    return 1e6 * float(np.median(times))


def benchmark_diffik(num_problems: int = 2000, seed: int = 0) -> dict:
    """Median per-tick time [us] of both solvers (kinematics + QP) on the same problems.

    Two problem sets: closed-loop tracking ticks (what the controller does every 10 ms) and random
    configurations with nearby targets (where joint-velocity bounds are often active).
    """
    params = DiffIKParams()
    kinematics = PandaKinematics()
    ours = OsqpDifferentialIK(kinematics, params)
    plant, context, frame, drake_params = _drake_arm(params)

    def drake_solve(q, target):
        plant.SetPositions(context, q)
        DoDifferentialInverseKinematics(plant, context, RigidTransform(target), frame, drake_params)

    result = {"diffik_problems": num_problems}
    problem_sets = {
        "": _tracking_problems(kinematics, params, num_problems),
        "random_": _random_problems(kinematics, np.random.default_rng(seed), num_problems),
    }
    for prefix, problems in problem_sets.items():
        ours_us = _median_us(ours.solve, problems)
        drake_us = _median_us(drake_solve, problems)
        result[f"diffik_{prefix}median_us"] = ours_us
        result[f"drake_diffik_{prefix}median_us"] = drake_us
        result[f"diffik_{prefix}time_ratio_to_drake"] = ours_us / drake_us
    return result
