"""System 2: 64 image tokens per 224x224 frame, pixel shuffle layout, middle-layer read-out, LM loss."""

import numpy as np
import pytest
import torch

from trivla_drake.nn.pixel_shuffle import pixel_shuffle
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.trivla import TriVLA




@pytest.fixture(scope="module")
def model():
    return TriVLA(make_config("tiny")).eval()


def _frames(n, seed=0):
    return torch.from_numpy(np.random.default_rng(seed).integers(0, 256, (n, 224, 224, 3), dtype=np.uint8))


def test_pixel_shuffle_folds_2x2_blocks_in_row_major_order():
    grid, channels = 4, 3
    tokens = torch.arange(grid * grid * channels, dtype=torch.float32).reshape(1, grid * grid, channels)
    out = pixel_shuffle(tokens, 0.5)
    assert out.shape == (1, 4, 4 * channels)
    as_grid = tokens.reshape(grid, grid, channels)
    for i in range(2):
        for j in range(2):
            expected = torch.cat([as_grid[2 * i + r, 2 * j + c] for r in range(2) for c in range(2)])
            assert torch.equal(out[0, i * 2 + j], expected)


def test_64_image_tokens_per_224_frame(model):
    vl = model.vision_language
    assert vl.num_image_tokens == 64
    with torch.no_grad():
        tokens = vl.encode_images(_frames(3))
    assert tokens.shape == (3, 64, vl.hidden_size)
    for preset in ("cpu", "paper"):
        vision = make_config(preset).vision_language.vision
        assert (vision.image_size // vision.patch_size) ** 2 // 4 == 64


def test_q_vl_is_the_chosen_llm_layer_and_later_layers_never_run(model):
    vl = model.vision_language
    k = vl.config.select_layer
    assert k < len(vl.llm.model.layers)  # the tiny preset keeps a layer above the read-out
    frames = _frames(2)[None]
    ids = model._vl_instruction_ids(["stack the blocks"], "instruction")
    calls = {i: 0 for i in range(len(vl.llm.model.layers))}
    hooks = [
        layer.register_forward_hook(lambda *a, i=i: calls.__setitem__(i, calls[i] + 1))
        for i, layer in enumerate(vl.llm.model.layers)
    ]
    norm_calls = []
    hooks.append(vl.llm.model.norm.register_forward_hook(lambda *a: norm_calls.append(1)))
    try:
        with torch.no_grad():
            q_vl, mask = vl(frames, ids)
    finally:
        for h in hooks:
            h.remove()
    assert all(calls[i] == 1 for i in range(k)) and all(calls[i] == 0 for i in range(k, len(calls)))
    assert not norm_calls
    prompt_len = sum(len(p) for p in vl.build_prompts(ids, 2)[0].text_pieces) + 2 * 64
    assert q_vl.shape == (1, prompt_len, vl.hidden_size) and mask.all()

    # The same states as the full LLM's hidden_states[k] (transformers' own indexing: 0 = embeddings).
    with torch.no_grad():
        tokens = vl.encode_images(frames.flatten(0, 1)).unflatten(0, (1, 2))
        embeds, attn, _ = vl.assemble(tokens, vl.build_prompts(ids, 2))
        full = vl.llm.model(inputs_embeds=embeds, attention_mask=attn.long(), output_hidden_states=True)
    torch.testing.assert_close(q_vl, full.hidden_states[k])
    assert not torch.allclose(q_vl, full.hidden_states[-1])


def test_batching_with_padding_matches_single_samples(model):
    frames = _frames(4, seed=1).reshape(2, 2, 224, 224, 3)
    texts = ["open the drawer", "push the blue block to the left side"]
    with torch.no_grad():
        q_batch, mask = model.vision_language(frames, model._vl_instruction_ids(texts, "instruction"))
        for b, text in enumerate(texts):
            q_one, _ = model.vision_language(frames[b : b + 1], model._vl_instruction_ids([text], "instruction"))
            n = q_one.shape[1]
            assert mask[b].sum() == n
            torch.testing.assert_close(q_batch[b, :n], q_one[0], atol=1e-5, rtol=1e-4)


def test_vlm_loss_trains_the_projector(model):
    frames = _frames(4, seed=2)
    batch = {
        "static_rgb": frames[:2],
        "wrist_rgb": frames[2:],
        "instruction": ["what is on the table?", "is the drawer open?"],
        "answer": ["a red block", "no"],
    }
    model.zero_grad()
    loss, info = model.compute_vlm_loss(batch)
    assert torch.isfinite(loss) and info["vlm_loss"] == pytest.approx(loss.item())
    loss.backward()
    assert model.vision_language.projector[1].weight.grad.abs().sum() > 0
    model.zero_grad()
    with pytest.raises(ValueError, match="answer"):
        model.compute_vlm_loss({**batch, "answer": ["a red block", ""]})


def test_dense_block_targets_mark_the_cells_that_show_each_block():
    """A token's cell shows block k when at least DENSE_MIN_FRACTION of its pixels are labelled
    1 + k; cells are row-major, as the tokens after pixel shuffle."""
    from trivla_drake.nn.vision_language import dense_block_targets

    labels = torch.zeros(1, 56, 56, dtype=torch.uint8)
    labels[0, 30:32, 5:10] = 2  # 10 pixels of block 1 in cell (row 1, column 0): token 2
    labels[0, 3, 40:42] = 3  # 2 pixels of block 2 in cell (0, 1): 0.26% of its 784, below the share
    targets = dense_block_targets(labels, grid=2, classes=3)
    assert targets.shape == (1, 4, 3)
    assert targets[0, 2, 1] == 1 and targets.sum() == 1
    with pytest.raises(ValueError, match="block labels go up to 4"):
        dense_block_targets(labels + 1 * (labels == 3), grid=2, classes=3)
    with pytest.raises(ValueError, match="divisible by 3"):
        dense_block_targets(labels, grid=3, classes=3)


def test_dense_block_targets_with_subcells_say_where_in_the_cell_a_block_lies():
    """With sub-cells each token's entries are its cell's sub-cells in row-major order, each with
    one entry per class; one sub-cell per side is the whole cell."""
    from trivla_drake.nn.vision_language import dense_block_targets

    labels = torch.zeros(1, 56, 56, dtype=torch.uint8)
    labels[0, 30:32, 5:10] = 2  # token 2 (cell row 1, column 0), its sub-cell (row 0, column 0) of 2 x 2
    labels[0, 50:52, 50:52] = 1  # token 3 (row 1, column 1), sub-cell (1, 1)
    labels[0, 5:8, 30:33] = 1  # token 1 (row 0, column 1), sub-cell (0, 0): tells rows from columns apart
    targets = dense_block_targets(labels, grid=2, classes=3, subcells=2)
    assert targets.shape == (1, 4, 12)
    assert targets[0, 2, 0 * 3 + 1] == 1 and targets[0, 3, 3 * 3 + 0] == 1 and targets[0, 1, 0] == 1
    assert targets.sum() == 3
    whole = dense_block_targets(labels, grid=2, classes=3)
    assert torch.equal(whole, targets.view(1, 4, 4, 3).amax(2))
    with pytest.raises(ValueError, match="2 tokens x 3 sub-cells"):
        dense_block_targets(labels, grid=2, classes=3, subcells=3)


def test_dense_subcells_widen_the_block_head_and_are_checked():
    import dataclasses

    cfg = make_config("tiny", use_system3=False)
    vl = dataclasses.replace(cfg.vision_language, dense_classes=3, dense_subcells=2)
    model = TriVLA(dataclasses.replace(cfg, vision_language=vl))
    assert model.vision_language.block_head.out_features == 3 * 4
    size = model.image_size
    labels = torch.zeros(1, 2, size, size, dtype=torch.uint8)
    labels[:, 0, 10:20, 10:20] = 1
    frames = _frames(2, seed=5)
    batch = {"static_rgb": frames[:1], "wrist_rgb": frames[1:], "instruction": ["is the drawer open?"],
             "answer": ["no"], "block_labels": labels}
    loss, info = model.compute_vlm_loss(batch, dense_weight=1.0)
    assert info["dense_loss"] > 0 and torch.isfinite(loss)
    cell = size // round(model.vision_language.num_image_tokens**0.5)
    with pytest.raises(ValueError, match=f"dense_subcells \\(train: vlm.dense_subcells\\) must be >= 1 and divide a token's image cell \\({cell} pixels\\)"):
        TriVLA(dataclasses.replace(cfg, vision_language=dataclasses.replace(vl, dense_subcells=cell + 1)))


def test_dense_loss_trains_the_vision_tower_and_names_bad_labels():
    import dataclasses

    cfg = make_config("tiny", use_system3=False)
    cfg = dataclasses.replace(cfg, vision_language=dataclasses.replace(cfg.vision_language, dense_classes=3))
    torch.manual_seed(0)
    model = TriVLA(cfg)
    size = model.image_size
    frames = _frames(4, seed=4)
    labels = torch.zeros(2, 2, size, size, dtype=torch.uint8)
    labels[:, 0, 10:40, 10:40] = 1
    labels[1, 1, 100:140, 50:90] = 3
    batch = {"static_rgb": frames[:2], "wrist_rgb": frames[2:], "instruction": ["is the drawer open?"] * 2,
             "answer": ["no", "yes"], "block_labels": labels}
    plain, plain_info = model.compute_vlm_loss(batch)
    loss, info = model.compute_vlm_loss(batch, dense_weight=0.5)
    assert "dense_loss" not in plain_info and info["vlm_loss"] == pytest.approx(plain_info["vlm_loss"], rel=1e-5)
    assert loss.item() == pytest.approx(info["vlm_loss"] + 0.5 * info["dense_loss"], rel=1e-5)
    model.zero_grad()
    loss.backward()
    vl = model.vision_language
    assert vl.block_head.weight.grad.abs().sum() > 0
    assert next(vl.vision_encoder.parameters()).grad.abs().sum() > 0
    with pytest.raises(ValueError, match="block_labels"):
        model.compute_vlm_loss({k: v for k, v in batch.items() if k != "block_labels"}, dense_weight=1.0)
    with pytest.raises(ValueError, match="block_labels"):
        model.compute_vlm_loss({**batch, "block_labels": labels[:, :1]}, dense_weight=1.0)
    with pytest.raises(ValueError, match="dense_weight must be >= 0"):
        model.compute_vlm_loss(batch, dense_weight=-1.0)
    with pytest.raises(ValueError, match="dense_classes is 0"):
        TriVLA(make_config("tiny", use_system3=False)).compute_vlm_loss(batch, dense_weight=1.0)
    with pytest.raises(ValueError, match="dense_classes"):
        TriVLA(dataclasses.replace(cfg, vision_language=dataclasses.replace(cfg.vision_language, dense_classes=-1)))
