"""The instruction grounding anchored on the static camera's image cells (`PolicyConfig.grounding_anchor_camera`,
nn/token_anchor.py, nn/camera_cells.py): each cell's place on the table is the camera's geometry, the
anchored sub-goal is the places the query picks, it learns positions that only *which* token says, it
saves and loads, a run adds it keeping every other weight, and bad settings are refused naming the field."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.camera_cells import cell_table_points, check_calibration, rotation_from_rpy
from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint
from trivla_drake.nn.config import make_config
from trivla_drake.nn.instruction_grounding import InstructionGrounding
from trivla_drake.nn.panda_tcp import denormalize_position, normalize_position
from trivla_drake.nn.token_anchor import TokenAnchor
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.trainer import apply_ablations

# The default scenario's static camera (station/cameras.py: camera_calibration gives these; a station test
# checks them against the renderer).
STATIC_CAMERA = (1.0, 0.45, 0.62, -2.2537436631002783, 0.0, 2.2352431730291378,
                 215.15, 215.15, 111.5, 111.5, 224.0, 224.0)


def _config(anchor: tuple = STATIC_CAMERA):
    config = make_config("tiny")
    return dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, grounding_anchor_camera=anchor))


def test_each_cells_place_projects_back_to_its_cells_centre():
    places = cell_table_points(STATIC_CAMERA, 8, 0.0225)
    assert places.shape == (64, 3) and np.allclose(places[:, 2], 0.0225)
    x, y, z, roll, pitch, yaw, fx, fy, cx, cy, _, _ = STATIC_CAMERA
    in_camera = (places - np.array([x, y, z])) @ rotation_from_rpy(roll, pitch, yaw)  # R^T p, row-wise
    u = fx * in_camera[:, 0] / in_camera[:, 2] + cx
    v = fy * in_camera[:, 1] / in_camera[:, 2] + cy
    rows, cols = np.divmod(np.arange(64), 8)
    np.testing.assert_allclose(u, 28 * cols + 13.5, atol=1e-6)
    np.testing.assert_allclose(v, 28 * rows + 13.5, atol=1e-6)
    # The camera looks from the front left: the image's bottom row is nearer to it than its top row.
    camera = np.array([x, y])
    assert np.linalg.norm(places[56:, :2] - camera, axis=1).max() < np.linalg.norm(places[:8, :2] - camera, axis=1).min()


@pytest.mark.parametrize("calibration, message", [
    (STATIC_CAMERA[:11], "must have 12 numbers"),
    (STATIC_CAMERA[:6] + (0.0,) + STATIC_CAMERA[7:], "fx must be positive"),
    (STATIC_CAMERA[:10] + (float("nan"), 224.0), "finite"),
    (STATIC_CAMERA[:10] + (True, 224.0), "finite numbers"),
    (3.0, "must be 12 numbers"),
    ((0.4, 0.0, 0.01) + STATIC_CAMERA[3:], "does not look down"),  # below the blocks' plane
    (STATIC_CAMERA[:3] + (0.0,) + STATIC_CAMERA[4:], "does not look down"),  # roll 0: it looks straight up
    (STATIC_CAMERA[:3] + (-math.pi / 2,) + STATIC_CAMERA[4:], "does not look down"),  # level: half sees the sky
])
def test_bad_calibrations_are_refused_naming_the_field(tmp_path, calibration, message):
    with pytest.raises(ValueError, match=f"policy.grounding_anchor_camera.*{message}"):
        _config(calibration)
    train = {"stage": "policy", "data": str(tmp_path), "out": str(tmp_path / "o"), "grounding_weight": 1.0}
    with pytest.raises(ValueError, match=f"^grounding_anchor_camera.*{message}"):
        TrainConfig(**train, grounding_anchor_camera=calibration).resolved().validate()


def test_a_camera_that_sees_the_table_only_in_part_is_refused_by_the_geometry_too():
    level = STATIC_CAMERA[:3] + (-math.pi / 2,) + STATIC_CAMERA[4:]  # its image's lower half sees the table
    with pytest.raises(ValueError, match="^static: .*does not look down"):
        cell_table_points(level, 8, 0.0225, "static")
    with pytest.raises(ValueError, match="^static: fx must be positive"):
        cell_table_points(STATIC_CAMERA[:6] + (0.0,) + STATIC_CAMERA[7:], 8, 0.0225, "static")
    check_calibration(level, "static")  # as numbers it is fine: only the table's plane rules it out


def test_the_anchor_is_the_picked_cells_place_plus_its_offset():
    places = torch.tensor([[0.3, 0.1, 0.02], [0.6, -0.2, 0.02], [0.5, 0.3, 0.02]])
    anchor = TokenAnchor(8, places)
    tokens = torch.zeros(1, 3, 8)
    tokens[0, 1, 0] = 1.0  # only token 1 carries the feature the query looks for
    with torch.no_grad():
        anchor.key[1].weight.copy_(torch.eye(8) * 100.0)
        anchor.key[1].bias.zero_()
        anchor.query.weight.copy_(torch.eye(8))
        anchor.query.bias.zero_()
    query = torch.zeros(1, 8)
    query[0, 0] = 1.0
    position, weights = anchor(query, tokens)
    assert weights[0, 1] > 0.999
    torch.testing.assert_close(denormalize_position(position), places[1:2], atol=1e-3, rtol=0)
    with torch.no_grad():
        anchor.offset[1].bias.copy_(torch.tensor([0.1, 0.0, 0.0]))
    torch.testing.assert_close(denormalize_position(anchor(query, tokens)[0]),
                               places[1:2] + torch.tensor([[0.02, 0.0, 0.0]]), atol=1e-3, rtol=0)
    with pytest.raises(ValueError, match=r"tokens must be \(B, 3, D\)"):
        anchor(query, tokens[:, :2])


def _train_grounding(anchored: bool, steps: int) -> float:
    """Held-out error [m] of a grounding trained on tokens that mark a block only by *which* token is
    lit (no position embedding): the block lies at that token's place."""
    generator = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    dim, cells = 16, 16
    places = torch.from_numpy(cell_table_points(STATIC_CAMERA, 4, 0.0225)).float()
    grounding = InstructionGrounding(dim, 2, anchor=TokenAnchor(dim, places) if anchored else None, anchor_start=0)
    optimizer = torch.optim.Adam(grounding.parameters(), lr=3e-3)
    marker = torch.randn(dim, generator=generator)

    def batch(size):
        which = torch.randint(cells, (size,), generator=generator)
        tokens = torch.randn(size, cells, dim, generator=generator) * 0.1
        tokens[torch.arange(size), which] += marker
        instruction = torch.randn(size, 3, dim, generator=generator) * 0.1
        return instruction, torch.ones(size, 3, dtype=torch.bool), tokens, places[which]

    for _ in range(steps):
        instruction, mask, tokens, target = batch(32)
        loss = (grounding(instruction, mask, tokens)[1] - normalize_position(target)).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    instruction, mask, tokens, target = batch(256)
    with torch.no_grad():
        predicted = denormalize_position(grounding(instruction, mask, tokens)[1])
    return (predicted - target)[:, :2].norm(dim=1).median().item()


def test_an_anchored_grounding_learns_where_only_which_token_says():
    anchored, plain = _train_grounding(True, 150), _train_grounding(False, 150)
    assert anchored < 0.02, anchored  # within 2 cm of the lit cell's place
    assert plain > 2 * anchored, (plain, anchored)


def test_the_model_saves_loads_and_predicts_with_the_anchor(tmp_path):
    model = TriVLA(_config()).eval()
    grid = math.isqrt(model.vision_language.num_image_tokens)
    expected = normalize_position(torch.from_numpy(cell_table_points(STATIC_CAMERA, grid, 0.0225)).float())
    torch.testing.assert_close(model.policy.grounding.anchor.places.detach(), expected)
    assert model.policy.grounding.anchor_start == model.vision_language.image_token_span(0)[0]
    obs = example_observation()
    subgoal = model.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"])
    save_checkpoint(model, str(tmp_path / "m"))
    loaded = load_checkpoint(str(tmp_path / "m"))
    assert loaded.config.policy.grounding_anchor_camera == STATIC_CAMERA
    np.testing.assert_array_equal(
        loaded.predict_subgoal(obs["static_rgb"], obs["wrist_rgb"], obs["instruction"], obs["state"]), subgoal)
    assert {n for n in model.policy.binding_parameters() if ".anchor." in n}  # a bind trains it, a follow keeps it


def test_a_run_adds_the_anchor_keeping_every_weight_and_a_follow_may_not():
    grounded = TriVLA(_config(()))
    rebuilt = apply_ablations(grounded, True, True, "--init", grounding_anchor_camera=STATIC_CAMERA)
    assert rebuilt.config.policy.grounding_anchor_camera == STATIC_CAMERA and rebuilt.policy.grounding.anchor is not None
    for name, p in grounded.policy.named_parameters():
        assert torch.equal(p, rebuilt.policy.get_parameter(name)), name
    assert apply_ablations(rebuilt, True, True, "--init") is rebuilt  # kept once there
    assert apply_ablations(rebuilt, True, True, "--init", grounding_anchor_camera=STATIC_CAMERA) is rebuilt


def test_an_anchor_without_grounding_is_refused_naming_the_field(tmp_path):
    config = make_config("tiny")
    with pytest.raises(ValueError, match="policy.grounding_anchor_camera.*policy.instruction_grounding"):
        dataclasses.replace(config, policy=dataclasses.replace(config.policy, grounding_anchor_camera=STATIC_CAMERA))
    base = {"stage": "policy", "data": str(tmp_path), "out": str(tmp_path / "o"),
            "grounding_anchor_camera": STATIC_CAMERA}
    for options in ({}, {"stage": "video"}):
        with pytest.raises(ValueError, match=r"grounding_anchor_camera \(--grounding-anchor\)"):
            TrainConfig(**{**base, **options}).resolved().validate()
    with pytest.raises(ValueError, match="grounding_anchor_camera: fx must be positive"):
        TrainConfig(**{**base, "grounding_weight": 1.0,
                       "grounding_anchor_camera": STATIC_CAMERA[:6] + (0.0,) + STATIC_CAMERA[7:]}).resolved().validate()
    TrainConfig(**{**base, "grounding_weight": 1.0}).resolved().validate()


# A camera 10 cm above the tool-centre point, looking along its z axis (down for a hand pointing down).
DOWN_CAMERA = (0.0, 0.0, -0.1, 0.0, 0.0, 0.0, 100.0, 100.0, 111.5, 111.5, 224.0, 224.0)


def _tcp_features(position, rotation) -> torch.Tensor:
    columns = torch.tensor(rotation, dtype=torch.float32)[:, :2].T.reshape(6)
    return torch.cat([normalize_position(torch.tensor(position, dtype=torch.float32)), columns])[None]


def test_the_wrist_cells_are_placed_below_the_hand_and_a_ray_that_misses_the_table_gets_no_weight():
    from trivla_drake.nn.camera_cells import camera_pose, cell_rays

    rotation, origin = camera_pose(DOWN_CAMERA)
    anchor = TokenAnchor(8, torch.zeros(1, 3), wrist_rays=torch.from_numpy(cell_rays(DOWN_CAMERA, 2)).float(),
                         wrist_pose=(torch.from_numpy(rotation).float(), torch.from_numpy(origin).float()),
                         plane_height=0.0225)
    hand_down = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]  # tcp z points down
    places, valid = anchor.wrist_places(_tcp_features([0.5, 0.1, 0.2], hand_down))
    places = denormalize_position(places)[0]
    assert valid.all()
    # The camera is at z = 0.3, 0.2775 above the plane; the 2 x 2 cells centre 56 px off the axis, f = 100 px.
    reach = 0.2775 * 56.0 / 100.0
    expected = torch.tensor([[0.5 - reach, 0.1 + reach], [0.5 + reach, 0.1 + reach],
                             [0.5 - reach, 0.1 - reach], [0.5 + reach, 0.1 - reach]])
    torch.testing.assert_close(places[:, :2], expected, atol=1e-4, rtol=0)
    assert torch.allclose(places[:, 2], torch.tensor(0.0225))
    hand_up = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    _, valid = anchor.wrist_places(_tcp_features([0.5, 0.1, 0.2], hand_up))
    assert not valid.any()
    tokens, wrist = torch.randn(1, 1, 8), torch.randn(1, 4, 8)
    _, weights = anchor(torch.randn(1, 8), tokens, wrist, _tcp_features([0.5, 0.1, 0.2], hand_up))
    assert weights[0, 0] == 1.0 and (weights[0, 1:] == 0).all()  # only the static cell is left
    with pytest.raises(ValueError, match=r"tcp must be \(1, 9\)"):
        anchor(torch.randn(1, 8), tokens, wrist)
    with pytest.raises(ValueError, match=r"wrist_tokens must be \(1, 4, D\)"):
        anchor(torch.randn(1, 8), tokens, wrist[:, :3], _tcp_features([0.5, 0.1, 0.2], hand_down))


def test_a_wrist_anchored_model_needs_the_state_saves_and_loads(tmp_path):
    model = TriVLA(dataclasses.replace(_config(), policy=dataclasses.replace(
        _config().policy, grounding_anchor_wrist_camera=DOWN_CAMERA))).eval()
    obs = example_observation()
    views = obs["static_rgb"], obs["wrist_rgb"], obs["instruction"]
    with pytest.raises(ValueError, match="state is required.*grounding_anchor_wrist_camera"):
        model.predict_subgoal(*views)
    subgoal = model.predict_subgoal(*views, obs["state"])
    moved = obs["state"].copy()
    moved[0] += 0.3
    assert not np.allclose(model.predict_subgoal(*views, moved), subgoal)  # the wrist cells moved with the hand
    save_checkpoint(model, str(tmp_path / "m"))
    loaded = load_checkpoint(str(tmp_path / "m"))
    assert loaded.config.policy.grounding_anchor_wrist_camera == DOWN_CAMERA
    np.testing.assert_array_equal(loaded.predict_subgoal(*views, obs["state"]), subgoal)
    rebuilt = apply_ablations(TriVLA(_config()), True, True, "--init", grounding_anchor_wrist_camera=DOWN_CAMERA)
    assert rebuilt.policy.grounding.anchor.wrist_cells == model.vision_language.num_image_tokens


def test_a_wrist_anchor_without_a_static_one_or_the_tcp_features_is_refused(tmp_path):
    config = make_config("tiny")
    policy = dataclasses.replace(config.policy, tcp_features=True, instruction_grounding=True,
                                 grounding_anchor_wrist_camera=DOWN_CAMERA)
    with pytest.raises(ValueError, match="policy.grounding_anchor_wrist_camera.*policy.grounding_anchor_camera"):
        dataclasses.replace(config, policy=policy)
    with pytest.raises(ValueError, match="policy.grounding_anchor_wrist_camera.*policy.tcp_features"):
        dataclasses.replace(config, policy=dataclasses.replace(policy, tcp_features=False,
                                                               grounding_anchor_camera=STATIC_CAMERA))
    base = {"stage": "policy", "data": str(tmp_path), "out": str(tmp_path / "o"), "grounding_weight": 1.0,
            "grounding_anchor_wrist_camera": DOWN_CAMERA}
    with pytest.raises(ValueError, match=r"grounding_anchor_wrist_camera \(--grounding-anchor-wrist\).*--grounding-anchor"):
        TrainConfig(**base).resolved().validate()
    TrainConfig(**base, grounding_anchor_camera=STATIC_CAMERA).resolved().validate()


def test_the_train_flags_take_the_default_scenarios_cameras():
    from trivla_drake.cli import build_parser
    from trivla_drake.train.cli_commands import config_from_args

    argv = ["train", "--stage", "policy", "--data", "d", "--out", "o", "--grounding-weight", "1"]
    plain = config_from_args(build_parser().parse_args(argv))
    assert plain.grounding_anchor_camera == () and plain.grounding_anchor_wrist_camera == ()
    config = config_from_args(build_parser().parse_args(argv + ["--grounding-anchor", "--grounding-anchor-wrist"]))
    np.testing.assert_allclose(config.grounding_anchor_camera, STATIC_CAMERA, atol=1e-6)
    # The wrist camera: 7 cm beside the tool-centre point and 8.34 cm behind it (up, with the hand pointing
    # down), tilted 15 degrees; f = 112 / tan(37.5 degrees).
    np.testing.assert_allclose(config.grounding_anchor_wrist_camera[:6],
                               (0.07, 0.0, -0.0834, 0.0, -math.radians(15), -math.pi / 2), atol=1e-6)
    assert config.grounding_anchor_wrist_camera[6] == pytest.approx(112 / math.tan(math.radians(37.5)))


def test_the_anchors_places_are_not_decayed_and_its_matrices_are(tmp_path):
    from trivla_drake.train.trainer import _optimizer

    model = TriVLA(_config())
    config = TrainConfig(stage="policy", data=str(tmp_path), out=str(tmp_path / "o"), grounding_weight=1.0,
                         weight_decay=0.1).resolved()
    optimizer = _optimizer(model.policy, config)
    decay_of = {id(p): group["weight_decay"] for group in optimizer.param_groups for p in group["params"]}
    anchor = model.policy.grounding.anchor
    assert decay_of[id(anchor.places)] == 0.0
    assert decay_of[id(anchor.key[1].weight)] == 0.1


def test_the_two_read_outs_share_one_computation_of_the_cells():
    places = torch.from_numpy(cell_table_points(STATIC_CAMERA, 2, 0.0225)).float()
    anchor = TokenAnchor(8, places, wrist_rays=torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]]),
                         wrist_pose=(torch.eye(3), torch.zeros(3)), plane_height=0.0225)
    grounding = InstructionGrounding(8, 2, reads_gripper=True, anchor=anchor, anchor_start=0, anchor_wrist_start=4)
    computed = []
    cells = anchor.cells
    anchor.cells = lambda *args: computed.append(1) or cells(*args)
    tcp = _tcp_features([0.5, 0.1, 0.3], [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]).expand(2, -1)
    words = torch.randn(2, 3, 8)
    goal, subgoal = grounding(words, torch.ones(2, 3, dtype=torch.bool), torch.randn(2, 6, 8), tcp,
                              torch.tensor([[0.0], [1.0]]))
    assert computed == [1] and subgoal.shape == (2, 3)  # both read-outs ran, on one computation of the cells
    # The geometry is float32 whatever the tcp's dtype or autocast: bfloat16 would cost millimetres.
    tcp_bf16 = tcp.bfloat16()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        places_bf16, valid_bf16 = anchor.wrist_places(tcp_bf16)
    places_fp32, valid_fp32 = anchor.wrist_places(tcp_bf16.float())
    assert places_bf16.dtype == torch.float32 and torch.equal(valid_bf16, valid_fp32)
    torch.testing.assert_close(places_bf16, places_fp32, rtol=0, atol=0)


def test_a_held_only_bind_may_not_add_an_anchor_both_read_outs_would_use(tmp_path):
    from trivla_drake.train.trainer import build_model

    config = _config(())
    save_checkpoint(TriVLA(dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, grounding_reads_gripper=True))), str(tmp_path / "init"))
    held_only = {"stage": "policy", "preset": "tiny", "data": str(tmp_path), "out": str(tmp_path / "o"),
                 "grounding_weight": 1.0,
                 "init": str(tmp_path / "init"), "grounding_phase": "bind", "keep_grounding": True,
                 "grounding_reads_gripper": True, "bind_held_only": True}
    run = TrainConfig(**held_only, grounding_anchor_camera=STATIC_CAMERA).resolved()
    run.validate()
    with pytest.raises(ValueError, match=r"grounding_anchor_camera \(--grounding-anchor\).*--bind-held-only"):
        build_model(run, None)
    assert build_model(TrainConfig(**held_only).resolved(), None).policy.grounding.anchor is None
