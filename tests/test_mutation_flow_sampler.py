"""The Euler sampler evaluates the velocity at the start of each step (t = 0, dt, ..., 1 - dt).

A constant velocity or a trained network cannot tell the start of a step from its end; a velocity that
changes with time can: for v(x, t) = t, N Euler steps from t = 0 give exactly x_0 + (N - 1) / (2 N)
(the left Riemann sum of t), and evaluating at the end of each step would give x_0 + (N + 1) / (2 N).
"""

import pytest
import torch

from trivla_drake.nn import flow_matching


@pytest.mark.parametrize("num_steps", [1, 2, 4, 10])
def test_euler_sampler_evaluates_the_velocity_at_the_start_of_each_step(num_steps):
    noise = torch.tensor([[0.25, -1.0], [2.0, 0.0]], dtype=torch.float64)
    times_seen = []

    def velocity_equal_to_time(x, t):
        times_seen.append(t.clone())
        return t[:, None].expand_as(x)

    out = flow_matching.euler_sample(velocity_equal_to_time, noise, num_steps)

    expected_shift = (num_steps - 1) / (2 * num_steps)
    torch.testing.assert_close(out, noise + expected_shift, rtol=0.0, atol=1e-12)
    # One call per step, every sample at the step's start time, in order.
    assert len(times_seen) == num_steps
    for i, t in enumerate(times_seen):
        assert t.shape == (noise.shape[0],) and t.dtype == noise.dtype
        torch.testing.assert_close(t, torch.full_like(t, i / num_steps), rtol=0.0, atol=1e-12)


def test_euler_sampler_feeds_each_step_the_state_it_reached():
    """v(x, t) = x: N Euler steps multiply x_0 by (1 + 1/N)^N (a sampler that reused x_0 would give 2 x_0)."""
    noise = torch.tensor([[1.0, -0.5, 3.0]], dtype=torch.float64)
    out = flow_matching.euler_sample(lambda x, t: x, noise, 5)
    torch.testing.assert_close(out, noise * (1.0 + 1.0 / 5) ** 5, rtol=1e-12, atol=0.0)
