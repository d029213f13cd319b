"""Reading a `SceneState` from a station's Context and writing a `SceneSpec` into it."""

from __future__ import annotations

import numpy as np
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import Context, Diagram

from trivla_drake.station.button_lamp import LAMP_LIFT_ON
from trivla_drake.tasks.scene import BLOCK_COLORS, Layout, SceneSpec, SceneState, yaw_rotation


class StationHandles:
    """The bodies, joints and systems of a station (from `make_station`) that tasks look at."""

    def __init__(self, station: Diagram):
        self.station = station
        self.plant = plant = station.GetSubsystemByName("plant")
        self.lamp_logic = station.GetSubsystemByName("button_lamp_logic")
        self.panda = plant.GetModelInstanceByName("panda")
        self.blocks = {
            c: plant.GetBodyByName("block", plant.GetModelInstanceByName(f"block_{c}")) for c in BLOCK_COLORS
        }
        drawer = plant.GetModelInstanceByName("drawer")
        button = plant.GetModelInstanceByName("button")
        self.drawer_slide = plant.GetJointByName("drawer_slide", drawer)
        self.button_press = plant.GetJointByName("button_press", button)
        self.lamp_lift = plant.GetJointByName("lamp_lift", button)
        self.tcp_frame = plant.GetFrameByName("panda_hand_tcp", self.panda)
        self._bowl = plant.GetBodyByName("bowl", plant.GetModelInstanceByName("bowl"))
        self._cabinet = plant.GetBodyByName("cabinet", drawer)
        self._housing = plant.GetBodyByName("housing", button)
        self._cap = plant.GetBodyByName("cap", button)
        self._layout: Layout | None = None

    def layout(self, root_context: Context) -> Layout:
        """The welded fixtures' poses (read once)."""
        if self._layout is None:
            pc = self.plant.GetMyContextFromRoot(root_context)
            pose = lambda body: self.plant.EvalBodyPoseInWorld(pc, body).GetAsMatrix4()  # noqa: E731
            housing = pose(self._housing)
            cap_offset = self._cap_rest_offset()
            self._layout = Layout(
                bowl=pose(self._bowl),
                cabinet=pose(self._cabinet),
                button_housing=housing,
                cap_rest=(housing @ np.append(cap_offset, 1.0))[:3],
            )
        return self._layout

    def _cap_rest_offset(self) -> np.ndarray:
        # The cap's pose in the housing at joint position 0: the joint frames' fixed offsets.
        joint = self.button_press
        X_PF = joint.frame_on_parent().GetFixedPoseInBodyFrame()
        X_CM = joint.frame_on_child().GetFixedPoseInBodyFrame()
        return (X_PF @ X_CM.inverse()).translation()

    def read(self, root_context: Context) -> SceneState:
        """The scene's current state."""
        plant, pc = self.plant, self.plant.GetMyContextFromRoot(root_context)
        q = plant.GetPositions(pc, self.panda)
        lamp_context = self.lamp_logic.GetMyContextFromRoot(root_context)
        return SceneState(
            layout=self.layout(root_context),
            blocks={c: plant.EvalBodyPoseInWorld(pc, body).GetAsMatrix4() for c, body in self.blocks.items()},
            drawer_opening=float(self.drawer_slide.get_translation(pc)),
            lamp_on=bool(self.lamp_logic.GetOutputPort("lamp_on").Eval(lamp_context)[0] > 0.5),
            button_press=float(self.button_press.get_translation(pc)),
            tcp=self.tcp_frame.CalcPoseInWorld(pc).GetAsMatrix4(),
            finger_width=float(q[7] + q[8]),
            arm_q=np.array(q[:7]),
        )

    def apply(self, root_context: Context, spec: SceneSpec) -> None:
        """Put the scene into `spec`'s state, everything at rest (call before Simulator.Initialize)."""
        plant, pc = self.plant, self.plant.GetMyContextFromRoot(root_context)
        plant.SetVelocities(pc, np.zeros(plant.num_velocities()))
        for color, placement in spec.blocks.items():
            X = RigidTransform(RotationMatrix(yaw_rotation(placement.yaw)), np.asarray(placement.position))
            plant.SetFreeBodyPose(pc, self.blocks[color], X)
        self.drawer_slide.set_translation(pc, float(spec.drawer_opening))
        self.button_press.set_translation(pc, 0.0)
        self.lamp_lift.set_translation(pc, LAMP_LIFT_ON if spec.lamp_on else 0.0)
        self.lamp_logic.set_lit(self.lamp_logic.GetMyMutableContextFromRoot(root_context), spec.lamp_on)
        q = np.concatenate([np.asarray(spec.arm_q, dtype=float), [0.04, 0.04]])
        plant.SetPositions(pc, self.panda, q)
