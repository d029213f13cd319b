"""Flow matching (time convention t = 0 noise, t = 1 data) learns a known 2-D multi-modal distribution.

The checks are discriminative: training with a flipped velocity target, sampling with the opposite
time convention (lerobot pi0's: t = 1 noise) or with a sign error in the Euler update all fail them
(asserted below), so a wrong loss or sampler fails this file.
"""

import pytest
import torch
from torch import nn

from trivla_drake.nn import flow_matching
from trivla_drake.nn.dit import sinusoidal_embedding



MODES = torch.tensor([[1.5, 1.5], [1.5, -1.5], [-1.5, 1.5], [-1.5, -1.5]])
MODE_STD = 0.1
NEAR = 0.75  # a sample 'lands on' a mode within 7.5 standard deviations of it


def sample_mixture(n, generator):
    idx = torch.randint(0, len(MODES), (n,), generator=generator)
    return MODES[idx] + MODE_STD * torch.randn(n, 2, generator=generator)


class VelocityMLP(nn.Module):
    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(2 + 32, 128), nn.SiLU(), nn.Linear(128, 128), nn.SiLU(), nn.Linear(128, 2))

    def forward(self, x, t):
        return self.net(torch.cat([x, sinusoidal_embedding(t, 32)], dim=-1))


def train(flip_target=False, steps=600, seed=0):
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    net = VelocityMLP()
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(steps):
        data = sample_mixture(256, gen)
        if flip_target:  # the wrong sign: regress noise - data instead of data - noise
            t = flow_matching.sample_flow_time(256, generator=gen)
            noise = torch.randn(data.shape, generator=gen)
            x_t = flow_matching.interpolate(noise, data, t)
            loss = ((net(x_t, t) + flow_matching.velocity_target(noise, data)) ** 2).mean()
        else:
            loss, _ = flow_matching.flow_matching_loss(net, data, generator=gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net


def mode_statistics(samples):
    dist = torch.cdist(samples, MODES)
    nearest = dist.argmin(dim=1)
    near = dist.min(dim=1).values < NEAR
    shares = torch.bincount(nearest[near], minlength=len(MODES)).float() / len(samples)
    return near.float().mean().item(), shares


def looks_like_the_mixture(samples):
    near, shares = mode_statistics(samples)
    return near > 0.8 and bool((shares > 0.15).all())


@pytest.fixture(scope="module")
def trained():
    return train()


def test_learns_all_modes_of_a_2d_mixture(trained):
    with torch.no_grad():
        noise = torch.randn(2000, 2, generator=torch.Generator().manual_seed(1))
        samples = flow_matching.euler_sample(trained, noise, num_steps=10)
    near, shares = mode_statistics(samples)
    assert near > 0.8, f"only {near:.0%} of samples near a mode"
    assert (shares > 0.15).all(), f"mode shares {shares.tolist()}"


def test_sampler_of_the_opposite_time_convention_fails(trained):
    def pi0_style_sampler(velocity_fn, noise, num_steps):  # t = 1 is noise, integrate t: 1 -> 0
        x, dt = noise, -1.0 / num_steps
        for i in range(num_steps):
            t = torch.full((x.shape[0],), 1.0 + i * dt)
            x = x + dt * velocity_fn(x, t)
        return x

    with torch.no_grad():
        noise = torch.randn(2000, 2, generator=torch.Generator().manual_seed(1))
        assert not looks_like_the_mixture(pi0_style_sampler(trained, noise, 10))
        # and a sign error in the Euler update
        assert not looks_like_the_mixture(flow_matching.euler_sample(lambda x, t: -trained(x, t), noise, 10))


def test_flipped_velocity_target_fails():
    net = train(flip_target=True, steps=300)
    with torch.no_grad():
        noise = torch.randn(2000, 2, generator=torch.Generator().manual_seed(1))
        assert not looks_like_the_mixture(flow_matching.euler_sample(net, noise, num_steps=10))


def test_time_sampling_convention():
    t = flow_matching.sample_flow_time(20000, generator=torch.Generator().manual_seed(0))
    assert t.min() >= 0 and t.max() <= 1
    # u ~ Beta(1.5, 1) has mean 0.6, so t = (0.999 - u) / 0.999 has mean ~0.4: weighted to the noise end.
    assert t.mean().item() == pytest.approx((0.999 - 0.6) / 0.999, abs=0.01)
    def general_beta(seed):
        return flow_matching.sample_flow_time(5, alpha=2.0, beta=3.0, generator=torch.Generator().manual_seed(seed))

    assert torch.equal(general_beta(3), general_beta(3))
    noise, data = torch.zeros(2, 3), torch.ones(2, 3)
    assert torch.equal(flow_matching.interpolate(noise, data, torch.zeros(2)), noise)
    assert torch.equal(flow_matching.interpolate(noise, data, torch.ones(2)), data)


def test_euler_is_exact_for_straight_paths():
    data = torch.tensor([[3.0, -1.0]])
    noise = torch.tensor([[0.5, 0.5]])
    out = flow_matching.euler_sample(lambda x, t: flow_matching.velocity_target(noise, data), noise, 4)
    torch.testing.assert_close(out, data)
    with pytest.raises(ValueError):
        flow_matching.euler_sample(lambda x, t: x, noise, 0)
