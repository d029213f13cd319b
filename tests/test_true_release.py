"""results/subgoal_diagnostics/true_release.py: the oracle's release position as System 1's sub-goal while carrying."""

import dataclasses
import json

import numpy as np
import torch

from trivla_drake.action import GRIPPER_OPEN
from trivla_drake.nn.checkpoint import save_checkpoint
from trivla_drake.nn.config import make_config
from trivla_drake.nn.panda_tcp import normalize_position
from trivla_drake.nn.trivla import TriVLA
from trivla_drake.tasks.scene import Layout, scene_from_spec
from trivla_drake.tasks.suite import get_task, sample_task_instance


def _grounded_checkpoint(folder):
    config = make_config("tiny", init_seed=4)
    config = dataclasses.replace(config, policy=dataclasses.replace(
        config.policy, tcp_features=True, instruction_grounding=True, subgoal_offset=True))
    save_checkpoint(TriVLA(config).eval(), str(folder))
    return str(folder)


def test_the_release_replaces_the_subgoal_only_while_the_named_block_is_held(tmp_path, results_script, monkeypatch):
    script = results_script("subgoal_diagnostics/true_release.py")
    policy = script.TrueRelease.from_checkpoint(_grounded_checkpoint(tmp_path / "model"))
    from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy

    monkeypatch.setattr(TriVLAHarnessPolicy, "act", lambda self, obs: np.zeros((1, 7)))  # no model run
    layout = Layout.default()
    spec, instance = sample_task_instance(get_task("stack_block"), np.random.default_rng(3), layout)
    scene = scene_from_spec(spec, layout)
    policy.reset(instance.instruction, 0)
    policy.act({"privileged": {"scene": scene, "task": instance}})
    plan = get_task("stack_block").plan(instance.params, scene)
    release = [wp for wp in plan if wp.gripper == GRIPPER_OPEN][-1].pose[:3, 3]
    np.testing.assert_allclose(policy.release, release)
    # The release lies over the destination block, not where the block to pick up is.
    assert np.linalg.norm(release[:2] - scene.block_position(instance.params[1])[:2]) < 0.01
    assert policy.true is None and policy.overrides == 0  # not held: the grounding's own sub-goal

    monkeypatch.setattr(type(scene), "is_held", lambda self, color: color == instance.params[0])
    policy.act({"privileged": {"scene": scene, "task": instance}})
    np.testing.assert_allclose(policy.true, release)
    assert policy.overrides == 1

    system1 = policy.model.policy
    vl = torch.randn(1, system1.vl_fixed_positions + 5, system1.vl_proj.out_features)  # tokens at DiT width
    mask = torch.ones(vl.shape[:2], dtype=torch.bool)
    tcp = torch.zeros(1, 9)
    _, carried = system1._ground(vl, mask, tcp)
    expected = normalize_position(torch.as_tensor(release, dtype=carried.dtype))
    torch.testing.assert_close(carried[0, :3], expected)
    policy.true = None
    _, own = system1._ground(vl, mask, tcp)
    assert not torch.allclose(own[0, :3], expected)
    policy.reset("another", 1)  # a new episode draws its release again
    assert policy.release is None


def test_the_script_evaluates_place_and_stack_on_each_seed(tmp_path, results_script, monkeypatch, capsys):
    from trivla_drake.eval import evaluate as ev

    script = results_script("subgoal_diagnostics/true_release.py")
    configs = []

    def fake_evaluate(config, progress=True):  # the episodes themselves are the evaluation's (tests/test_evaluate*)
        configs.append(config)
        assert ev._policy(*config.policy_key()).privileged  # the plan needs the scene
        return {"tasks": {t: {"successes": 1} for t in config.tasks}}

    monkeypatch.setattr(ev, "evaluate", fake_evaluate)
    monkeypatch.setattr("sys.argv", ["true_release.py", "1000,1003", str(tmp_path / "out"),
                                     _grounded_checkpoint(tmp_path / "model")])
    try:
        script.main()
    finally:
        ev._POLICY_CACHE.pop(ev.EvalConfig(policy="trivla").policy_key(), None)
    assert [(c.seed, c.episodes, c.workers, c.prelude) for c in configs] == [(1000, 2, 1, 0), (1003, 2, 1, 0)]
    assert configs[0].tasks == ["place_in_bowl", "stack_block"]
    assert json.loads((tmp_path / "out" / "release_seed1003.json").read_text())["tasks"]["stack_block"]["successes"] == 1
    assert "1003" in capsys.readouterr().out
