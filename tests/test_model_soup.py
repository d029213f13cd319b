"""`trivla-drake soup`: the uniform average of System 1s trained from one start; refused, with the reason
named and an existing output intact, when the models do not share their config, buffers or frozen systems."""

import copy
import json

import numpy as np
import pytest
import torch

from trivla_drake.cli import main
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint
from trivla_drake.train.model_soup import soup_state_dict


def _nudged(model, prefix, seed, scale=0.05):
    """A copy of `model` whose parameters under `prefix` are moved by seeded noise (a 'follow run')."""
    other = copy.deepcopy(model)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in other.named_parameters():
            if name.startswith(prefix):
                parameter.add_(scale * torch.randn(parameter.shape, generator=generator))
    return other


@pytest.fixture(scope="module")
def two_follows(saved, tmp_path_factory):
    """(models, folders): the `saved` tiny model with its System 1 moved two ways, saved in float32."""
    model, _ = saved
    root = tmp_path_factory.mktemp("follows")
    models, folders = [], []
    for seed in (1, 2):
        follow = _nudged(model, "policy.", seed)
        folder = root / f"follow{seed}"
        save_checkpoint(follow, str(folder))
        models.append(follow)
        folders.append(str(folder))
    return models, folders


def test_the_soup_is_the_mean_of_system_1_and_keeps_the_frozen_systems(two_follows, saved, tmp_path, capsys):
    (a, b), folders = two_follows
    out = tmp_path / "soup"
    assert main(["soup", *folders, "--out", str(out), "--set", "dtype=float32"]) == 0
    assert "the average of 2 models" in capsys.readouterr().out
    soup = load_checkpoint(str(out))
    parameters_a, parameters_b = dict(a.named_parameters()), dict(b.named_parameters())
    moved = 0
    for name, parameter in soup.named_parameters():
        expected = (parameters_a[name] + parameters_b[name]) / 2
        torch.testing.assert_close(parameter, expected, rtol=0, atol=1e-6)
        moved += int(not torch.equal(parameters_a[name], parameters_b[name]))
    assert moved > 10  # System 1 really differed, so the test compares averages, not copies
    for name, buffer in soup.named_buffers():
        assert torch.equal(buffer, dict(a.named_buffers())[name]), name
    assert soup.normalization == a.normalization
    obs = example_observation()
    actions = soup.eval().predict_action_chunk(obs, seed=3)
    assert not np.allclose(actions, a.eval().predict_action_chunk(obs, seed=3))


def test_a_soup_of_one_model_twice_is_that_model(saved, tmp_path):
    model, folder = saved
    out = tmp_path / "same"
    assert main(["soup", folder, folder, "--out", str(out), "--set", "dtype=float32"]) == 0
    obs = example_observation()
    np.testing.assert_array_equal(load_checkpoint(str(out)).eval().predict_action_chunk(obs, seed=4),
                                  model.predict_action_chunk(obs, seed=4))


def test_an_export_in_float16_soups_with_the_float32_runs_followed_from_it(two_follows, tmp_path):
    """The shipped model is an export (float16); a follow of it saves float32. The storage dtype is not the model."""
    (a, _), _ = two_follows
    exported = tmp_path / "exported"
    save_checkpoint(a, str(exported), weights_dtype="float16")
    assert json.loads((exported / "config.json").read_text())["weights_dtype"] == "float16"
    start = load_checkpoint(str(exported))
    follow = _nudged(start, "policy.", 5)  # its frozen systems are the export's, as loaded
    save_checkpoint(follow, str(tmp_path / "follow"))
    assert json.loads((tmp_path / "follow" / "config.json").read_text())["weights_dtype"] == "float32"
    out = tmp_path / "soup"
    assert main(["soup", str(exported), str(tmp_path / "follow"), "--out", str(out), "--set", "dtype=float32"]) == 0
    started, followed = dict(start.named_parameters()), dict(follow.named_parameters())
    for name, parameter in load_checkpoint(str(out)).named_parameters():
        torch.testing.assert_close(parameter, (started[name] + followed[name]) / 2, rtol=0, atol=1e-6)


def test_a_soup_refuses_models_whose_frozen_system_2_differs(saved, two_follows, tmp_path, capsys):
    model, _ = saved
    _, folders = two_follows
    other = tmp_path / "other_system2"
    save_checkpoint(_nudged(model, "vision_language.", 7), str(other))
    target = tmp_path / "soup"
    assert main(["soup", folders[0], folders[1], "--out", str(target)]) == 0
    before = (target / "model.safetensors").read_bytes()
    assert main(["soup", folders[0], str(other), "--out", str(target)]) == 2
    err = capsys.readouterr().err
    assert "vision_language." in err and "frozen System 2 or 3" in err
    assert (target / "model.safetensors").read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]


def test_a_soup_refuses_differing_buffers(saved):
    model, _ = saved
    other = copy.deepcopy(model)
    stored = other.state_dict()  # persistent buffers only (e.g. the feature standardizers' statistics)
    name, buffer = next((n, b) for n, b in other.named_buffers() if n in stored and b.is_floating_point())
    with torch.no_grad():
        buffer.add_(1.0)
    with pytest.raises(ValueError, match=rf"{name} \(a buffer\) differs between first and second"):
        soup_state_dict([model, other], ["first", "second"])


def test_a_soup_names_the_config_fields_that_differ(two_follows, tmp_path, capsys):
    _, folders = two_follows
    changed = tmp_path / "changed"
    changed.mkdir()
    config = json.loads(open(f"{folders[1]}/config.json").read())
    config["preset"] = "cpu"
    (changed / "config.json").write_text(json.dumps(config))
    (changed / "model.safetensors").write_bytes(open(f"{folders[1]}/model.safetensors", "rb").read())
    assert main(["soup", folders[0], str(changed), "--out", str(tmp_path / "x")]) == 2
    assert "differs from" in (err := capsys.readouterr().err) and "preset" in err
    assert not (tmp_path / "x").exists()


def test_a_soup_needs_two_checkpoints_and_real_folders(two_follows, tmp_path, capsys):
    _, folders = two_follows
    assert main(["soup", folders[0], "--out", str(tmp_path / "x")]) == 2
    assert "at least 2 checkpoints" in capsys.readouterr().err
    assert main(["soup", folders[0], str(tmp_path / "missing"), "--out", str(tmp_path / "x")]) == 2
    assert "not a checkpoint folder" in capsys.readouterr().err
    with pytest.raises(ValueError, match="at least 2 models"):
        soup_state_dict([torch.nn.Linear(2, 2)])
