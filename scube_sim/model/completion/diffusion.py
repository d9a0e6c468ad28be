"""The paper's prior as the completion (issue 45's option): latent diffusion over the frozen coarse
structure VAE (`geometry-vae-coarse-cpu`: 0.8 m grid, latent at a quarter of it), conditioned on
the evidence grid (`features`) instead of lifted image features.

Training: the ground truth's grid is encoded by the frozen VAE (posterior mean / latent_std, as the
geometry stage's diffusion); a step t is drawn per item, the latent noised, and the denoiser
(`geometry.dense_nets.Denoiser3d`) predicts v from the noisy latent, the step and the condition:
the evidence channels the config names, brought to the latent's resolution by strided
convolutions (`EvidenceEncoder`). Loss: MSE to v.

Inference (`forward`): DDIM from noise seeded by `seed` (the same evidence, the same grid), the
latent decoded by the VAE; per cell the occupancy probability is the product of the sigmoids of
the cell and of its ancestors at the decoder's coarser levels (the VAE's pruning, soft), handed
back as a logit with the label logits: the deterministic network's interface, so the merge and the
scores treat both alike.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from pydantic import Field, model_validator
from torch import nn
from torch.nn import functional as F

from ...config import StrictModel
from ...errors import InputError
from ..geometry.dense_nets import Denoiser3d, ResBlock3d, StructureVAE, VAEConfig
from ..nn.diffusion import NoiseSchedule, ddim_sample
from .features import FEATURES

__all__ = ["CompletionDiffusion", "CompletionDiffusionNet"]

LOGIT_EPS = 1e-6


class CompletionDiffusion(StrictModel):
    """vae_checkpoint: the coarse structure VAE (frozen; path or shipped name) and `vae` its
    architecture; cond_channels: the condition's channels at the latent's resolution; widths,
    blocks, groups: the denoiser's U-Net (level 0 at the latent's resolution); the schedule:
    `train_steps` linear steps from beta_start to beta_end, `sample_steps` DDIM steps at inference,
    from noise seeded by `seed`."""

    vae_checkpoint: str = "geometry-vae-coarse-cpu"
    vae: VAEConfig = Field(default_factory=lambda: VAEConfig(widths=[16, 64], blocks=1, latent_channels=8,
                                                             kl_weight=1e-4, groups=8, child_kernel=3))
    cond_channels: int = Field(default=32, ge=1, le=512)
    widths: tuple[int, ...] = Field(default=(32, 64, 96), min_length=1, max_length=4)
    blocks: int = Field(default=1, ge=1, le=4)
    groups: int = Field(default=8, ge=1, le=32)
    train_steps: int = Field(default=1000, ge=1)
    beta_start: float = Field(default=1e-4, gt=0)
    beta_end: float = Field(default=2e-2, gt=0)
    sample_steps: int = Field(default=10, ge=1)
    seed: int = 0

    @property
    def level(self) -> str:
        return "coarse"  # `geometry.stage.frozen_vae` checks the VAE's level

    @model_validator(mode="after")
    def _check(self):
        if self.sample_steps > self.train_steps:
            raise ValueError(f"sample_steps ({self.sample_steps}) cannot exceed train_steps ({self.train_steps})")
        return self


class EvidenceEncoder(nn.Module):
    """(B, C_in, X, Y, Z) evidence -> (B, out, X / stride, Y / stride, Z / stride): a convolution
    and a residual block at the grid's resolution, then a strided convolution and a residual
    block per halving."""

    def __init__(self, cin: int, out: int, stride: int, groups: int):
        super().__init__()
        if stride < 1 or stride & (stride - 1):
            raise ValueError(f"EvidenceEncoder: stride must be a power of two, got {stride}")
        width = max(8, out // 2)
        layers: list[nn.Module] = [nn.Conv3d(cin, width, 3, padding=1), ResBlock3d(width, width, groups)]
        c = width
        while stride > 1:
            layers += [nn.Conv3d(c, out, 3, stride=2, padding=1), ResBlock3d(out, out, groups)]
            c, stride = out, stride // 2
        if c != out:
            layers.append(nn.Conv3d(c, out, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class CompletionDiffusionNet(nn.Module):
    """(B, len(FEATURES), X, Y, Z) -> (occupancy logits (B, X, Y, Z), label logits (B, NUM_LABELS,
    X, Y, Z)) by DDIM over the frozen VAE's latent (module docstring); X, Y, Z divisible by the
    VAE's stride times 2 ** (len(widths) - 1). `cfg` is the `CompletionModel` (its `features`
    and `diffusion`); load_vae: (name, diffusion config) -> the trained VAE or None (a checkpoint
    of this network holds the VAE's weights)."""

    def __init__(self, cfg, load_vae: Callable | None = None):
        super().__init__()
        if cfg.diffusion is None:
            raise ValueError("CompletionDiffusionNet: the model config has no diffusion section")
        self.cfg = cfg
        d = cfg.diffusion
        self.inputs = [FEATURES.index(f) for f in cfg.features]
        self.vae = StructureVAE(d.vae)
        self.vae_loaded = False
        if load_vae is not None:
            trained = load_vae(d.vae_checkpoint, d)
            if trained is not None:
                self.vae.load_state_dict(trained.state_dict())
                self.vae_loaded = True
        for p in self.vae.parameters():
            p.requires_grad_(False)
        self.encoder = EvidenceEncoder(len(self.inputs), d.cond_channels, self.vae.stride, d.groups)
        self.denoiser = Denoiser3d(d.vae.latent_channels, d.cond_channels, tuple(d.widths), d.blocks, d.groups)
        self.schedule = NoiseSchedule(d.train_steps, d.beta_start, d.beta_end)

    def train(self, mode: bool = True):
        super().train(mode)
        self.vae.eval()  # frozen: no running statistics move
        return self

    @property
    def multiple(self) -> int:
        """The box's sides must be multiples of this."""
        return self.vae.stride * 2 ** (len(self.cfg.diffusion.widths) - 1)

    def _check(self, x: torch.Tensor) -> None:
        if x.ndim != 5 or x.shape[1] != len(FEATURES):
            raise ValueError(f"CompletionDiffusionNet: expected (B, {len(FEATURES)}, X, Y, Z), got {tuple(x.shape)}")
        if any(s % self.multiple for s in x.shape[2:]):
            raise ValueError(f"CompletionDiffusionNet: box {tuple(x.shape[2:])} not divisible by {self.multiple}")

    def loss(self, features: torch.Tensor, occupancy: torch.Tensor, labels: torch.Tensor,
             generator: torch.Generator | None = None) -> torch.Tensor:
        """v-MSE of one batch: features (B, len(FEATURES), X, Y, Z), the truth's occupancy (B, X, Y,
        Z) float and labels (B, X, Y, Z) (-1 empty)."""
        self._check(features)
        if not self.vae_loaded:
            raise InputError(f"model.diffusion.vae_checkpoint {self.cfg.diffusion.vae_checkpoint!r}: not found; "
                             f"the completion's diffusion needs the trained coarse structure VAE")
        with torch.no_grad():
            mu, _ = self.vae.encode(occupancy, labels)
            x0 = mu / self.vae.latent_std
        cond = self.encoder(features[:, self.inputs])
        t = torch.randint(0, self.schedule.steps, (x0.shape[0],), generator=generator)
        noise = torch.randn(x0.shape, generator=generator)
        v = self.denoiser(self.schedule.q_sample(x0, t, noise), cond, t)
        return F.mse_loss(v, self.schedule.v_target(x0, t, noise))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        self._check(x)
        d = self.cfg.diffusion
        cond = self.encoder(x[:, self.inputs])
        shape = (x.shape[0], d.vae.latent_channels, *cond.shape[2:])
        noise = torch.randn(shape, generator=torch.Generator().manual_seed(int(d.seed)))
        z = ddim_sample(lambda xt, t: self.denoiser(xt, cond, torch.full((xt.shape[0],), t)), noise, self.schedule,
                        d.sample_steps)
        occ_levels, occ_final, lab = self.vae.decode(z * self.vae.latent_std)
        logp = F.logsigmoid(occ_final)
        for logits in occ_levels:  # each ancestor's probability, spread over its children
            s = occ_final.shape[-1] // logits.shape[-1]
            up = logits.repeat_interleave(s, 1).repeat_interleave(s, 2).repeat_interleave(s, 3)
            logp = logp + F.logsigmoid(up)
        p = logp.exp().clamp(LOGIT_EPS, 1 - LOGIT_EPS)
        return torch.log(p) - torch.log1p(-p), lab
