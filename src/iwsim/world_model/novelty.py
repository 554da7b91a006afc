"""A trust signal: how far a world model's inputs stray from its training data.

A world model is faithful where it was trained. Each step's input, the newest context
latent and the two actions around it, is compared with the training data's inputs by a
Gaussian fitted to them (mean and shrunk covariance): the novelty of a step is the squared
Mahalanobis distance divided by the dimension, about 1 for an input like the training
data's and large for one unlike any of them (a latent the codec never produced, such as a
morphing block, or motions of a kind never seen). An episode's novelty is the mean over
its steps. It is an out-of-distribution score (in the family of Lee et al. 2018, "A
Simple Unified Framework for Detecting Out-of-Distribution Samples"), computed in the
model's own units so that it costs one small matrix product per step:

    nov = fit_novelty(features)              # features (N, D) of the training data
    nov(latents, prev_actions, actions)      # (B,) one value per rollout
"""

from __future__ import annotations

import torch
from torch import nn

SHRINK = 0.01  # covariance shrinkage towards its diagonal: keeps rare directions finite


def novelty_features(latents: torch.Tensor, prev_actions: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """A step's input as one vector: standardised latents (B, C, h, w) and normalised
    actions (B, A), (B, A) -> (B, C*h*w + 2A)."""
    return torch.cat([latents.flatten(1), prev_actions, actions], 1).float()


class Novelty(nn.Module):
    """The Gaussian of the training inputs: ``mean`` (D,) and ``whiten`` (D, D) with
    whiten @ (x - mean) of unit covariance on the training data."""

    mean: torch.Tensor  # buffers
    whiten: torch.Tensor

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("whiten", torch.eye(dim))

    @property
    def dim(self) -> int:
        return self.mean.shape[0]

    def forward(self, latents: torch.Tensor, prev_actions: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """(B,) squared Mahalanobis distance / D of each input (see the module's docstring)."""
        x = novelty_features(latents, prev_actions, actions) - self.mean
        return (x @ self.whiten.T).pow(2).sum(1) / self.dim


def fit_novelty(features: torch.Tensor, shrink: float = SHRINK) -> Novelty:
    """The :class:`Novelty` of training inputs ``features`` (N, D) (:func:`novelty_features`)."""
    x = features.double()
    mean = x.mean(0)
    cov = torch.cov((x - mean).T) if len(x) > 1 else torch.zeros(x.shape[1], x.shape[1], dtype=torch.float64)
    cov = torch.atleast_2d(cov)
    # Shrink the correlations, not the variances (each feature keeps its own scale), and a
    # floor for features that never vary in the data (a step that varies them is novel).
    eye = torch.eye(len(cov), dtype=torch.float64)
    floor = 1e-6 * max(float(cov.diagonal().mean()), 1e-8)
    cov = (1 - shrink) * cov + shrink * torch.diag(cov.diagonal()) + floor * eye
    vals, vecs = torch.linalg.eigh(cov)
    nov = Novelty(x.shape[1])
    nov.mean.copy_(mean.float())
    nov.whiten.copy_((vecs / vals.clamp_min(1e-12).sqrt()).T.float())
    return nov

