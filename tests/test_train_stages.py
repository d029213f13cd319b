"""The three stages end to end on the tiny preset: each trains only its system, chains through
--init, writes a final checkpoint `load_checkpoint` reads, and the policy stage carries the dataset's
normalisation and computes System 2/3 features once."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from trivla_drake.config_io import with_flags
from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.nn import TriVLA, load_checkpoint, make_config, save_checkpoint
from trivla_drake.train import TrainConfig, train
from trivla_drake.train.config import OptimizerConfig
from trivla_drake.train.synthetic import write_synthetic_dataset


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """video -> vlm -> policy on a 3-episode synthetic dataset."""
    root = tmp_path_factory.mktemp("stages")
    data = write_synthetic_dataset(root / "data", episodes=3, length=24)
    common = dict(preset="tiny", batch_size=4, checkpoint_every=10, cache_dir=str(root / "cache"), progress=False,
                  optimizer=OptimizerConfig(warmup_steps=2), lr=1e-3, log_every=1)
    video = train(with_flags(TrainConfig(stage="video", data=data, out=str(root / "video"), steps=20, **common),
                             {"video.future_stride": 3}))
    vlm = train(with_flags(TrainConfig(stage="vlm", out=str(root / "vlm"), init=video["final_checkpoint"], steps=20,
                                       **common), {"vlm.vqa_scenes": 10, "vlm.vqa_questions_per_scene": 4}))
    policy = train(TrainConfig(stage="policy", data=data, out=str(root / "policy"), init=vlm["final_checkpoint"],
                               steps=20, **common))
    return {"root": root, "data": data, "common": common, "video": video, "vlm": vlm, "policy": policy}


def _weights(model: TriVLA, prefix: str) -> dict[str, torch.Tensor]:
    return {k: v for k, v in model.state_dict().items() if k.startswith(prefix)}


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _rows(run_dir) -> list[dict]:
    return [json.loads(line) for line in open(run_dir / "log.jsonl")]


def _losses(run_dir) -> list[float]:
    return [json.loads(line)["loss"] for line in open(run_dir / "log.jsonl")]


def test_video_stage_trains_only_system3_unet(runs):
    fresh = TriVLA(make_config("tiny", init_seed=0))
    video = load_checkpoint(runs["video"]["final_checkpoint"])
    assert not _same(_weights(video, "dynamics.unet."), _weights(fresh, "dynamics.unet."))
    for frozen in ("dynamics.vae.", "dynamics.text_encoder.", "vision_language.", "policy."):
        assert _same(_weights(video, frozen), _weights(fresh, frozen)), frozen
    losses = _losses(runs["root"] / "video")
    assert len(losses) == 20 and np.mean(losses[-5:]) < np.mean(losses[:5])
    assert runs["video"]["future_stride"] == 3 and runs["video"]["samples"] == 3 * 2 * (24 - 6)


def test_vlm_stage_trains_only_system2_and_reports_vqa_accuracy(runs):
    video = load_checkpoint(runs["video"]["final_checkpoint"])
    vlm = load_checkpoint(runs["vlm"]["final_checkpoint"])
    assert not _same(_weights(vlm, "vision_language."), _weights(video, "vision_language."))
    for frozen in ("dynamics.", "policy."):
        assert _same(_weights(vlm, frozen), _weights(video, frozen)), frozen
    losses = _losses(runs["root"] / "vlm")
    assert np.mean(losses[-5:]) < np.mean(losses[:5])
    summary = runs["vlm"]
    assert summary["vqa_eval_questions"] > 0 and 0.0 <= summary["vqa_accuracy"] <= 1.0


def test_policy_stage_trains_system1_with_the_dataset_normalisation(runs):
    vlm = load_checkpoint(runs["vlm"]["final_checkpoint"])
    policy = load_checkpoint(runs["policy"]["final_checkpoint"])
    assert not _same(_weights(policy, "policy."), _weights(vlm, "policy."))
    for frozen in ("vision_language.", "dynamics."):
        assert _same(_weights(policy, frozen), _weights(vlm, frozen)), frozen
    stats = LeRobotReader(runs["data"]).stats
    norm = policy.normalization
    assert norm.state_mean == pytest.approx(stats["observation.state"]["mean"])
    assert norm.action_min == pytest.approx(stats["action"]["min"])
    assert norm.action_max == pytest.approx(stats["action"]["max"])
    meta = yaml.safe_load((runs["root"] / "policy" / "final" / "train_config.yaml").read_text())
    assert meta["stage"] == "policy" and meta["init"] == runs["vlm"]["final_checkpoint"]


def test_policy_stage_standardises_the_cached_features(runs):
    """System 1 reads Q_vl and F_p standardised with the statistics of the cached training features."""
    from pathlib import Path

    from safetensors import safe_open

    policy = load_checkpoint(runs["policy"]["final_checkpoint"]).policy
    q_vl, static = [], []
    for path in sorted(Path(runs["policy"]["feature_cache"]).glob("*.safetensors")):
        with safe_open(str(path), framework="pt") as f:
            q_vl.append(f.get_tensor("q_vl").float()[:, : policy.vl_standardizer.positions])
            static.append(f.get_tensor("dynamics_static").float().flatten(0, 1))
    assert runs["policy"]["feature_statistics_frames"] == 3 * 24
    with torch.no_grad():
        z = policy.vl_standardizer(torch.cat(q_vl))[:, : policy.vl_standardizer.positions]
        z_static = policy.dynamics_standardizers[0](torch.cat(static))
    assert z.mean(0).abs().max() < 1e-3 and z_static.mean(0).abs().max() < 1e-3
    assert 0.8 < float(z.std(0, unbiased=False).median()) < 1.01
    assert 0.8 < float(z_static.std(0, unbiased=False).median()) < 1.01


def test_feature_cache_holds_system2_3_outputs_and_is_computed_once(runs, tmp_path):
    from safetensors import safe_open

    summary = runs["policy"]
    assert summary["feature_shards_computed"] == 3 and summary["feature_shards_reused"] == 0
    model = load_checkpoint(runs["vlm"]["final_checkpoint"]).eval()
    reader = LeRobotReader(runs["data"])
    shards = sorted((runs["root"] / "cache" / "features").glob("*/*.safetensors"))
    assert len(shards) == 3
    with safe_open(str(shards[0]), framework="pt") as f:
        instruction = f.metadata()["instruction"]
        episode = reader.tasks.index(instruction)  # the synthetic tasks differ per episode
        q_vl = f.get_tensor("q_vl")
        assert f.get_tensor("frame_index").tolist() == list(range(24))
        assert tuple(f.get_tensor("dynamics_static").shape) == (24, *model.dynamics.feature_shape)
    from trivla_drake.train.datasets import resize_frames

    frame = lambda cam: torch.from_numpy(resize_frames(reader.episode_video(episode, cam)[:1], 224))  # noqa: E731
    with torch.inference_mode():
        expected, _ = model.encode_vision_language_batch(
            frame("observation.images.static"), frame("observation.images.wrist"), [instruction])
    torch.testing.assert_close(q_vl[0].float(), expected[0], atol=2e-2, rtol=2e-2)  # float16 storage

    again = train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "again"), steps=2,
                              init=runs["vlm"]["final_checkpoint"], **runs["common"]))
    assert again["feature_shards_computed"] == 0 and again["feature_shards_reused"] == 3
    assert again["feature_cache"] == summary["feature_cache"]


def test_ablation_without_system2_keeps_system3_and_caches_other_features(runs, tmp_path):
    summary = train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "no_s2"), steps=2,
                                init=runs["vlm"]["final_checkpoint"], use_system2=False, **runs["common"]))
    model = load_checkpoint(summary["final_checkpoint"])
    assert model.vision_language is None and model.dynamics is not None
    vlm = load_checkpoint(runs["vlm"]["final_checkpoint"])
    assert _same(_weights(model, "dynamics."), _weights(vlm, "dynamics."))
    assert summary["feature_cache"] != runs["policy"]["feature_cache"]
    # The full model's shards hold these System 3 features: the arm reads them instead of computing.
    assert summary["feature_shards_borrowed"] == 3 and summary["feature_shards_computed"] == 0
    with pytest.raises(ValueError, match="cannot be switched back on"):
        train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "back_on"), steps=2,
                          init=summary["final_checkpoint"], **runs["common"]))


def test_every_stage_writes_its_loss_curve(runs, tmp_path):
    import shutil

    from trivla_drake.train.loss_plot import read_log

    for stage in ("video", "vlm", "policy"):
        plot = runs["root"] / stage / "loss.png"
        assert runs[stage]["loss_plot"] == str(plot)
        assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 5000
    log = shutil.copy(runs["root"] / "policy" / "log.jsonl", tmp_path / "log.jsonl")
    rows = read_log(log)
    with open(log, "a") as f:
        f.write('{"step": 99, "loss"')  # torn line of a killed run
    assert read_log(log) == rows


def test_policy_stage_sets_the_tcp_features_of_an_init_checkpoint(runs, tmp_path):
    from trivla_drake.train.model_setup import apply_ablations

    vlm = load_checkpoint(runs["vlm"]["final_checkpoint"])
    assert vlm.config.policy.tcp_features  # the default of every preset and of `train`
    plain = apply_ablations(vlm, True, True, "test", tcp_features=False)
    assert not plain.config.policy.tcp_features and plain.tcp_features is None
    assert _same(_weights(plain, "vision_language."), _weights(vlm, "vision_language."))
    # every run trains with them: one from a checkpoint without them adds them
    save_checkpoint(plain, str(tmp_path / "no_tcp"))
    summary = train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "tcp"), steps=2,
                                init=str(tmp_path / "no_tcp"), **runs["common"]))
    assert load_checkpoint(summary["final_checkpoint"]).config.policy.tcp_features


def test_policy_stage_adds_the_vl_position_embedding(runs, tmp_path):
    """policy.vl_position_embedding gives System 1 a fresh embedding of Q_vl's leading token positions
    (an --init without one), trains it, reloads it from the checkpoint, keeps System 2 as it was,
    and is refused where there is no System 1 training or no System 2."""
    init = runs["policy"]["final_checkpoint"]
    summary = train(with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "pos"), init=init,
                                           steps=3, **runs["common"]), {"policy.vl_position_embedding": True}))
    before, after = load_checkpoint(init), load_checkpoint(summary["final_checkpoint"])
    assert before.policy.vl_position is None and not before.config.policy.vl_position_embedding
    assert after.config.policy.vl_position_embedding
    fixed = after.vision_language.instruction_offset(2)
    assert after.policy.vl_position.shape == (fixed, after.config.policy.hidden_size)
    for name, value in before.vision_language.state_dict().items():
        torch.testing.assert_close(after.vision_language.state_dict()[name], value)
    # resuming from a checkpoint that has it keeps it without the flag
    again = train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "again"),
                              init=summary["final_checkpoint"], steps=1, **runs["common"]))
    continued = load_checkpoint(again["final_checkpoint"]).policy.vl_position
    assert continued.shape[0] == fixed
    assert not torch.equal(continued, after.policy.vl_position)  # trained with the rest of System 1
    with pytest.raises(ValueError, match="policy.vl_position_embedding .* setting of the policy stage; this run is the vlm stage"):
        with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "v")),
                   {"policy.vl_position_embedding": True}).resolved().validate()
    with pytest.raises(ValueError, match="policy.vl_position_embedding .*needs System 2"):
        with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "n"), use_system2=False),
                   {"policy.vl_position_embedding": True}).resolved().validate()


def test_policy_stage_adds_the_instruction_grounding_and_logs_its_loss(runs, tmp_path):
    """policy.grounding.weight gives System 1 a fresh instruction grounding (an --init without one), trains
    it on sub-goals from the dataset's tcp poses, logs both losses, keeps it when continued, and is
    refused without a weight, without tcp poses, outside the policy stage and without System 2."""
    data = write_synthetic_dataset(tmp_path / "data", episodes=3, length=24, tcp_pose=True)
    init = runs["policy"]["final_checkpoint"]
    summary = train(with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "g"), init=init, steps=3,
                                           **runs["common"]), {"policy.grounding.weight": 0.5}))
    before, after = load_checkpoint(init), load_checkpoint(summary["final_checkpoint"])
    assert before.policy.grounding is None and after.config.policy.instruction_grounding
    fresh = TriVLA(after.config).policy.grounding.state_dict()
    assert any(not torch.equal(v, fresh[k]) for k, v in after.policy.grounding.state_dict().items())
    logged = [json.loads(line) for line in open(tmp_path / "g" / "log.jsonl")]
    assert all({"flow_loss", "grounding_loss"} <= set(row) for row in logged)
    from trivla_drake.train.loss_plot import loss_components

    assert loss_components(logged) == ["flow_loss", "grounding_loss"]  # drawn in OUT/loss.png too
    assert loss_components(_rows(runs["root"] / "policy")) == []
    groups = torch.load(tmp_path / "g" / "final" / "training_state.pt", weights_only=False)["optimizer"]["param_groups"]
    assert sorted({g["lr_scale"] for g in groups}) == [1.0, 3.0]  # the grounding learns 3x faster by default
    base = next(g["lr"] for g in groups if g["lr_scale"] == 1.0)
    assert all(g["lr"] == pytest.approx(base * g["lr_scale"]) for g in groups)
    grounded = summary["final_checkpoint"]
    with pytest.raises(ValueError, match="policy.grounding.weight > 0"):
        train(TrainConfig(stage="policy", data=data, out=str(tmp_path / "w"), init=grounded, steps=1,
                          **runs["common"]))
    with pytest.raises(ValueError, match="observation.tcp_pose"):
        train(with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "t"), init=grounded,
                                     steps=1, **runs["common"]), {"policy.grounding.weight": 1.0}))
    assert not (tmp_path / "t" / "final").exists()
    with pytest.raises(ValueError, match="policy.grounding.weight .* setting of the policy stage; this run is the vlm stage"):
        with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "v")),
                   {"policy.grounding.weight": 1.0}).resolved().validate()
    with pytest.raises(ValueError, match="policy.grounding.weight .*needs System 2"):
        with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "n"), use_system2=False),
                   {"policy.grounding.weight": 1.0}).resolved().validate()
    with pytest.raises(ValueError, match="policy.grounding.lr_scale must be a finite number > 0"):
        with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "s")),
                   {"policy.grounding.lr_scale": 0.0}).resolved().validate()
    with pytest.raises(ValueError, match="policy.grounding.weight must be a finite number >= 0"):
        with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "m")),
                   {"policy.grounding.weight": -1.0}).resolved().validate()


def test_grounding_phases_bind_then_follow(runs, tmp_path, monkeypatch):
    """The two-step recipe: policy.grounding.phase bind trains only the binding (the grounding but its goal
    projection, and the Q_vl path) on the sub-goal loss alone over the approach frames; follow, from
    that checkpoint, keeps the binding and trains the rest of System 1 on both losses. Follow without a
    bound grounding, and either phase without a grounding weight, are refused naming the field."""
    data = write_synthetic_dataset(tmp_path / "data", episodes=3, length=24, tcp_pose=True)
    init = runs["policy"]["final_checkpoint"]
    bound = train(with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "bind"), init=init, steps=3,
                                         **runs["common"]), {"policy.grounding.weight": 1.0,
                                                             "policy.grounding.phase": "bind"}))
    assert bound["samples"] == 3 * 12  # the synthetic gripper first changes at frame 12 of 24
    before, after = load_checkpoint(init), load_checkpoint(bound["final_checkpoint"])
    binding = set(after.policy.binding_parameters())
    assert {"vl_proj.weight", "vl_norm.weight", "grounding.compose.weight"} <= binding
    assert not any(name.startswith("grounding.goal.") for name in binding)
    changed = {name for name, p in after.policy.named_parameters()
               if name in dict(before.policy.named_parameters()) and not torch.equal(p,
                                                                                     before.policy.get_parameter(name))}
    assert changed and changed <= binding and "vl_proj.weight" in changed
    assert torch.equal(after.policy.grounding.goal[2].weight, torch.zeros_like(after.policy.grounding.goal[2].weight))
    logged = _rows(tmp_path / "bind")
    assert all("grounding_loss" in row and "flow_loss" not in row for row in logged)
    groups = torch.load(tmp_path / "bind" / "final" / "training_state.pt",
                        weights_only=False)["optimizer"]["param_groups"]
    assert {g["lr_scale"] for g in groups} == {1.0}  # bind trains at lr

    # a bind run from a grounded checkpoint starts from a fresh grounding drawn from --seed
    from trivla_drake.train.model_setup import build_model

    again = with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "x"), init=bound["final_checkpoint"],
                                   steps=1, seed=5, **runs["common"]), {"policy.grounding.weight": 1.0,
                                                                        "policy.grounding.phase": "bind"}).resolved()
    rebound = build_model(again, None).policy.grounding.state_dict()
    assert not torch.equal(rebound["compose.weight"], after.policy.grounding.compose.weight)
    assert torch.equal(rebound["compose.weight"], build_model(again, None).policy.grounding.compose.weight)
    # policy.grounding.keep: a bind run goes on from --init's grounding (a curriculum); refused without one
    kept = build_model(with_flags(again, {"policy.grounding.keep": True}), None).policy.grounding.state_dict()
    assert all(torch.equal(kept[k], v) for k, v in after.policy.grounding.state_dict().items())
    with pytest.raises(ValueError, match="policy.grounding.keep .*which has none"):
        build_model(with_flags(dataclasses.replace(again, init=init), {"policy.grounding.keep": True}), None)
    with pytest.raises(ValueError, match="policy.grounding.reads_gripper .*follow run keeps.*bind one with"):
        build_model(with_flags(again, {"policy.grounding.phase": "follow", "policy.grounding.reads_gripper": True}),
                    None)
    # policy.grounding keep, reads_gripper and bind_held_only: only the held-block read-out (a copy of the
    # bound read-out) trains; every other weight and the feature statistics stay the bound checkpoint's (on
    # other data, whose statistics differ)
    held_data = write_synthetic_dataset(tmp_path / "held_data", episodes=3, length=24, tcp_pose=True, seed=2)
    held_only = train(with_flags(TrainConfig(stage="policy", data=held_data, out=str(tmp_path / "held"),
                                             init=bound["final_checkpoint"], steps=2, **runs["common"]), {"policy.grounding.weight": 1.0, "policy.grounding.phase": "bind", "policy.grounding.keep": True, "policy.grounding.reads_gripper": True, "policy.grounding.bind_held_only": True}))
    gripped = load_checkpoint(held_only["final_checkpoint"])
    held = set(gripped.policy.held_parameters())
    assert held and all(name.startswith("grounding.held.") for name in held)
    mine = gripped.policy.state_dict()
    for name, value in after.policy.state_dict().items():
        assert torch.equal(mine[name], value), name
    # policy.fresh_system1 in a follow run: a System 1 drawn anew from --seed but for the bound checkpoint's
    # binding and feature statistics, which it keeps (a policy learnt anew on a grounding bound elsewhere)
    fresh_follow = with_flags(again, {"policy.grounding.phase": "follow", "policy.fresh_system1": True})
    fresh_follow.validate()
    anew = build_model(fresh_follow, None).policy
    drawn = load_checkpoint(bound["final_checkpoint"])
    drawn.reset_system1(5)
    bound_weights = dict(after.policy.named_parameters())
    for name, p in anew.named_parameters():
        assert torch.equal(p, (bound_weights if name in binding else dict(drawn.policy.named_parameters()))[name]), name
    assert not all(torch.equal(p, bound_weights[name]) for name, p in anew.named_parameters() if name not in binding)
    for name, buffer in after.policy.named_buffers():
        assert torch.equal(anew.get_buffer(name), buffer), name
    with pytest.raises(ValueError, match=r"policy.fresh_system1 .*joint, or follow"):
        with_flags(again, {"policy.fresh_system1": True}).validate()  # a bind run
    keep = with_flags(again, {"policy.grounding.keep": True})
    for bad in (with_flags(keep, {"policy.grounding.phase": "follow"}), dataclasses.replace(keep, init=None)):
        with pytest.raises(ValueError, match=r"policy.grounding.keep .*bind and init"):
            bad.validate()
    other = write_synthetic_dataset(tmp_path / "other", episodes=3, length=24, tcp_pose=True, seed=1)
    follow = train(with_flags(TrainConfig(stage="policy", data=other, out=str(tmp_path / "follow"),
                                          init=bound["final_checkpoint"], steps=3, **runs["common"]), {"policy.grounding.weight": 1.0, "policy.grounding.phase": "follow"}))
    assert follow["samples"] == 3 * 24
    followed = load_checkpoint(follow["final_checkpoint"])
    for name, p in followed.policy.named_parameters():
        assert torch.equal(p, after.policy.get_parameter(name)) == (name in binding), name
    assert all({"flow_loss", "grounding_loss"} <= set(row) for row in _rows(tmp_path / "follow"))
    # the binding's feature statistics stay, though another dataset's would differ
    assert torch.equal(followed.policy.vl_standardizer.mean, after.policy.vl_standardizer.mean)
    # policy.subgoal_offset: a follow run adds the offset encoder (from zero) and trains it with the rest
    offset = train(with_flags(TrainConfig(stage="policy", data=other, out=str(tmp_path / "offset"),
                                          init=bound["final_checkpoint"], steps=2, **runs["common"]), {"policy.grounding.weight": 1.0, "policy.grounding.phase": "follow", "policy.subgoal_offset": True}))
    offset_model = load_checkpoint(offset["final_checkpoint"])
    assert offset_model.config.policy.subgoal_offset and not after.config.policy.subgoal_offset
    assert offset_model.policy.subgoal_offset.mlp[2].weight.abs().sum() > 0
    assert torch.equal(offset_model.policy.grounding.compose.weight, after.policy.grounding.compose.weight)

    with pytest.raises(ValueError, match="follow keeps the instruction grounding.*bind first"):
        train(with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "f1"), init=init, steps=1,
                                     **runs["common"]), {"policy.grounding.weight": 1.0,
                                                         "policy.grounding.phase": "follow"}))
    with pytest.raises(ValueError, match="follow keeps the instruction grounding.*--init"):
        train(with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "f2"), steps=1, **runs["common"]),
                         {"policy.grounding.weight": 1.0, "policy.grounding.phase": "follow"}))
    assert not (tmp_path / "f1").exists() or not any((tmp_path / "f1").iterdir())
    with pytest.raises(ValueError, match="policy.grounding.phase .*needs policy.grounding.weight > 0"):
        with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "w")),
                   {"policy.grounding.phase": "bind"}).resolved().validate()
    with pytest.raises(ValueError, match="policy.grounding.phase must be one of joint, bind, follow"):
        with_flags(TrainConfig(stage="policy", data=data, out=str(tmp_path / "p")), {"policy.grounding.weight": 1.0,
                                                                                     "policy.grounding.phase": "both"}).resolved().validate()


def test_vlm_stage_dense_loss_adds_the_block_head_and_logs_its_loss(runs, tmp_path):
    """vlm.dense_weight gives System 2 a fresh block head (an --init without one), trains it on the VQA
    set's label maps next to the LM loss, logs the dense loss, and is refused outside the vlm stage."""
    summary = train(with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "dense"),
                                           init=runs["video"]["final_checkpoint"], steps=3, **runs["common"]), {"vlm.vqa_scenes": 10, "vlm.vqa_questions_per_scene": 4, "vlm.vqa_eval_questions": 0, "vlm.dense_weight": 1.0}))
    model = load_checkpoint(summary["final_checkpoint"])
    assert model.config.vision_language.dense_classes == 3 and model.vision_language.block_head is not None
    logged = [json.loads(line) for line in (tmp_path / "dense" / "log.jsonl").read_text().splitlines()]
    assert len(logged) == 3 and all(row["dense_loss"] > 0 for row in logged)
    assert all(row["loss"] > row["vlm_loss"] for row in logged)
    # the policy stage keeps the head untouched (it trains System 1 only)
    with pytest.raises(ValueError, match="vlm.dense_weight .* setting of the vlm stage; this run is the policy stage"):
        with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "p")),
                   {"vlm.dense_weight": 1.0}).resolved().validate()
    with pytest.raises(ValueError, match="vlm.dense_weight must be >= 0"):
        with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "v")), {"vlm.dense_weight": -1.0}).resolved().validate()
    # vlm.dense_subcells on a model whose head has whole cells: a fresh, wider head, recorded in the config
    finer = train(with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "finer"), init=summary["final_checkpoint"],
                                         steps=1, **runs["common"]), {"vlm.vqa_scenes": 10,
                                                                      "vlm.vqa_questions_per_scene": 4, "vlm.vqa_eval_questions": 0, "vlm.dense_weight": 1.0, "vlm.dense_subcells": 2}))
    finer_model = load_checkpoint(finer["final_checkpoint"])
    assert finer_model.config.vision_language.dense_subcells == 2
    assert finer_model.vision_language.block_head.out_features == 3 * 4
    again = train(with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "again"), init=finer["final_checkpoint"],
                                         steps=1, **runs["common"]), {"vlm.vqa_scenes": 10,
                                                                      "vlm.vqa_questions_per_scene": 4, "vlm.vqa_eval_questions": 0, "vlm.dense_weight": 1.0}))  # no vlm.dense_subcells: the head is kept
    assert load_checkpoint(again["final_checkpoint"]).config.vision_language.dense_subcells == 2
    with pytest.raises(ValueError, match="vlm.dense_subcells .*needs vlm.dense_weight"):
        with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "v")), {"vlm.dense_subcells": 2}).resolved().validate()
    with pytest.raises(ValueError, match="vlm.dense_subcells must be >= 1"):
        with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "v")), {"vlm.dense_weight": 1.0,
                                                                       "vlm.dense_subcells": 0}).resolved().validate()


def test_vlm_stage_refuses_a_model_exported_without_its_upper_llm_layers(runs, tmp_path):
    """An export with drop_unused_llm_layers answers no questions: the vlm stage says so before it trains."""
    from trivla_drake.train.checkpoints import export_checkpoint

    trimmed = export_checkpoint(runs["vlm"]["final_checkpoint"], tmp_path / "trimmed", drop_unused_llm_layers=True)
    with pytest.raises(ValueError, match="drop_unused_llm_layers.*export with drop_unused_llm_layers false"):
        train(with_flags(TrainConfig(stage="vlm", out=str(tmp_path / "v"), init=str(trimmed), steps=2,
                                     **runs["common"]), {"vlm.vqa_scenes": 10, "vlm.vqa_questions_per_scene": 4,
                                                         "vlm.vqa_eval_questions": 0}))
    assert not (tmp_path / "v" / "final").exists()
    # the policy stage may start from it (Q_vl is the same)
    summary = train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "p"), init=str(trimmed),
                                steps=2, **runs["common"]))
    assert len(load_checkpoint(summary["final_checkpoint"]).vision_language.llm.model.layers) == 1


def test_a_fresh_vlm_run_builds_every_llm_layer_of_a_preset_that_drops_them(tmp_path):
    """The paper preset builds its LLM only up to the read-out layer (Q_vl needs no more); a fresh
    vlm run reads its answers from the last layer, so it builds them all. Configs only: no weights."""
    from trivla_drake.train.model_setup import fresh_model_config

    assert make_config("paper").vision_language.drop_unused_llm_layers
    for stage, drops in (("vlm", False), ("policy", True)):
        config = TrainConfig(stage=stage, preset="paper", data=str(tmp_path), out=str(tmp_path / stage)).resolved()
        assert fresh_model_config(config).vision_language.drop_unused_llm_layers is drops, stage


def test_arm_without_system2_computes_system3_features_equal_to_the_ones_it_borrows(runs, tmp_path):
    from trivla_drake.train.datasets import PolicyFeatureDataset
    from trivla_drake.train.distributed import DistEnv
    from trivla_drake.train.features import dynamics_feature_key, ensure_feature_cache, feature_cache_key
    from trivla_drake.train.model_setup import apply_ablations

    full = load_checkpoint(runs["vlm"]["final_checkpoint"]).eval()
    arm = apply_ablations(full, False, True, "test")
    reader = LeRobotReader(runs["data"])
    config = TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "o"), **runs["common"])
    assert dynamics_feature_key(arm, config) == dynamics_feature_key(full, config)
    assert feature_cache_key(arm, config) != feature_cache_key(full, config)
    lent, summary = ensure_feature_cache(arm, reader, [0, 1, 2], config, DistEnv(), progress=False)
    assert summary["feature_shards_borrowed"] == 3 and summary["feature_shards_computed"] == 0
    assert all(path.parent.name == feature_cache_key(full, config) for path in lent.values())
    # Computed afresh in a cache of its own, the arm's System 3 features equal the borrowed ones.
    alone = dataclasses.replace(config, cache_dir=str(tmp_path / "own_cache"))
    own, summary = ensure_feature_cache(arm, reader, [0, 1, 2], alone, DistEnv(), progress=False)
    assert summary["feature_shards_borrowed"] == 0 and summary["feature_shards_computed"] == 3
    kwargs = dict(feature_stride=1, action_horizon=arm.config.policy.action_horizon, use_system2=False,
                  use_system3=True)
    a, b = PolicyFeatureDataset(reader, [0, 1, 2], lent, **kwargs), PolicyFeatureDataset(reader, [0, 1, 2], own,
                                                                                         **kwargs)
    for i in (0, len(a) - 1):
        assert "q_vl" not in a[i]
        torch.testing.assert_close(a[i]["dynamics_wrist"], b[i]["dynamics_wrist"])
        torch.testing.assert_close(a[i]["dynamics_static"], b[i]["dynamics_static"])
    assert summary["feature_cache_lenders"] == [] and summary["feature_cache_bytes_per_episode"] > 0
    # Another System 3 (weights or config), or another stride, borrows nothing.
    other = apply_ablations(load_checkpoint(runs["video"]["final_checkpoint"]).eval(), False, True, "test")
    with torch.no_grad():
        next(other.dynamics.parameters()).add_(1e-3)
    retuned = apply_ablations(full, False, True, "test")
    retuned.config = dataclasses.replace(
        retuned.config, dynamics=dataclasses.replace(retuned.config.dynamics,
                                                     sigma_max=retuned.config.dynamics.sigma_max / 2))
    for model, setting in ((other, config), (retuned, config), (arm, with_flags(config, {"features.stride": 2}))):
        assert dynamics_feature_key(model, setting) != dynamics_feature_key(full, config)
        setting = dataclasses.replace(setting, cache_dir=str(tmp_path / "lenders"))
        lender = tmp_path / "lenders" / "features"
        lender.mkdir(parents=True, exist_ok=True)
        if not (lender / feature_cache_key(full, config)).exists():
            (lender / feature_cache_key(full, config)).symlink_to(Path(lent[0]).parent)
        _, summary = ensure_feature_cache(model, reader, [0], setting, DistEnv(), progress=False)
        assert summary["feature_shards_borrowed"] == 0 and summary["feature_shards_computed"] == 1


def test_a_retrained_system2_copies_system3_features_from_a_lender(runs, tmp_path):
    """A model whose System 2 differs but whose System 3 is the same computes Q_vl only: its own
    shards get the lender's System 3 tensors, and equal the shards it computes alone."""
    from safetensors.torch import load_file

    from trivla_drake.train.distributed import DistEnv
    from trivla_drake.train.features import dynamics_feature_key, ensure_feature_cache, feature_cache_key

    reader = LeRobotReader(runs["data"])
    config = TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "o"), **runs["common"])
    config = dataclasses.replace(config, cache_dir=str(tmp_path / "cache"))  # the lender is deleted below
    full = load_checkpoint(runs["vlm"]["final_checkpoint"]).eval()
    lender, _ = ensure_feature_cache(full, reader, [0, 1, 2], config, DistEnv(), progress=False)
    retrained = load_checkpoint(runs["vlm"]["final_checkpoint"]).eval()
    with torch.no_grad():
        next(retrained.vision_language.vision_encoder.parameters()).add_(1e-2)
    assert dynamics_feature_key(retrained, config) == dynamics_feature_key(full, config)
    assert feature_cache_key(retrained, config) != feature_cache_key(full, config)
    shards, summary = ensure_feature_cache(retrained, reader, [0, 1, 2], config, DistEnv(), progress=False)
    assert summary["feature_shards_dynamics_copied"] == 3 and summary["feature_shards_borrowed"] == 0
    assert summary["feature_cache_lenders"] == [str(lender[0].parent)]
    assert all(path.parent.name == feature_cache_key(retrained, config) for path in shards.values())
    alone = dataclasses.replace(config, cache_dir=str(tmp_path / "own_cache"))
    own, summary = ensure_feature_cache(retrained, reader, [0, 1, 2], alone, DistEnv(), progress=False)
    assert summary["feature_shards_dynamics_copied"] == 0 and summary["feature_cache_lenders"] == []
    for episode in (0, 2):
        copied, computed, lent = (load_file(str(s[episode])) for s in (shards, own, lender))
        assert copied.keys() == computed.keys()
        for key in copied:
            torch.testing.assert_close(copied[key], computed[key])
        torch.testing.assert_close(copied["dynamics_static"], lent["dynamics_static"])
        assert not torch.equal(copied["q_vl"], lent["q_vl"])
    # written, the shards stand alone: the lender's removal leaves them valid, and they are reused
    shutil.rmtree(lender[0].parent)
    _, summary = ensure_feature_cache(retrained, reader, [0, 1, 2], config, DistEnv(), progress=False)
    assert summary["feature_shards_reused"] == 3 and summary["feature_shards_computed"] == 0


def test_system2_from_swaps_in_another_system2_and_keeps_systems_1_and_3(runs, tmp_path):
    """policy.system2_from: the --init model with the donor's System 2 (trimmed as --init's is); System 3's
    features are copied from --init's cache, Q_vl computed with the new System 2."""
    summary = train(with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "swap"), steps=2,
                                           init=runs["policy"]["final_checkpoint"], **runs["common"]), {"policy.system2_from": runs["video"]["final_checkpoint"]}))
    model = load_checkpoint(summary["final_checkpoint"])
    donor, init = load_checkpoint(runs["video"]["final_checkpoint"]), load_checkpoint(runs["policy"]["final_checkpoint"])
    assert _same(_weights(model, "vision_language."), _weights(donor, "vision_language."))
    assert _same(_weights(model, "dynamics."), _weights(init, "dynamics."))
    assert not _same(_weights(model, "vision_language."), _weights(init, "vision_language."))
    assert summary["feature_shards_dynamics_copied"] == 3 and summary["feature_shards_computed"] == 3
    assert summary["feature_cache"] != runs["policy"]["feature_cache"]
    with pytest.raises(ValueError, match="policy.system2_from .*needs init and System 2"):
        with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "v")),
                   {"policy.system2_from": runs["video"]["final_checkpoint"]}).resolved().validate()
    with pytest.raises(ValueError, match="system2_from.*follow run"):
        with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "v"),
                               init=runs["policy"]["final_checkpoint"]), {"policy.grounding.weight": 1.0,
                                                                          "policy.grounding.phase": "follow", "policy.system2_from": runs["video"]["final_checkpoint"]}).resolved().validate()
    no_s2 = train(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "no_s2"), steps=1,
                              init=runs["policy"]["final_checkpoint"], use_system2=False, **runs["common"]))
    with pytest.raises(ValueError, match="policy.system2_from .*needs one in both models"):
        train(with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "bad"), steps=1,
                                     init=runs["policy"]["final_checkpoint"], **runs["common"]), {"policy.system2_from": no_s2["final_checkpoint"]}))
    assert not (tmp_path / "bad" / "final").exists()
    with pytest.raises(FileNotFoundError, match="policy.system2_from .*not a checkpoint directory"):
        train(with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "missing"), steps=1,
                                     init=runs["policy"]["final_checkpoint"], **runs["common"]), {"policy.system2_from": str(tmp_path / "nowhere")}))


def test_fresh_system1_trains_a_new_system1_on_the_init_models_systems_2_and_3(runs, tmp_path):
    """policy.fresh_system1: System 1 drawn anew from --seed (not --init's), Systems 2 and 3 kept as --init has
    them; the same seed draws the same System 1."""
    init = load_checkpoint(runs["policy"]["final_checkpoint"])
    common = {**runs["common"], "lr": 1e-12, "optimizer": OptimizerConfig(warmup_steps=1)}
    summary = train(with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "fresh"), steps=1,
                                           seed=5, init=runs["policy"]["final_checkpoint"], **common), {"policy.fresh_system1": True}))
    model = load_checkpoint(summary["final_checkpoint"])
    assert _same(_weights(model, "vision_language."), _weights(init, "vision_language."))
    assert _same(_weights(model, "dynamics."), _weights(init, "dynamics."))
    expected = load_checkpoint(runs["policy"]["final_checkpoint"])
    expected.reset_system1(5)
    trained, drawn, old = (dict(m.policy.named_parameters()) for m in (model, expected, init))
    assert trained.keys() == drawn.keys() == old.keys()
    assert all(torch.allclose(trained[k], drawn[k], atol=1e-6) for k in trained)  # one step at lr 1e-12
    assert not all(torch.allclose(trained[k], old[k], atol=1e-3) for k in trained)
    other = load_checkpoint(runs["policy"]["final_checkpoint"])
    other.reset_system1(6)
    assert not _same(_weights(other, "policy."), _weights(expected, "policy."))
    with pytest.raises(ValueError, match="policy.fresh_system1 .*needs init and policy.grounding.phase joint"):
        with_flags(TrainConfig(stage="policy", data=runs["data"], out=str(tmp_path / "v")),
                   {"policy.fresh_system1": True}).resolved().validate()


def _narrowed_copy(data, out):
    """A copy of `data` whose meta/stats.json gives every action half its range (the frames unchanged)."""
    shutil.copytree(data, out)
    stats_path = Path(out) / "meta" / "stats.json"
    stats = json.loads(stats_path.read_text())
    stats["action"]["min"] = [0.5 * v for v in stats["action"]["min"]]
    stats["action"]["max"] = [0.5 * v for v in stats["action"]["max"]]
    stats_path.write_text(json.dumps(stats))
    return str(out)


def test_a_refit_on_narrower_actions_says_what_narrowed(runs, tmp_path, capsys):
    """A follow on a dataset with narrower action ranges: the statistics are refitted to it and a note names the
    narrowed dimensions."""
    init = load_checkpoint(runs["policy"]["final_checkpoint"]).normalization
    narrow = _narrowed_copy(runs["data"], tmp_path / "narrow")
    refit = train(TrainConfig(stage="policy", data=narrow, out=str(tmp_path / "refit"), steps=1,
                              init=runs["policy"]["final_checkpoint"], **runs["common"]))
    note = capsys.readouterr().err
    assert "action ranges are narrower" in note
    refitted = load_checkpoint(refit["final_checkpoint"]).normalization
    assert refitted.action_max == pytest.approx([0.5 * v for v in init.action_max])


def test_narrowed_action_ranges_names_only_the_dimensions_that_shrank():
    from trivla_drake.nn.normalization import NormalizationStats
    from trivla_drake.train.datasets import narrowed_action_ranges

    old = NormalizationStats([0.0], [1.0], [-1.0, -1.0, -1.0], [1.0, 1.0, 1.0])
    new = NormalizationStats([0.0], [1.0], [-1.0, -0.9, -2.0], [1.0, 0.3, 2.0])
    assert narrowed_action_ranges(old, new, ("x", "z", "w")) == ["z [-1, 1] -> [-0.9, 0.3]"]
    assert narrowed_action_ranges(old, old, ("x", "z", "w")) == []
