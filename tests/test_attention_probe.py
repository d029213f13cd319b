"""The attention probe reads where a block is only when the tokens carry their positions, and names
bad input."""

import numpy as np
import pytest

from trivla_drake.eval.attention_probe import attention_probe


def _tokens_with_blocks(n=300, tokens=16, dim=8, blocks=2, seed=0):
    """Each block k shows up in one random token as channel k; its (x, y) is where that token lies
    on a 4x4 grid. Nothing in the token's content says where it is."""
    rng = np.random.default_rng(seed)
    x = 0.1 * rng.normal(size=(n, tokens, dim)).astype(np.float32)
    y = np.zeros((n, 2 * blocks))
    for i in range(n):
        for k, t in enumerate(rng.choice(tokens, blocks, replace=False)):
            x[i, t, k] += 3.0
            y[i, 2 * k : 2 * k + 2] = divmod(int(t), 4)
    return x, y


def test_attention_read_out_needs_token_positions_to_locate_blocks():
    x, y = _tokens_with_blocks()
    r2_without, _ = attention_probe(x, y, positions=False, steps=600)
    r2_with, rmse_with = attention_probe(x, y, positions=True, steps=1500)
    assert r2_without.shape == r2_with.shape == (4,)
    assert (r2_without < 0.2).all(), r2_without
    assert (r2_with > 0.8).all() and (rmse_with < 0.6).all(), (r2_with, rmse_with)


@pytest.mark.parametrize(
    "tokens, targets, kwargs, message",
    [
        (np.zeros((20, 4)), np.zeros((20, 2)), {}, "tokens must be 3-D"),
        (np.zeros((20, 4, 3)), np.zeros((20, 3)), {}, "targets must be"),
        (np.zeros((20, 4, 3)), np.zeros((19, 2)), {}, "tokens has 20 rows but targets has 19"),
        (np.zeros((5, 4, 3)), np.zeros((5, 2)), {}, "held_out"),
        (np.full((20, 4, 3), np.nan), np.zeros((20, 2)), {}, "finite"),
        (np.zeros((20, 4, 3)), np.zeros((20, 2)), {"steps": 0}, "steps"),
    ],
)
def test_attention_probe_rejects_bad_input(tokens, targets, kwargs, message):
    with pytest.raises(ValueError, match=message):
        attention_probe(tokens, targets, positions=True, **kwargs)
