"""How the harness plays TriVLA's action chunks (`inference.execute_steps`, `inference.ensemble_decay`): replanning every
K steps plays the first K rows of each chunk, ACT's temporal ensembling averages the chunks that cover a
step, and bad settings are named."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from trivla_drake.eval.evaluate import EvalConfig
from trivla_drake.eval.inference_config import InferenceConfig
from trivla_drake.eval.policies import load_policy
from trivla_drake.eval.trivla_harness_policy import TriVLAHarnessPolicy
from trivla_drake.nn import TriVLA, make_config, save_checkpoint
from trivla_drake.nn.benchmark import example_observation

HORIZON = 10


class CountingModel:
    """Stands in for TriVLA: call n (from 1) returns the chunk whose row k is 100 n + k in every entry."""

    def __init__(self):
        self.config = SimpleNamespace(policy=SimpleNamespace(action_horizon=HORIZON))
        self.calls = 0
        self.seeds = []

    def eval(self):
        return self

    def predict_action_chunk(self, observation, seed=None):
        self.calls += 1
        self.seeds.append(seed)
        return np.tile((100.0 * self.calls + np.arange(HORIZON))[:, None], (1, 7)).astype(np.float32)


def _observation():
    return {"static_rgb": None, "wrist_rgb": None, "state": None}


def test_the_default_plays_whole_chunks_and_execute_steps_the_first_rows():
    whole = TriVLAHarnessPolicy(CountingModel())
    whole.reset("lift the red block", 3)
    np.testing.assert_array_equal(whole.act(_observation())[:, 0], 100 + np.arange(10))
    every_three = TriVLAHarnessPolicy(CountingModel(), execute_steps=3)
    every_three.reset("lift the red block", 3)
    np.testing.assert_array_equal(every_three.act(_observation())[:, 0], [100, 101, 102])
    np.testing.assert_array_equal(every_three.act(_observation())[:, 0], [200, 201, 202])
    assert every_three.model.seeds == [3 * 100_003 + 1, 3 * 100_003 + 2]  # fresh noise per chunk


def test_ensembling_averages_every_chunk_that_covers_a_step():
    decay = 0.5
    policy = TriVLAHarnessPolicy(CountingModel(), execute_steps=4, ensemble_decay=decay)
    policy.reset("open the drawer", 0)
    first = policy.act(_observation())[:, 0]
    np.testing.assert_array_equal(first, [100, 101, 102, 103])  # one chunk covers steps 0-3
    second = policy.act(_observation())[:, 0]
    # Steps 4-7: chunk 1 (observed at step 0) holds rows 4-7, chunk 2 (step 4) rows 0-3.
    w_old, w_new = 1.0, math.exp(-decay)
    expected = [(w_old * (104 + k) + w_new * (200 + k)) / (w_old + w_new) for k in range(4)]
    np.testing.assert_allclose(second, expected, rtol=1e-6)
    third = policy.act(_observation())[:, 0]
    # Steps 8-11: chunk 1 covers 8 and 9 only; chunks 2 and 3 cover all four.
    weights3 = np.exp(-decay * np.arange(3))
    step8 = np.average([108, 204, 300], weights=weights3)
    step10 = np.average([206, 302], weights=weights3[:2])
    np.testing.assert_allclose(third[[0, 2]], [step8, step10], rtol=1e-6)
    policy.reset("open the drawer", 1)  # a new episode forgets the old chunks
    np.testing.assert_array_equal(policy.act(_observation())[:, 0], [400, 401, 402, 403])


def test_decay_zero_is_a_plain_mean_and_a_whole_chunk_leaves_nothing_to_ensemble():
    mean = TriVLAHarnessPolicy(CountingModel(), execute_steps=5, ensemble_decay=0.0)
    mean.reset("x", 0)
    mean.act(_observation())
    np.testing.assert_allclose(mean.act(_observation())[:, 0], [(105 + k + 200 + k) / 2 for k in range(5)])
    whole = TriVLAHarnessPolicy(CountingModel(), ensemble_decay=0.1)
    whole.reset("x", 0)
    whole.act(_observation())
    np.testing.assert_array_equal(whole.act(_observation())[:, 0], 200 + np.arange(10))


def test_a_real_checkpoint_replans_with_the_same_chunks(tmp_path):
    model = TriVLA(make_config("tiny"), load_pretrained=False).eval()
    save_checkpoint(model, str(tmp_path / "ckpt"))
    policy = load_policy(str(tmp_path / "ckpt"), execute_steps=2)  # what each evaluate worker runs
    observation = example_observation(model.image_size, model.config.policy.state_dim)
    policy.reset(observation["instruction"], 5)
    rows = policy.act(observation)
    assert rows.shape == (2, 7)
    np.testing.assert_array_equal(rows, model.predict_action_chunk(observation, seed=5 * 100_003 + 1)[:2])


@pytest.mark.parametrize("bad", [0, 11, 2.5, True])
def test_bad_execute_steps_are_named(bad):
    with pytest.raises(ValueError, match="execute_steps"):
        TriVLAHarnessPolicy(CountingModel(), execute_steps=bad)
    if bad != 11:  # the chunk length is the checkpoint's, checked when it loads
        with pytest.raises(ValueError, match="inference.execute_steps"):
            EvalConfig(policy="trivla", tasks=["lift_block"], episodes=1,
                       inference=InferenceConfig(execute_steps=bad)).validate()


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf, "fast"])
def test_bad_ensemble_decays_are_named(bad):
    with pytest.raises(ValueError, match="ensemble_decay"):
        TriVLAHarnessPolicy(CountingModel(), execute_steps=5, ensemble_decay=bad)
    with pytest.raises(ValueError, match="inference.ensemble_decay"):
        EvalConfig(policy="trivla", tasks=["lift_block"], episodes=1,
                   inference=InferenceConfig(ensemble_decay=bad)).validate()


def test_chunk_settings_with_a_policy_that_has_no_chunks_are_errors_at_the_cli(capsys):
    from trivla_drake.cli import main

    with pytest.raises(ValueError, match="inference.execute_steps applies to TriVLA checkpoints only"):
        load_policy("oracle", execute_steps=5)
    assert main(["evaluate", "--policy", "random", "--tasks", "lift_block", "--episodes", "1",
                 "--set", "inference.ensemble_decay=0.1", "--no-progress"]) == 2
    assert "inference.ensemble_decay" in capsys.readouterr().err
    assert main(["evaluate", "--policy", "trivla", "--tasks", "lift_block", "--episodes", "1",
                 "--set", "inference.execute_steps=0", "--no-progress"]) == 2
    assert "inference.execute_steps" in capsys.readouterr().err


def test_demo_and_tables_take_the_same_settings_and_name_bad_ones(tmp_path, capsys):
    from trivla_drake.cli import main
    from trivla_drake.eval.paper_tables import TablesConfig, _stored, stored_evaluation_path

    assert main(["demo", "--policy", "oracle", "--set", "inference.execute_steps=5"]) == 2
    assert "inference.* and --latency go with --policy trivla" in capsys.readouterr().err
    save_checkpoint(TriVLA(make_config("tiny"), load_pretrained=False), str(tmp_path / "ckpt"))
    assert main(["demo", "--checkpoint", str(tmp_path / "ckpt"), "--set", "inference.execute_steps=11"]) == 2
    assert "inference.execute_steps must be an integer from 1 to the chunk length 10" in capsys.readouterr().err
    assert main(["demo", "--checkpoint", str(tmp_path / "ckpt"), "--set", "inference.ensemble_decay=-1"]) == 2
    assert "inference.ensemble_decay" in capsys.readouterr().err
    # A short Drake run records its settings, and every tick plays an action.
    assert main(["demo", "--checkpoint", str(tmp_path / "ckpt"), "--task", "turn_on_light", "--set", "max_seconds=0.5",
                 "--set", "inference.execute_steps=5", "--set", "inference.ensemble_decay=0.1", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert (report["execute_steps"], report["ensemble_decay"]) == (5, 0.1)
    assert report["control_hz"] == pytest.approx(36.0, rel=0.03)
    full = {"full": str(tmp_path / "ckpt")}
    with pytest.raises(ValueError, match="inference.execute_steps"):
        TablesConfig(checkpoints=full, inference=InferenceConfig(execute_steps=0)).validate()
    with pytest.raises(ValueError, match="inference.ensemble_decay"):
        TablesConfig(checkpoints=full, inference=InferenceConfig(ensemble_decay=math.nan)).validate()

    # `tables` stores each setting's evaluations apart, and the default's under its old key.
    settings = {"kind": "evaluate", "seed": 0}
    stored = str(tmp_path / "stored")
    default = TablesConfig(results_dir=stored)
    replanning = TablesConfig(results_dir=stored, inference=InferenceConfig(execute_steps=5))
    ensembled = TablesConfig(results_dir=stored, inference=InferenceConfig(execute_steps=5, ensemble_decay=0.1))
    for config, value in ((default, "default"), (replanning, "k5"), (ensembled, "k5e"), (default, "again")):
        _stored(config, str(tmp_path / "ckpt"), settings, lambda value=value: {"value": value})
    records = [json.loads(p.read_text())["settings"] for p in (tmp_path / "stored").glob("*.json")]
    assert sorted(map(str, records)) == sorted(map(str, [settings, {**settings, "execute_steps": 5},
                                                         {**settings, "execute_steps": 5, "ensemble_decay": 0.1}]))
    assert _stored(default, str(tmp_path / "ckpt"), settings, lambda: {"value": "recomputed"}) == {"value": "default"}
    assert _stored(ensembled, str(tmp_path / "ckpt"), settings, lambda: {"value": "recomputed"}) == {"value": "k5e"}
    # Each record lies where stored_evaluation_path names it for its own settings (what research scripts look up).
    for path in (tmp_path / "stored").glob("*.json"):
        assert stored_evaluation_path(stored, str(tmp_path / "ckpt"), json.loads(path.read_text())["settings"]) == path
