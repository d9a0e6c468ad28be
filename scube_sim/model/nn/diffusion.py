"""Gaussian diffusion on latents with the v-parameterisation and DDIM sampling (the geometry stage's
latent diffusion, paper appendix C: 1000 steps, linear noise schedule).

Forward process: x_t = sqrt(abar_t) x_0 + sqrt(1 - abar_t) eps, with abar_t = prod_{s <= t} (1 - beta_s)
and beta linear from `beta_start` to `beta_end` over the steps (Ho et al. 2020; t = 0 .. steps - 1).
The network predicts v = sqrt(abar_t) eps - sqrt(1 - abar_t) x_0 (Salimans & Ho 2022), from which

    x_0 = sqrt(abar_t) x_t - sqrt(1 - abar_t) v,     eps = sqrt(1 - abar_t) x_t + sqrt(abar_t) v.

Latents are any tensor whose first dimension is the row the timestep belongs to: a dense batch
(B, C, X, Y, Z) with t (B,), or a sparse latent's features (N, C) with t (N,) per site (the
site's sample's t). DDIM (Song et al. 2021, eta = 0) walks a subsequence of the training steps;
with a perfect v the sampler returns x_0 exactly whatever the number of steps.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

__all__ = ["NoiseSchedule", "ddim_sample", "ddim_timesteps"]


class NoiseSchedule:
    """The linear beta schedule of `steps` steps and its derived quantities (float64 tables)."""

    def __init__(self, steps: int = 1000, beta_start: float = 1e-4, beta_end: float = 2e-2):
        if steps < 1:
            raise ValueError(f"steps: expected >= 1, got {steps}")
        if not 0.0 < beta_start <= beta_end < 1.0:
            raise ValueError(f"expected 0 < beta_start <= beta_end < 1, got {beta_start}, {beta_end}")
        self.steps = int(steps)
        self.betas = torch.linspace(beta_start, beta_end, steps, dtype=torch.float64)
        self.alpha_bar = torch.cumprod(1.0 - self.betas, 0)

    def _coef(self, table: torch.Tensor, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """table[t] shaped to broadcast over x's trailing dims, in x's dtype."""
        t = torch.as_tensor(t, dtype=torch.int64)
        if t.ndim == 0:
            t = t.expand(x.shape[0])
        if t.shape[0] != x.shape[0]:
            raise ValueError(f"t: expected one step per row of x ({x.shape[0]}), got {tuple(t.shape)}")
        if bool(((t < 0) | (t >= self.steps)).any()):
            raise ValueError(f"t: expected steps in [0, {self.steps}), got {t.min().item()}..{t.max().item()}")
        return table[t].to(x.dtype).reshape(-1, *([1] * (x.ndim - 1)))

    def signal(self, t, x):
        """sqrt(abar_t), broadcast over x."""
        return self._coef(self.alpha_bar.sqrt(), t, x)

    def noise_level(self, t, x):
        """sqrt(1 - abar_t), broadcast over x."""
        return self._coef((1.0 - self.alpha_bar).sqrt(), t, x)

    def q_sample(self, x0: torch.Tensor, t, noise: torch.Tensor) -> torch.Tensor:
        """x_t given x_0, the step per row and the noise (same shape as x_0)."""
        return self.signal(t, x0) * x0 + self.noise_level(t, x0) * noise

    def v_target(self, x0: torch.Tensor, t, noise: torch.Tensor) -> torch.Tensor:
        """The network's target v = sqrt(abar) eps - sqrt(1 - abar) x_0."""
        return self.signal(t, x0) * noise - self.noise_level(t, x0) * x0

    def x0_from_v(self, xt: torch.Tensor, t, v: torch.Tensor) -> torch.Tensor:
        return self.signal(t, xt) * xt - self.noise_level(t, xt) * v

    def eps_from_v(self, xt: torch.Tensor, t, v: torch.Tensor) -> torch.Tensor:
        return self.noise_level(t, xt) * xt + self.signal(t, xt) * v


def ddim_timesteps(train_steps: int, steps: int) -> list[int]:
    """The `steps` training steps DDIM visits, from the noisiest (train_steps - 1) down to 0 (one
    step: the noisiest alone), evenly spaced and distinct; 1 <= steps <= train_steps."""
    if not 1 <= steps <= train_steps:
        raise ValueError(f"DDIM steps: expected 1 .. {train_steps}, got {steps}")
    ts = np.round(np.linspace(train_steps - 1, 0, steps)).astype(np.int64) if steps > 1 else [train_steps - 1]
    return [int(t) for t in ts]


def ddim_sample(v_fn: Callable[[torch.Tensor, int], torch.Tensor], noise: torch.Tensor, schedule: NoiseSchedule,
                steps: int, progress: Callable[[int], None] | None = None) -> torch.Tensor:
    """Deterministic DDIM (eta = 0) from x_T = `noise` to x_0 in `steps` network calls.

    v_fn(x_t, t) -> v for every row at step t (an int; the caller broadcasts it). Each step takes
    x_0 and eps from v and moves to the next visited step: x_s = sqrt(abar_s) x_0 + sqrt(1 - abar_s)
    eps; after the last step (t = 0 when steps > 1) it returns the x_0 estimate."""
    ts = ddim_timesteps(schedule.steps, steps)
    x = noise
    x0 = noise
    for i, t in enumerate(ts):
        v = v_fn(x, t)
        x0 = schedule.x0_from_v(x, t, v)
        if i + 1 == len(ts):
            break
        eps = schedule.eps_from_v(x, t, v)
        s = ts[i + 1]
        x = schedule.signal(s, x) * x0 + schedule.noise_level(s, x) * eps
        if progress is not None:
            progress(i + 1)
    if progress is not None:
        progress(len(ts))
    return x0
