"""The latent diffusion's schedule, v-parameterisation and DDIM sampler against their closed forms."""

import numpy as np
import pytest
import torch

from scube_sim.model.nn.diffusion import NoiseSchedule, ddim_sample, ddim_timesteps


def test_linear_schedule_matches_its_definition():
    s = NoiseSchedule(1000, 1e-4, 2e-2)
    betas = np.linspace(1e-4, 2e-2, 1000)
    np.testing.assert_allclose(s.alpha_bar.numpy(), np.cumprod(1 - betas), rtol=1e-12)
    # DDPM's schedule leaves almost no signal at the last step (abar_T ~ 4e-5)
    assert 1e-5 < float(s.alpha_bar[-1]) < 1e-4
    assert float(s.alpha_bar[0]) == pytest.approx(1 - 1e-4)


def test_v_parameterisation_identities():
    s = NoiseSchedule(1000)
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(6, 3, 4, 4, 2, dtype=torch.float64, generator=g)
    eps = torch.randn(x0.shape, dtype=torch.float64, generator=g)
    t = torch.tensor([0, 1, 10, 500, 998, 999])
    xt = s.q_sample(x0, t, eps)
    v = s.v_target(x0, t, eps)
    torch.testing.assert_close(s.x0_from_v(xt, t, v), x0, rtol=0, atol=1e-12)
    torch.testing.assert_close(s.eps_from_v(xt, t, v), eps, rtol=0, atol=1e-12)
    # v is a rotation of (x0, eps): its norm with x_t's is preserved per element
    torch.testing.assert_close(xt ** 2 + v ** 2, x0 ** 2 + eps ** 2, rtol=0, atol=1e-12)


def test_sparse_rows_take_their_own_step():
    s = NoiseSchedule(1000)
    x0 = torch.ones(5, 8, dtype=torch.float64)
    t = torch.tensor([0, 0, 999, 999, 500])
    xt = s.q_sample(x0, t, torch.zeros_like(x0))
    expect = s.alpha_bar.sqrt()[t][:, None].expand(5, 8)
    torch.testing.assert_close(xt, expect)
    with pytest.raises(ValueError, match="one step per row"):
        s.q_sample(x0, torch.tensor([0, 1]), x0)
    with pytest.raises(ValueError, match=r"\[0, 1000\)"):
        s.q_sample(x0, torch.full((5,), 1000), x0)


@pytest.mark.parametrize("steps", [1, 5, 10, 25, 50, 1000])
def test_ddim_with_a_perfect_denoiser_recovers_the_data(steps):
    s = NoiseSchedule(1000)
    g = torch.Generator().manual_seed(steps)
    data = torch.randn(3, 8, 4, 4, 4, dtype=torch.float64, generator=g)
    noise = torch.randn(data.shape, dtype=torch.float64, generator=g)

    def oracle(x, t):
        # the v that is exactly right for this x_t: eps implied by x_t and the true data
        eps = (x - s.signal(t, x) * data) / s.noise_level(t, x)
        return s.v_target(data, t, eps)

    calls = []
    out = ddim_sample(lambda x, t: (calls.append(t), oracle(x, t))[1], noise, s, steps)
    torch.testing.assert_close(out, data, rtol=0, atol=1e-9)
    assert calls == ddim_timesteps(1000, steps) and len(calls) == steps and calls[0] == 999


def test_ddim_timesteps():
    assert ddim_timesteps(1000, 1) == [999]
    assert ddim_timesteps(1000, 2) == [999, 0]
    ts = ddim_timesteps(1000, 50)
    assert len(ts) == 50 and ts[0] == 999 and ts[-1] == 0 and all(a > b for a, b in zip(ts, ts[1:]))
    assert ddim_timesteps(10, 10) == list(range(9, -1, -1))
    for bad in (0, 1001):
        with pytest.raises(ValueError, match="DDIM steps"):
            ddim_timesteps(1000, bad)


def test_ddim_on_a_gaussian_prior_is_the_exact_flow():
    """Data ~ N(0, sigma^2): the optimal v is linear in x_t, and DDIM's ODE maps x_T ~ N(0, 1) to
    x_0 = sigma x_T * (1 + O(abar_T)); with many steps the sample's std approaches sigma."""
    s = NoiseSchedule(1000)
    sigma = 0.3

    def v_opt(x, t):
        a, b = s.signal(t, x), s.noise_level(t, x)
        # E[x0 | x_t] = a sigma^2 / (a^2 sigma^2 + b^2) x_t; v = (a x_t - x0) / b
        x0 = a * sigma ** 2 / (a ** 2 * sigma ** 2 + b ** 2) * x
        return (a * x - x0) / b

    noise = torch.randn(20000, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    out = ddim_sample(v_opt, noise, s, 200)
    assert float(out.std()) == pytest.approx(sigma, rel=0.03)
