"""lift_block's success predicate: a block resting on another block is not lifted, a carried one is.

A 4.5 cm block stacked on another has its centre at 6.75 cm, above a 5 cm threshold: halving the lift
height (0.10 m) would count every stacked block as lifted; only closed-loop tests noticed that before.
"""

import numpy as np

from trivla_drake.tasks import Layout, get_task
from trivla_drake.tasks.scene import BLOCK_HALF, BLOCK_SIZE, BlockPlacement, SceneSpec, scene_from_spec, tcp_pose

LAYOUT = Layout.default()
FAR_BLUE = {"blue": BlockPlacement((0.55, -0.1, BLOCK_HALF), 0.0)}


def _scene(green_z: float, *, held: bool = False):
    """Red on the table at (0.45, 0.05); green above it, its centre at `green_z`."""
    blocks = {
        "red": BlockPlacement((0.45, 0.05, BLOCK_HALF), 0.1),
        "green": BlockPlacement((0.45, 0.05, green_z), 0.1),
        **FAR_BLUE,
    }
    scene = scene_from_spec(SceneSpec(blocks=blocks), LAYOUT)
    if held:  # closed fingers around the green block
        scene.tcp, scene.finger_width = tcp_pose(scene.block_position("green"), 0.1), BLOCK_SIZE
    return scene


def test_a_block_resting_on_another_block_is_not_lifted():
    lift = get_task("lift_block")
    stacked = _scene(BLOCK_HALF + BLOCK_SIZE)
    assert stacked.stacked_on("green", "red")  # the scene is what the test says it is
    assert np.isclose(stacked.block_position("green")[2], 0.0675)
    assert not lift.success(("green",), stacked, stacked), \
        f"a block resting on another (centre at 0.0675 m) counts as lifted (lift height {lift.LIFT_Z} m)"
    # Nor is it lifted while the hand, closed on it, has raised it only a little off its base.
    nudged = _scene(BLOCK_HALF + BLOCK_SIZE + 0.02, held=True)
    assert nudged.is_held("green")
    assert not lift.success(("green",), stacked, nudged), \
        f"a block raised 2 cm off its base (centre at 0.0875 m) counts as lifted (lift height {lift.LIFT_Z} m)"


def test_a_block_carried_above_the_lift_height_is_lifted():
    lift = get_task("lift_block")
    stacked = _scene(BLOCK_HALF + BLOCK_SIZE)
    carried = _scene(0.12, held=True)
    assert carried.is_held("green")
    assert lift.success(("green",), stacked, carried), f"a block carried at 0.12 m is not lifted ({lift.LIFT_Z} m)"
    # The red base, still on the table, is not lifted in either scene.
    assert not lift.success(("red",), stacked, carried)
