"""The pretrained-loading path on tiny random models saved to a temp dir (never downloads): SigLIP,
Llama (SmolLM2's architecture), a transformers tokenizer, CLIP text, SVD's unet/ and vae/, Eagle-2."""

import dataclasses

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from trivla_drake.nn import pretrained
from trivla_drake.nn.benchmark import example_observation
from trivla_drake.nn.checkpoint import load_checkpoint, save_checkpoint
from trivla_drake.nn.pixel_shuffle import pixel_shuffle
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.tokenizer import PretrainedTokenizer
from trivla_drake.nn.trivla import TriVLA



SPECIALS = ["<|im_start|>", "<|im_end|>", "<img>", "</img>"]


def _byte_level_hf_tokenizer():
    """A byte-level BPE tokenizer without merges, built offline like a released one's files."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast

    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet())
    tok = Tokenizer(models.BPE(vocab={c: i for i, c in enumerate(alphabet)}, merges=[]))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    return PreTrainedTokenizerFast(
        tokenizer_object=tok,
        bos_token="<|endoftext|>",
        eos_token="<|endoftext|>",
        pad_token="<pad>",
        additional_special_tokens=SPECIALS,
    )


@pytest.fixture(scope="module")
def released(tmp_path_factory):
    """Tiny 'released' models saved with save_pretrained, and the originals to compare with."""
    root = tmp_path_factory.mktemp("released")
    torch.manual_seed(0)
    base = make_config("tiny")
    hf_tok = _byte_level_hf_tokenizer()
    vocab = len(hf_tok) + 2
    siglip = pretrained.build_siglip_vision(pretrained.siglip_vision_config(base.vision_language.vision)).eval()
    llm_cfg = dataclasses.replace(base.vision_language.llm, vocab_size=vocab)
    llm = pretrained.build_llama(pretrained.llama_config(llm_cfg, pad_token_id=hf_tok.pad_token_id)).eval()
    text_cfg = dataclasses.replace(base.dynamics.text, vocab_size=vocab)
    clip = pretrained.build_clip_text(
        pretrained.clip_text_config(
            text_cfg,
            pad_token_id=hf_tok.pad_token_id,
            bos_token_id=hf_tok.bos_token_id,
            eos_token_id=hf_tok.eos_token_id,
        )
    ).eval()
    vae = pretrained.build_svd_vae(pretrained.svd_vae_config(base.dynamics.vae)).eval()
    unet = pretrained.build_svd_unet(
        pretrained.svd_unet_config(base.dynamics.unet, latent_channels=4, num_frames=base.dynamics.num_frames)
    ).eval()
    siglip.save_pretrained(root / "siglip")
    llm.save_pretrained(root / "smollm2")
    hf_tok.save_pretrained(root / "smollm2")
    clip.save_pretrained(root / "clip")
    hf_tok.save_pretrained(root / "clip")
    unet.save_pretrained(root / "svd" / "unet")
    vae.save_pretrained(root / "svd" / "vae")
    return dict(root=root, siglip=siglip, llm=llm, clip=clip, vae=vae, unet=unet)


def _config_with_paths(root):
    base = make_config("tiny")
    vl = dataclasses.replace(
        base.vision_language,
        siglip_path=str(root / "siglip"),
        llm_path=str(root / "smollm2"),
        tokenizer_path=str(root / "smollm2"),
    )
    dyn = dataclasses.replace(
        base.dynamics,
        svd_path=str(root / "svd"),
        text_encoder_path=str(root / "clip"),
        text_tokenizer_path=str(root / "clip"),
    )
    return dataclasses.replace(base, vision_language=vl, dynamics=dyn)


def _assert_same_module_outputs(a, b, *args, **kwargs):
    """Same weights, and the same outputs (up to float reassociation between attention kernels)."""
    state_a, state_b = a.state_dict(), b.state_dict()
    assert state_a.keys() == state_b.keys()
    assert all(torch.equal(state_a[k], state_b[k]) for k in state_a)
    with torch.no_grad():
        out_a, out_b = a(*args, **kwargs), b(*args, **kwargs)
    torch.testing.assert_close(_main_output(out_a), _main_output(out_b), rtol=1e-4, atol=1e-5)


def _main_output(out):
    if torch.is_tensor(out):
        return out
    if isinstance(out, tuple):
        return out[0]
    return out.sample if hasattr(out, "sample") else out.last_hidden_state


def test_components_load_from_local_directories(released):
    model = TriVLA(_config_with_paths(released["root"])).eval()
    vl, dyn = model.vision_language, model.dynamics
    assert isinstance(vl.tokenizer, PretrainedTokenizer) and isinstance(dyn.tokenizer, PretrainedTokenizer)
    pixels = torch.randn(1, 3, 224, 224)
    _assert_same_module_outputs(vl.vision_encoder, released["siglip"], pixel_values=pixels)
    ids = torch.tensor([[5, 9, 200, 3]])
    _assert_same_module_outputs(vl.llm.model, released["llm"].model, input_ids=ids)
    _assert_same_module_outputs(dyn.text_encoder, released["clip"], input_ids=ids)
    _assert_same_module_outputs(dyn.vae.encoder, released["vae"].encoder, torch.randn(1, 3, 16, 16))
    sample = torch.randn(1, 3, 8, 8, 8)
    _assert_same_module_outputs(
        dyn.unet, released["unet"], sample, torch.tensor([1.0]), torch.randn(1, 4, 32), torch.zeros(1, 3)
    )
    # the pretrained tokenizer really is what tokenises instructions
    tok = vl.tokenizer.hf_tokenizer
    assert model._vl_instruction_ids(["hi there"], "instruction")[0] == tok.encode("hi there", add_special_tokens=False)
    chunk = model.predict_action_chunk(example_observation(), seed=0)
    assert chunk.shape == (10, 7)


def test_checkpoint_of_a_pretrained_model_carries_its_tokenizers(released, tmp_path):
    model = TriVLA(_config_with_paths(released["root"])).eval()
    save_checkpoint(model, str(tmp_path / "ckpt"))
    assert (tmp_path / "ckpt" / "tokenizer_vision_language").is_dir()
    loaded = load_checkpoint(str(tmp_path / "ckpt")).eval()
    assert isinstance(loaded.vision_language.tokenizer, PretrainedTokenizer)
    obs = example_observation()
    np.testing.assert_array_equal(model.predict_action_chunk(obs, seed=2), loaded.predict_action_chunk(obs, seed=2))


def test_llm_can_be_cut_at_the_read_out_layer(released):
    cut = pretrained.load_llama(str(released["root"] / "smollm2"), num_hidden_layers=1).eval()
    assert len(cut.model.layers) == 1
    ids = torch.tensor([[1, 2, 3]])
    with torch.no_grad():
        full = released["llm"].model(input_ids=ids, output_hidden_states=True).hidden_states[1]
        part = cut.model(input_ids=ids, output_hidden_states=True).hidden_states[1]
    # hidden_states[1] of the cut model is its last entry, which transformers replaces by the normed one
    torch.testing.assert_close(cut.model.norm(full), part)


def test_eagle2_checkpoint_layout_loads(released, tmp_path):
    siglip, llm = released["siglip"], released["llm"]
    torch.manual_seed(1)
    projector = pretrained.eagle_projector(siglip.config.hidden_size, llm.config.hidden_size, 0.5)
    # The released layout (transformers 4.x): SigLIP's weights nest under vision_model.vision_model.*
    state = {f"vision_model.vision_model.{k}": v for k, v in siglip.state_dict().items()}
    state.update({f"mlp1.{k}": v for k, v in projector.state_dict().items()})
    state.update({f"language_model.{k}": v for k, v in llm.state_dict().items() if k != "lm_head.weight"})
    directory = tmp_path / "eagle2"
    directory.mkdir()
    save_file({k: v.contiguous() for k, v in state.items()}, str(directory / "model.safetensors"))
    meta = {
        "vision_config": siglip.config.to_dict(),
        "llm_config": llm.config.to_dict(),
        "downsample_ratio": 0.5,
        "select_layer": -1,
    }
    (directory / "config.json").write_text(__import__("json").dumps(meta))
    base = make_config("tiny")
    config = dataclasses.replace(
        base,
        vision_language=dataclasses.replace(
            base.vision_language, eagle2_path=str(directory), tokenizer_path=str(released["root"] / "smollm2")
        ),
    )
    vl = TriVLA(config).eval().vision_language
    frames = torch.from_numpy(example_observation()["static_rgb"])[None]
    with torch.no_grad():
        ours = vl.encode_images(frames)
        pixels = (frames.permute(0, 3, 1, 2).float() / 255 - 0.5) / 0.5
        reference = projector(pixel_shuffle(siglip(pixel_values=pixels).last_hidden_state))
    torch.testing.assert_close(ours, reference)
    with pytest.raises(ValueError, match="not a directory"):
        pretrained.load_eagle2(str(tmp_path / "missing"))
    (directory / "config.json").write_text(__import__("json").dumps({**meta, "ps_version": "v1"}))
    with pytest.raises(ValueError, match="ps_version 'v1'; only 'v2'"):  # v1 would transpose the token grid
        pretrained.load_eagle2(str(directory))


def test_missing_pretrained_directories_are_value_errors(tmp_path):
    base = make_config("tiny")
    config = dataclasses.replace(
        base, vision_language=dataclasses.replace(base.vision_language, siglip_path=str(tmp_path / "nope"))
    )
    with pytest.raises(ValueError, match="SigLIP path"):
        TriVLA(config)
    config = dataclasses.replace(base, dynamics=dataclasses.replace(base.dynamics, svd_path=str(tmp_path / "nope")))
    with pytest.raises(ValueError, match="SVD"):
        TriVLA(config)
