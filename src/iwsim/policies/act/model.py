"""ACT, Action Chunking with Transformers (Zhao et al. 2023, "Learning Fine-Grained
Bimanual Manipulation with Low-Cost Hardware"), small enough to train on a CPU.

The current image goes through a CNN trained from scratch; every cell of its feature map
is a token, with DETR's 2D sine position embedding (the paper uses ResNet-18 cells); or,
with ``image_tokens="keypoints"``, every spatial-softmax keypoint of the map is a token made
from its (x, y) by its own linear map (Diffusion Policy's pooling, which reads positions
finer than a cell). With several camera views the one CNN reads each view (one backbone
for all cameras, as LeRobot's ACT and the original code's ``backbones[0]``) and every
view's tokens join the sequence, each view's positions its cells' plus a learned embedding
of the view (the original gives every camera's cells the same 2D positions, so attention
cannot tell the views apart). A transformer encoder reads ``[z, agent_pos, image tokens]``; a
decoder with ``chunk_size`` learned queries cross-attends to it and regresses the next
``k`` actions at once.

Training is a CVAE (the paper's Sec. IV-A, Fig. 4): a small transformer over
``[CLS, agent_pos, action chunk]`` gives q(z | actions, agent_pos), z is drawn by
reparameterisation, and the loss is L1 + kl_weight * KL(q || N(0, I)). At inference
z = 0, the prior's mean.

Execution (Sec. IV-B, Algorithm 2): with temporal ensembling the policy is queried every
step and returns one action, the weighted average of every prediction made so far for
the current step, w_i = exp(-m * i) with w_0 the oldest; without it, the first
``n_action_steps`` actions of each chunk.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from iwsim.core.errors import InputError
from iwsim.policies.act.config import ACTConfig
from iwsim.policies.common import (
    ImageEncoder,
    Normalizer,
    Policy,
    PolicyBatch,
    SpatialSoftmax,
    prepare_obs,
)


def sinusoid(pos: torch.Tensor, dim: int) -> torch.Tensor:
    """Positions (N,) -> (N, dim): sin/cos interleaved at frequencies 10000^(-2j/dim)
    (Vaswani et al. 2017, Sec. 3.5), as ACT's tables."""
    j = torch.arange(dim, device=pos.device) // 2 * 2
    angle = pos.float()[:, None] * 10000 ** (-j / dim)
    return torch.where(torch.arange(dim, device=pos.device) % 2 == 0, angle.sin(), angle.cos())


def sine_2d(h: int, w: int, dim: int, device: torch.device) -> torch.Tensor:
    """DETR's 2D sine embedding of an h x w feature map -> (h * w, dim), row-major: half
    the channels encode the row, half the column, positions scaled to (0, 2 pi]."""
    rows = sinusoid((torch.arange(h, device=device) + 1) / h * 2 * math.pi, dim // 2)  # (h, dim/2)
    cols = sinusoid((torch.arange(w, device=device) + 1) / w * 2 * math.pi, dim // 2)  # (w, dim/2)
    return torch.cat([rows[:, None].expand(h, w, -1), cols[None].expand(h, w, -1)], -1).reshape(h * w, dim)


class EncoderLayer(nn.Module):
    """DETR's post-norm layer: positions are added to queries and keys in every layer,
    never to the values."""

    def __init__(self, cfg: ACTConfig) -> None:
        super().__init__()
        self.attn = nn.MultiheadAttention(cfg.dim, cfg.heads, dropout=cfg.dropout, batch_first=True)
        self.ff = nn.Sequential(nn.Linear(cfg.dim, cfg.ff_dim), nn.ReLU(), nn.Dropout(cfg.dropout),
                                nn.Linear(cfg.ff_dim, cfg.dim))
        self.norm1, self.norm2 = nn.LayerNorm(cfg.dim), nn.LayerNorm(cfg.dim)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor, pos: torch.Tensor, pad: torch.Tensor | None = None) -> torch.Tensor:
        """x (B, N, D), pos (1 or B, N, D), pad (B, N) True where ignored -> (B, N, D)."""
        q = x + pos
        x = self.norm1(x + self.drop(self.attn(q, q, x, key_padding_mask=pad, need_weights=False)[0]))
        return self.norm2(x + self.drop(self.ff(x)))


class DecoderLayer(nn.Module):
    """DETR's post-norm decoder layer: self-attention among the queries, then
    cross-attention to the encoder's tokens."""

    def __init__(self, cfg: ACTConfig) -> None:
        super().__init__()
        self.self_attn = nn.MultiheadAttention(cfg.dim, cfg.heads, dropout=cfg.dropout, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(cfg.dim, cfg.heads, dropout=cfg.dropout, batch_first=True)
        self.ff = nn.Sequential(nn.Linear(cfg.dim, cfg.ff_dim), nn.ReLU(), nn.Dropout(cfg.dropout),
                                nn.Linear(cfg.ff_dim, cfg.dim))
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(cfg.dim), nn.LayerNorm(cfg.dim), nn.LayerNorm(cfg.dim)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor, query_pos: torch.Tensor, memory: torch.Tensor, memory_pos: torch.Tensor
                ) -> torch.Tensor:
        """x (B, k, D), query_pos (1, k, D), memory (B, N, D), memory_pos (1, N, D) -> (B, k, D)."""
        q = x + query_pos
        x = self.norm1(x + self.drop(self.self_attn(q, q, x, need_weights=False)[0]))
        x = self.norm2(x + self.drop(self.cross_attn(x + query_pos, memory + memory_pos, memory,
                                                     need_weights=False)[0]))
        return self.norm3(x + self.drop(self.ff(x)))


class TemporalEnsemble:
    """The paper's temporal ensembling (Sec. IV-B, Algorithm 2), per batch item.

    Every query predicts actions for steps t .. t+k-1. The action for step t is the average
    of all predictions made for it, the i-th oldest weighted w_i = exp(-m * i) (w_0 the
    oldest; m > 0 favours old predictions, m = 0 is a plain mean), normalised to sum 1.
    Each prediction's weight is fixed when it arrives, so unnormalised sums suffice.
    """

    def __init__(self, m: float, chunk_size: int) -> None:
        self.m, self.chunk_size = m, chunk_size
        self.reset()

    def reset(self) -> None:
        self.sums: torch.Tensor | None = None  # (B, k, A): weighted sums for steps t .. t+k-1
        self.weights: torch.Tensor | None = None  # (k,): their total weights
        self.counts: torch.Tensor | None = None  # (k,): predictions made so far for each step

    def update(self, chunk: torch.Tensor) -> torch.Tensor:
        """Add the chunk (B, k, A) predicted at the current step; return the ensembled
        action (B, A) for it and advance one step."""
        b, k, a = chunk.shape
        if k != self.chunk_size:
            raise InputError(f"expected chunks of {self.chunk_size} actions, got {k}.")
        if self.sums is None:
            self.sums = chunk.new_zeros(b, k, a)
            self.weights = chunk.new_zeros(k)
            self.counts = torch.zeros(k, dtype=torch.long, device=chunk.device)
        elif self.sums.shape[0] != b or self.sums.shape[2] != a:
            raise InputError(f"the ensemble holds {self.sums.shape[0]} episodes of {self.sums.shape[2]}-D actions, "
                             f"got a chunk {tuple(chunk.shape)}; call reset() when episodes start.")
        assert self.weights is not None and self.counts is not None  # set with sums
        w = torch.exp(-self.m * self.counts.to(chunk.dtype))  # (k,): w_i, i = predictions already made
        self.sums = self.sums + w[:, None] * chunk
        self.weights = self.weights + w
        self.counts = self.counts + 1
        action = self.sums[:, 0] / self.weights[0]
        # Step t is done; step t+k has no predictions yet.
        self.sums = torch.cat([self.sums[:, 1:], chunk.new_zeros(b, 1, a)], 1)
        self.weights = torch.cat([self.weights[1:], chunk.new_zeros(1)])
        self.counts = torch.cat([self.counts[1:], self.counts.new_zeros(1)])
        return action


class ACTPolicy(Policy):
    """See the module docstring; the execution contract is in :mod:`iwsim.policies.common`."""

    def __init__(self, cfg: ACTConfig, action_norm: Normalizer, state_norm: Normalizer) -> None:
        super().__init__(cfg, action_norm, state_norm)
        d, k = cfg.dim, cfg.chunk_size
        # Observation side. Cells: the trunk's last 1x1 conv maps to d channels (ACT's input_proj).
        # Keypoints: it maps to K maps, each pooled to its expected (x, y), a token by its own linear map.
        keypoints = cfg.image_tokens == "keypoints"
        self.backbone = ImageEncoder(channels=cfg.encoder_channels, keypoints=cfg.keypoints if keypoints else d,
                                     first_stride=cfg.encoder_stride).net
        if keypoints:
            self.pool = SpatialSoftmax()
            self.keypoint_weight = nn.Parameter(torch.randn(cfg.keypoints, 2, d) / math.sqrt(2))
            self.keypoint_bias = nn.Parameter(torch.randn(cfg.keypoints, d) * 0.02)  # also tells the keypoints apart
            self.keypoint_pos = nn.Embedding(cfg.keypoints, d)
        if len(cfg.cameras) > 1:  # (one view: the weights of before views, no such embedding)
            self.view_pos = nn.Embedding(len(cfg.cameras), d)  # added to the positions of each view's tokens
        self.state_proj = nn.Linear(self.state_dim, d)
        self.latent_proj = nn.Linear(cfg.latent_dim, d)
        self.token_pos = nn.Embedding(2, d)  # learned positions of the [z, agent_pos] tokens
        self.encoder = nn.ModuleList(EncoderLayer(cfg) for _ in range(cfg.enc_layers))
        # DETR-style decoder: zero inputs, k learned query positions. All layers are used (the
        # original code, by a bug, used only the first; tonyzhaozh/act issue 25).
        self.query_pos = nn.Embedding(k, d)
        self.decoder = nn.ModuleList(DecoderLayer(cfg) for _ in range(cfg.dec_layers))
        self.decoder_norm = nn.LayerNorm(d)
        self.action_head = nn.Linear(d, self.action_dim)
        # CVAE encoder q(z | actions, agent_pos): BERT-like, the CLS output gives (mu, log sigma^2).
        self.cvae_cls = nn.Embedding(1, d)
        self.cvae_state_proj = nn.Linear(self.state_dim, d)
        self.cvae_action_proj = nn.Linear(self.action_dim, d)
        self.cvae_encoder = nn.ModuleList(EncoderLayer(cfg) for _ in range(cfg.vae_layers))
        self.cvae_out = nn.Linear(d, 2 * cfg.latent_dim)
        self.register_buffer("cvae_pos", sinusoid(torch.arange(2 + k), d)[None], persistent=False)  # (1, 2+k, D)
        for p in (*self.encoder.parameters(), *self.decoder.parameters(), *self.cvae_encoder.parameters()):
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)  # as DETR's and ACT's transformers
        self.ensemble = TemporalEnsemble(cfg.temporal_ensemble, k) if cfg.temporal_ensemble is not None else None

    def posterior(self, agent_pos: torch.Tensor, action: torch.Tensor, is_pad: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """q(z | ...): agent_pos (B, S), action (B, k, A) normalised, is_pad (B, k) ->
        mu, log sigma^2, each (B, L). Padded actions are masked out of the attention."""
        b = action.shape[0]
        tokens = torch.cat([self.cvae_cls.weight.expand(b, 1, -1), self.cvae_state_proj(agent_pos)[:, None],
                            self.cvae_action_proj(action)], 1)  # (B, 2+k, D)
        pad = torch.cat([is_pad.new_zeros(b, 2), is_pad], 1)  # (B, 2+k)
        for layer in self.cvae_encoder:
            tokens = layer(tokens, self.cvae_pos, pad)
        mu, logvar = self.cvae_out(tokens[:, 0]).chunk(2, -1)
        return mu, logvar

    def decode(self, image: torch.Tensor, agent_pos: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """image (B, 3V, H, W) in [-1, 1] (V views stacked along the channels), agent_pos
        (B, S) normalised, z (B, L) -> normalised action chunk (B, k, A)."""
        if not self.cfg.observe_state:
            agent_pos = torch.zeros_like(agent_pos)  # the token stays, carrying no information
        b, d, views = image.shape[0], self.cfg.dim, self.views
        feat = self.backbone(image.unflatten(1, (views, 3)).flatten(0, 1))  # (B * V, D or K, h, w): one shared CNN
        if self.cfg.image_tokens == "keypoints":
            xy = self.pool(feat).view(b * views, 2, -1).transpose(1, 2)  # (B * V, K, 2)
            cells = torch.einsum("bkc,kcd->bkd", xy, self.keypoint_weight) + self.keypoint_bias
            cell_pos = self.keypoint_pos.weight
        else:
            h, w = feat.shape[2:]
            cells, cell_pos = feat.flatten(2).transpose(1, 2), sine_2d(h, w, d, feat.device)
        if views > 1:  # every view's tokens in the sequence, view after view, told apart by their view's embedding
            cells = cells.reshape(b, views * cells.shape[1], d)
            cell_pos = (cell_pos[None] + self.view_pos.weight[:, None]).flatten(0, 1)  # (V * N, D)
        tokens = torch.cat([self.latent_proj(z)[:, None], self.state_proj(agent_pos)[:, None], cells], 1)
        pos = torch.cat([self.token_pos.weight, cell_pos])[None]  # (1, 2 + cells, D)
        for layer in self.encoder:
            tokens = layer(tokens, pos)
        x = tokens.new_zeros(b, self.cfg.chunk_size, d)
        for layer in self.decoder:
            x = layer(x, self.query_pos.weight[None], tokens, pos)
        return self.action_head(self.decoder_norm(x))

    def _check_batch(self, batch: PolicyBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The batch's current image (B, 3V, H, W), agent_pos (B, S), and its first k
        actions (B, k, A) and padding (B, k)."""
        image, pos, action, pad = batch.image, batch.agent_pos, batch.action, batch.action_is_pad
        c = 3 * self.views
        if image.ndim != 5 or image.shape[1:3] != (1, c) or pos.shape[1:] != (1, self.state_dim):
            raise InputError(f"expected image (B, 1, {c}, H, W) and agent_pos (B, 1, {self.state_dim}), got "
                             f"{tuple(image.shape)} and {tuple(pos.shape)}.")
        k = self.cfg.chunk_size
        if (action.ndim != 3 or action.shape[1] < k or action.shape[2] != self.action_dim
                or pad.shape != action.shape[:2]):
            raise InputError(f"expected action (B, >={k}, {self.action_dim}) and action_is_pad (B, >={k}), got "
                             f"{tuple(action.shape)} and {tuple(pad.shape)}.")
        return image[:, 0], pos[:, 0], action[:, :k], pad[:, :k]

    def forward(self, batch: PolicyBatch) -> tuple[torch.Tensor, dict[str, float]]:
        """The CVAE loss of a batch (see :class:`PolicyBatch`): L1 over the non-padded
        actions + kl_weight * KL(q(z | actions, agent_pos) || N(0, I))."""
        image, pos, action, pad = self._check_batch(batch)
        mu, logvar = self.posterior(pos, action, pad)
        z = mu + (0.5 * logvar).exp() * torch.randn_like(mu)  # reparameterisation (Kingma & Welling 2014)
        pred = self.decode(image, pos, z)
        # Mean over real actions only (the original code divides by all k actions, pads included).
        valid = (~pad)[..., None].to(pred.dtype)  # (B, k, 1)
        l1 = ((pred - action).abs() * valid).sum() / (valid.sum() * self.action_dim).clamp(min=1)
        # KL of a diagonal Gaussian from N(0, I), summed over z's dimensions, mean over the batch.
        kl = (-0.5 * (1 + logvar - mu.pow(2) - logvar.exp())).sum(-1).mean()
        return l1 + self.cfg.kl_weight * kl, {"l1": l1.item(), "kl": kl.item()}

    @torch.no_grad()
    def predict_chunk(self, obs: dict) -> torch.Tensor:
        """The whole chunk (B, k, A) in the data's units for the observation (see
        :mod:`iwsim.policies.common`), with z = 0 and dropout off; no state is kept."""
        image, pos = prepare_obs(obs, self.state_norm, self.cfg.obs_horizon, self.cameras)
        was_training = self.training
        self.eval()
        try:
            z = pos.new_zeros(pos.shape[0], self.cfg.latent_dim)
            chunk = self.decode(image[:, 0], pos[:, 0], z)
        finally:
            self.train(was_training)
        # Training targets lie in [-1, 1] by min-max construction: keep targets in the demonstrated range.
        return self.to_absolute(self.action_norm.unnormalize(chunk.clamp(-1, 1)), obs)

    def reset(self) -> None:
        """Forget the ensembled predictions: call when an episode starts."""
        if self.ensemble is not None:
            self.ensemble.reset()

    @torch.no_grad()
    def predict_action(self, obs: dict) -> np.ndarray:
        """The actions (B, Ta, A) to execute next, in the data's units: Ta = 1, the
        ensembled action, with temporal ensembling; else the chunk's first n_action_steps."""
        chunk = self.predict_chunk(obs)
        if self.ensemble is None:
            return chunk[:, :self.cfg.n_action_steps].cpu().numpy()
        return self.ensemble.update(chunk)[:, None].cpu().numpy()
