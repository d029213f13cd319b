"""System 1: embodiment-specific layers, Video Former (eq. 4) shapes, the DiT, and the action head."""

import pytest
import torch

from trivla_drake.nn.dit import DiffusionTransformer
from trivla_drake.nn.embodiment import EmbodimentLinear, EmbodimentMLP, check_embodiment_ids
from trivla_drake.nn.policy import FlowMatchingPolicy
from trivla_drake.nn.presets import make_config
from trivla_drake.nn.video_former import VideoFormer




def test_embodiment_weights_differ_and_only_the_used_slice_learns():
    torch.manual_seed(0)
    layer = EmbodimentMLP(3, 5, 16, 4)
    x = torch.randn(1, 5)
    outs = [layer(x, torch.tensor([e])) for e in range(3)]
    assert not torch.allclose(outs[0], outs[1]) and not torch.allclose(outs[1], outs[2])
    assert not torch.equal(layer.fc1.weight[0], layer.fc1.weight[1])
    # a batch mixing embodiments uses each sample's own weights
    mixed = layer(x.expand(3, 5), torch.tensor([0, 1, 2]))
    torch.testing.assert_close(mixed, torch.cat(outs))
    # gradients from embodiment 1 reach only slice 1
    layer(torch.randn(4, 5), torch.tensor([1, 1, 1, 1])).sum().backward()
    grad = layer.fc1.weight.grad
    assert grad[1].abs().sum() > 0 and grad[0].abs().sum() == 0 and grad[2].abs().sum() == 0
    single = EmbodimentLinear(2, 3, 2)
    assert single(torch.randn(2, 7, 3), torch.tensor([0, 1])).shape == (2, 7, 2)


def test_embodiment_gradients_are_the_same_on_every_run_with_several_threads():
    """A seeded training run repeats bit for bit: the weight gradient does not depend on how the CPU
    threads interleave (advanced indexing's backward added with atomics and differed run to run)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        torch.manual_seed(0)
        layer = EmbodimentLinear(2, 384, 192)
        x, upstream = torch.randn(32, 12, 384), torch.randn(32, 12, 192)
        ids = torch.tensor([0, 0, 1] * 10 + [0, 1])

        def weight_gradient() -> torch.Tensor:
            layer.zero_grad(set_to_none=True)
            (layer(x, ids) * upstream).sum().backward()
            return layer.weight.grad.clone()

        first = weight_gradient()
        assert all(torch.equal(first, weight_gradient()) for _ in range(8))
    finally:
        torch.set_num_threads(threads)


def test_unknown_embodiment_ids_are_rejected():
    with pytest.raises(ValueError, match="embodiment_id"):
        check_embodiment_ids(torch.tensor([0, 2]), 2)
    with pytest.raises(ValueError, match="embodiment_id"):
        check_embodiment_ids(torch.tensor([-1]), 2)


def test_video_former_shapes_eq4():
    former = VideoFormer(
        feature_channels=12, num_frames=3, feature_size=4, dim=16, depth=2, num_heads=2, queries_per_frame=5
    )
    static, wrist = torch.randn(2, 3, 12, 4, 4), torch.randn(2, 3, 12, 4, 4)
    q_p = former([static, wrist])
    assert q_p.shape == (2, 3 * 5, 16)
    # each view matters
    assert not torch.allclose(q_p, former([static, torch.randn_like(wrist)]))
    with pytest.raises(ValueError, match="dynamics features"):
        former([static, torch.randn(2, 4, 12, 4, 4)])


def test_dit_starts_ignoring_its_condition_and_respects_the_memory_mask():
    """AdaLN-Zero: every block's modulation starts at zero, so a fresh DiT's output does not depend on the time
    condition yet (its cross-attention to the memory is not gated, so the blocks are not identities)."""
    torch.manual_seed(0)
    dit = DiffusionTransformer(dim=16, depth=2, num_heads=2)
    x, cond = torch.randn(2, 6, 16), torch.randn(2, 16)
    memory = torch.randn(2, 4, 16)
    mask = torch.tensor([[True, True, False, False]] * 2)
    out = dit(x, cond, memory, mask)
    assert out.shape == x.shape
    torch.testing.assert_close(out, dit(x, torch.randn(2, 16), memory, mask))
    # masked memory tokens have no influence
    memory2 = memory.clone()
    memory2[:, 2:] += 100.0
    torch.testing.assert_close(out, dit(x, cond, memory2, mask))


def test_vl_position_embedding_marks_where_each_leading_token_lies():
    """With `vl_position_embedding`, identical Q_vl tokens at the leading (image) positions become
    different condition tokens, one per position; the instruction tokens after them are untouched.
    Without it the same tokens stay the same (System 1 cannot tell where a token lies)."""
    import dataclasses

    config = make_config("tiny").policy
    torch.manual_seed(0)
    q_vl = torch.randn(1, 1, 8).expand(2, 7, 8)
    memories = {}
    for on in (False, True):
        policy = FlowMatchingPolicy(dataclasses.replace(config, vl_position_embedding=on), vl_dim=8,
                                    dynamics_feature_shape=None, vl_fixed_positions=4)
        policy.vl_standardizer.eval()  # its identity start: every position the same statistics
        memories[on] = policy.conditions(torch.zeros(2, config.hidden_size), q_vl, None, None)[1]
        assert (policy.vl_position is not None) == on
    same = lambda m, i, j: torch.allclose(m[:, i], m[:, j])  # noqa: E731
    assert all(same(memories[False], 0, j) for j in range(1, 7))
    assert not any(same(memories[True], i, j) for i in range(4) for j in range(i + 1, 7))
    assert same(memories[True], 4, 5) and same(memories[True], 5, 6)


def test_action_head_overfits_a_fixed_chunk():
    config = make_config("tiny").policy
    torch.manual_seed(0)
    policy = FlowMatchingPolicy(config, vl_dim=8, dynamics_feature_shape=None)
    gen = torch.Generator().manual_seed(0)
    actions = torch.rand(1, config.action_horizon, config.action_dim, generator=gen) * 2 - 1
    q_vl = torch.randn(1, 3, 8, generator=gen)
    eid = torch.tensor([1])
    opt = torch.optim.Adam(policy.parameters(), lr=3e-3)
    for _ in range(200):
        q_s = policy.encode_state(torch.zeros(1, policy.state_input_dim), eid)
        q_s, memory, mask, _ = policy.conditions(q_s, q_vl, None, None)
        loss, _ = policy.loss(actions.expand(16, -1, -1), q_s.expand(16, -1), memory.expand(16, -1, -1),
                              mask.expand(16, -1), eid.expand(16), generator=gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        q_s = policy.encode_state(torch.zeros(1, policy.state_input_dim), eid)
        q_s, memory, mask, _ = policy.conditions(q_s, q_vl, None, None)
        sample = policy.sample(q_s.expand(8, -1), memory.expand(8, -1, -1), mask.expand(8, -1), eid.expand(8),
                               generator=gen, num_steps=10)
    error = (sample - actions).abs().mean().item()
    assert error < 0.15, f"mean abs error {error:.3f} after overfitting one chunk"
