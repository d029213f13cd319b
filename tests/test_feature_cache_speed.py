"""The feature cache's faster path computes exactly what the plain one does: System 3 with its instruction's work
done once (nn/shared_instruction.py), the episodes computed by worker threads (train/features.py), and the
throughput figures of train/throughput.py on a tiny model and dataset."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from trivla_drake.data.lerobot_reader import LeRobotReader
from trivla_drake.nn import TriVLA, make_config, save_checkpoint
from trivla_drake.nn.shared_instruction import SharedContextAttnProcessor, shared_instruction
from trivla_drake.train import features
from trivla_drake.train.config import TrainConfig
from trivla_drake.train.datasets import resize_frames
from trivla_drake.train.distributed import DistEnv
from trivla_drake.train.synthetic import write_synthetic_dataset


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("cache_speed")
    data = write_synthetic_dataset(root / "data", episodes=3, length=14)
    model = TriVLA(make_config("tiny", init_seed=0), load_pretrained=False).eval()
    return {"root": root, "data": data, "model": model}


def _frames(model: TriVLA, count: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.integers(0, 256, (count, model.image_size, model.image_size, 3), dtype=np.uint8))


@pytest.mark.parametrize("noise", ["fixed", "random"])
def test_shared_instruction_gives_bit_identical_system3_features(tiny, noise):
    model = tiny["model"]
    dynamics_config = dataclasses.replace(model.dynamics.config, feature_noise=noise)
    original_config, model.dynamics.config = model.dynamics.config, dynamics_config
    try:
        static, wrist = _frames(model, 3, 0), _frames(model, 3, 1)
        texts = ["lift the red block"] * 3

        def run():
            with torch.inference_mode():
                return model.encode_dynamics_batch(static, wrist, texts, generator=torch.Generator().manual_seed(7))

        with torch.enable_grad():  # with gradients encode_dynamics_batch takes the plain path
            plain = [f.detach() for f in model.encode_dynamics_batch(static, wrist, texts,
                                                                     generator=torch.Generator().manual_seed(7))]
        attentions = [m for m in model.dynamics.unet.modules() if hasattr(m, "processor")]
        before = [m.processor for m in attentions]
        with shared_instruction(model.dynamics) as processors:
            shared = run()
        assert processors and sum(p.shared_calls for p in processors) > 0  # the shared path ran
        assert all(torch.equal(a, b) for a, b in zip(plain, shared))
        assert [m.processor for m in attentions] == before  # restored
    finally:
        model.dynamics.config = original_config


def test_a_policy_call_shares_its_instruction_by_itself(tiny, monkeypatch):
    """Without gradients and with one instruction, TriVLA.encode_dynamics_batch enters shared_instruction itself (a
    policy call, the feature cache); a nested entry reuses the processors in place."""
    import trivla_drake.nn.trivla as trivla_module

    model = tiny["model"]
    entered = []

    def spy(dynamics):
        context = shared_instruction(dynamics)
        entered.append(context)
        return context

    monkeypatch.setattr(trivla_module, "shared_instruction", spy)
    static, wrist = _frames(model, 2, 6), _frames(model, 2, 7)
    with torch.inference_mode():
        model.encode_dynamics_batch(static, wrist, ["open the drawer"] * 2)
        model.encode_dynamics_batch(static, wrist, ["open the drawer", "close the drawer"])
        with shared_instruction(model.dynamics) as outer:
            model.encode_dynamics_batch(static, wrist, ["open the drawer"] * 2)
    assert len(entered) == 2 and sum(p.shared_calls for p in outer) > 0  # the nested call used the outer processors


def test_mixed_instructions_take_the_plain_path(tiny):
    model = tiny["model"]
    static, wrist = _frames(model, 2, 2), _frames(model, 2, 3)
    texts = ["lift the red block", "open the drawer"]
    with torch.inference_mode():
        plain = model.encode_dynamics_batch(static, wrist, texts)
        with shared_instruction(model.dynamics) as processors:
            shared = model.encode_dynamics_batch(static, wrist, texts)
    assert sum(p.shared_calls for p in processors) == 0
    assert all(torch.equal(a, b) for a, b in zip(plain, shared))


def test_the_text_encoder_runs_once_per_shared_instruction(tiny):
    model = tiny["model"]
    if model.dynamics.text_encoder is None:
        pytest.skip("this System 3 has no CLIP text encoder")
    rows: list[int] = []
    static, wrist = _frames(model, 4, 4), _frames(model, 4, 5)
    with torch.inference_mode(), shared_instruction(model.dynamics):
        # registered after the context's own hook: it sees the ids the encoder runs on
        hook = model.dynamics.text_encoder.register_forward_pre_hook(
            lambda module, args, kwargs: rows.append(kwargs["input_ids"].shape[0]), with_kwargs=True)
        try:
            model.encode_dynamics_batch(static, wrist, ["open the drawer"] * 4)
        finally:
            hook.remove()
    assert rows == [1]  # not 2 x 4 (both views of 4 frames)


def test_shared_processor_refuses_what_it_does_not_cover():
    calls = []
    processor = SharedContextAttnProcessor(lambda *args, **kwargs: calls.append(args) or "fallback")
    attn = type("Attn", (), {"spatial_norm": None, "group_norm": None, "norm_cross": False, "norm_q": None,
                             "norm_k": None})()
    hidden = torch.zeros(2, 3, 4)
    assert processor(attn, hidden, None) == "fallback"  # self-attention
    assert processor(attn, hidden, torch.ones(2, 5, 4), torch.ones(2, 3, 5)) == "fallback"  # a mask
    assert processor(attn, hidden, torch.ones(1, 5, 4)) == "fallback"  # one row: nothing to share
    assert processor.shared_calls == 0 and len(calls) == 3


def _config(tiny, cache: str, **features_settings) -> TrainConfig:
    config = TrainConfig(stage="policy", data=str(tiny["data"]), out=str(tiny["root"] / "unused"), cache_dir=cache,
                         progress=False)
    config.features = dataclasses.replace(config.features, **features_settings)
    return config


def test_episode_features_equal_a_plain_batch_by_batch_reference(tiny):
    model, reader = tiny["model"], LeRobotReader(tiny["data"])
    config = _config(tiny, str(tiny["root"] / "unused_cache"), stride=2, batch_size=3, dtype="float32")
    out = features.compute_episode_features(model, reader, 1, config)
    frames = np.arange(0, int(reader.episodes[1]["length"]), 2)
    assert out["frame_index"].tolist() == frames.tolist()
    view = lambda camera: resize_frames(reader.episode_video(1, camera)[frames], model.image_size)  # noqa: E731
    static, wrist = view(config.static_camera), view(config.wrist_camera)
    text = reader.task_of(1)
    expected: dict[str, list[torch.Tensor]] = {"q_vl": [], "dynamics_static": [], "dynamics_wrist": []}
    with torch.inference_mode():
        for start in range(0, len(frames), 3):
            s, w = (torch.from_numpy(np.ascontiguousarray(v[start : start + 3])) for v in (static, wrist))
            expected["q_vl"].append(model.encode_vision_language_batch(s, w, [text] * len(s))[0])
            f_static, f_wrist = model.encode_dynamics_batch(s, w, [text] * len(s))
            expected["dynamics_static"].append(f_static)
            expected["dynamics_wrist"].append(f_wrist)
    for key, chunks in expected.items():
        assert torch.equal(out[key], torch.cat(chunks)), key


def _shards(folder) -> dict[str, dict[str, torch.Tensor]]:
    return {path.name: load_file(str(path)) for path in sorted(folder.glob("features/*/*.safetensors"))}


def test_worker_threads_write_the_shards_one_worker_writes(tiny, tmp_path):
    model, reader = tiny["model"], LeRobotReader(tiny["data"])
    threads = torch.get_num_threads()
    results = {}
    for workers in (1, 2):
        config = _config(tiny, str(tmp_path / f"w{workers}"), stride=3)
        _, summary = features.ensure_feature_cache(model, reader, [0, 1, 2], config, DistEnv(), progress=False,
                                                   workers=workers)
        assert summary["feature_cache_workers"] == workers and summary["feature_shards_computed"] == 3
        results[workers] = _shards(tmp_path / f"w{workers}")
    assert torch.get_num_threads() == threads
    assert len(results[1]) == 3 and results[1].keys() == results[2].keys()
    for name, tensors in results[1].items():
        assert all(torch.equal(tensors[k], results[2][name][k]) for k in tensors), name


def test_a_failing_episode_stops_the_workers_and_is_raised(tiny, tmp_path, monkeypatch):
    model, reader = tiny["model"], LeRobotReader(tiny["data"])
    real = features.compute_episode_features

    def failing(model_copy, reader_, episode, *args, **kwargs):
        if episode == 1:
            raise ValueError("features of episode 1 overflow float16")
        return real(model_copy, reader_, episode, *args, **kwargs)

    monkeypatch.setattr(features, "compute_episode_features", failing)
    threads = torch.get_num_threads()
    with pytest.raises(ValueError, match="episode 1 overflow"):
        features.ensure_feature_cache(model, reader, [0, 1, 2], _config(tiny, str(tmp_path), stride=3), DistEnv(),
                                      progress=False, workers=2)
    assert torch.get_num_threads() == threads
    from trivla_drake.train.datasets import episode_content_fingerprint

    assert f"{episode_content_fingerprint(reader, 1)}.safetensors" not in _shards(tmp_path)


def test_feature_workers_checks_and_defaults(tiny, monkeypatch):
    model = tiny["model"]
    for bad in (0, -1, True, 1.5):
        with pytest.raises(ValueError, match="workers must be an integer >= 1"):
            features.feature_workers(model, bad)
    assert features.feature_workers(model, 3) == 3
    assert features.feature_workers(model, None) == torch.get_num_threads()
    monkeypatch.setattr(features, "MAX_WORKER_COPY_BYTES", 0)  # too big to copy per worker
    assert features.feature_workers(model, 3) == 1


def test_measure_feature_cache_reports_episodes_per_minute(tiny):
    from trivla_drake.train.throughput import measure_feature_cache

    result = measure_feature_cache(tiny["data"], episodes=2, workers=2, model=tiny["model"], feature_stride=5)
    assert result["episodes"] == 2 and result["frames"] == 2 * 3 and result["workers"] == 2
    assert result["per_minute"] == pytest.approx(60 * 2 / result["seconds"])
    for name, settings in [("episodes", {"episodes": 0}), ("workers", {"workers": 0}),
                           ("feature_stride", {"feature_stride": 0})]:
        with pytest.raises(ValueError, match=f"{name} must be an integer >= 1"):
            measure_feature_cache(tiny["data"], **{"episodes": 1, "workers": 1, "model": tiny["model"], **settings})


def test_measure_training_steps_reports_steps_per_second(tiny, tmp_path):
    from trivla_drake.train.throughput import measure_training_steps

    checkpoint = tmp_path / "tiny"
    save_checkpoint(tiny["model"], str(checkpoint))
    threads = torch.get_num_threads()
    result = measure_training_steps(tiny["data"], steps=2, batch_size=4, workers=1, warmup_steps=1,
                                    checkpoint=checkpoint, feature_stride=4)
    assert torch.get_num_threads() == threads
    assert result["steps"] == 2 and result["batch_size"] == 4 and result["steps_per_second"] > 0
    assert result["steps_per_second"] == pytest.approx(2 / result["seconds"])
    with pytest.raises(ValueError, match="steps must be an integer >= 1"):
        measure_training_steps(tiny["data"], steps=0, checkpoint=checkpoint)
