"""The baseline's visual features: a small convolutional beta-VAE of the four views, and its wrapper.

The paper's baseline agent sees a 10-dimensional beta-VAE latent of the cameras instead of keypoints. Here
one encoder takes the four views stacked along the channels (``(N, 12, S, S)``, S = 64 by default) and
gives the mean of a diagonal Gaussian posterior; the decoder reconstructs all four views. The loss is the
Bernoulli (binary cross-entropy) reconstruction summed over pixels plus ``beta`` times the KL divergence to
the unit Gaussian (Higgins et al., 2017). The agent's observation uses the posterior mean.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from s3k.detector import atomic_save, load_torch_file

VIEWS = 4


class BetaVAE(nn.Module):
    """Conv beta-VAE on ``(N, 3 * views, size, size)`` images in [0, 1]; ``size`` a multiple of 16."""

    def __init__(self, latent: int = 10, size: int = 64, views: int = VIEWS, width: int = 32):
        super().__init__()
        if size % 16:
            raise ValueError(f"BetaVAE: size must be a multiple of 16, got {size}")
        self.latent, self.size, self.views = int(latent), int(size), int(views)
        ch = 3 * views
        self.encoder = nn.Sequential(
            nn.Conv2d(ch, width, 4, 2, 1), nn.ReLU(), nn.Conv2d(width, width, 4, 2, 1), nn.ReLU(),
            nn.Conv2d(width, 2 * width, 4, 2, 1), nn.ReLU(),
            nn.Conv2d(2 * width, 2 * width, 4, 2, 1), nn.ReLU(),
            nn.Flatten())
        s = size // 16
        self._shape = (2 * width, s, s)
        flat = 2 * width * s * s
        self.to_stats = nn.Linear(flat, 2 * latent)
        self.from_latent = nn.Linear(latent, flat)
        self.decoder = nn.Sequential(
            nn.ReLU(), nn.ConvTranspose2d(2 * width, 2 * width, 4, 2, 1), nn.ReLU(),
            nn.ConvTranspose2d(2 * width, width, 4, 2, 1), nn.ReLU(),
            nn.ConvTranspose2d(width, width, 4, 2, 1), nn.ReLU(), nn.ConvTranspose2d(width, ch, 4, 2, 1))

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x (N, 3V, S, S)`` -> posterior ``(mean (N, L), log_var (N, L))``."""
        mean, log_var = self.to_stats(self.encoder(x)).chunk(2, dim=1)
        return mean, log_var.clamp(-10.0, 10.0)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """``z (N, L)`` -> reconstruction logits ``(N, 3V, S, S)``."""
        return self.decoder(self.from_latent(z).view(-1, *self._shape))

    def loss(self, x: torch.Tensor, beta: float, generator: torch.Generator | None = None
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """Per-sample mean of reconstruction + beta * KL (reparameterized sample)."""
        mean, log_var = self.encode(x)
        eps = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
        z = mean + torch.exp(0.5 * log_var) * eps
        recon = F.binary_cross_entropy_with_logits(self.decode(z), x, reduction="sum") / x.shape[0]
        kl = 0.5 * (mean.pow(2) + log_var.exp() - 1.0 - log_var).sum() / x.shape[0]
        return recon + beta * kl, {"recon": float(recon.detach()), "kl": float(kl.detach())}


def views_to_tensor(views: np.ndarray) -> torch.Tensor:
    """uint8 ``(..., V, S, S, 3)`` -> float ``(..., 3V, S, S)`` in [0, 1]."""
    x = torch.from_numpy(np.ascontiguousarray(views)).float().div_(255.0)
    x = x.movedim(-1, -3)  # (..., V, 3, S, S)
    return x.reshape(*x.shape[:-4], -1, *x.shape[-2:])


def train_beta_vae(images: np.ndarray, latent: int = 10, beta: float = 4.0, steps: int = 2000,
                   batch_size: int = 32, lr: float = 1e-3, seed: int = 0,
                   log: Callable[[int, float, dict], None] | None = None) -> BetaVAE:
    """Trains a :class:`BetaVAE` on ``images uint8 (N, V, S, S, 3)`` (unlabelled views of the env)."""
    if images.ndim != 5:
        raise ValueError(f"train_beta_vae: images must be (N, V, S, S, 3), got {images.shape}")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    vae = BetaVAE(latent, images.shape[2], images.shape[1])
    opt = torch.optim.Adam(vae.parameters(), lr=lr)
    data = views_to_tensor(images)
    for step in range(steps):
        idx = torch.randint(0, len(data), (batch_size,), generator=gen)
        loss, parts = vae.loss(data[idx], beta, gen)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if log is not None and (step % 100 == 0 or step == steps - 1):
            log(step, float(loss.detach()), parts)
    return vae.eval()


def save_vae(vae: BetaVAE, path: str | Path, beta: float) -> None:
    atomic_save({"model": vae.state_dict(), "latent": vae.latent, "size": vae.size, "views": vae.views,
                 "beta": beta}, path)


def load_vae(path: str | Path) -> BetaVAE:
    state = load_torch_file(path, "beta-VAE", ["model", "latent", "size", "views"])
    vae = BetaVAE(int(state["latent"]), int(state["size"]), int(state["views"]))
    vae.load_state_dict(state["model"])
    return vae.eval()


class LatentObservation(gym.ObservationWrapper):
    """Replaces the keypoints in the insertion env's observation by the beta-VAE latent of its four views.

    The observation is the gripper's state (15) then the latent mean (L). The reward is untouched: it still
    comes from the keypoints, as for the keypoint agent.
    """

    def __init__(self, env: gym.Env, vae: BetaVAE):
        super().__init__(env)
        self.vae = vae
        n = 15 + vae.latent
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (n,), np.float32)
        self.last_state: np.ndarray | None = None

    @torch.no_grad()
    def observation(self, observation: np.ndarray) -> np.ndarray:
        self.last_state = observation  # the keypoint observation, for the demonstrator
        views = self.env.unwrapped.views()[0]  # type: ignore[attr-defined]
        mean, _ = self.vae.encode(views_to_tensor(views)[None])
        return np.concatenate([observation[:15], mean[0].numpy()]).astype(np.float32)
