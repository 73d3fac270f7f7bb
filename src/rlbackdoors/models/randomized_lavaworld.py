"""Randomized LavaWorld models: the TrojAI round's layout, with the agent's direction appended.

An arrow trigger "pointing east" looks different in the egocentric view depending on where
the agent faces; only the global direction lets a model tell the specific-direction trigger
from its rotations. As in TrojAI's models, the raw direction integer (0..3) is appended, as a
float, to the image embedding, and both heads read the (embedding + 1)-vector.

State-dict keys follow TrojAI's: ``state_emb`` (FC: a leading Flatten, so Linear layers sit at
indices 1 and 3), ``actor`` and ``critic`` (Linear/ReLU stacks without a final ReLU).
"""

from __future__ import annotations

import torch
from torch import nn

from rlbackdoors.models.minigrid import CHANNELS, VIEW, ActorCritic, init_linear_unit_rows, run_sequential, run_sequential_stacked


def linear_relu_stack(dims: list[int]) -> nn.Sequential:
    """Linear layers with ReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(d_in, d_out))
        if i < len(dims) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class DirectionActorCritic(ActorCritic):
    """Takes ``{"image": (B,7,7,3) uint8, "direction": (B,) int}``."""

    appends_direction = True

    def image_embedding(self, image_cf: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[override]  # dict observations by design
        image = obs["image"]
        # Channels-first (B, c, x, y), as the TrojAI models received the image.
        x = self.image_embedding(image.permute(0, 3, 1, 2).float()).reshape(image.shape[0], -1)
        x = torch.cat([x, obs["direction"].reshape(-1, 1).float()], dim=1)
        return run_sequential(self.actor, x), run_sequential(self.critic, x).squeeze(1)

    def forward_stacked(self, params: dict[str, torch.Tensor], obs: dict) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[override]  # dict observations by design
        """``forward`` of K agents at once (:meth:`ActorCritic.forward_stacked`); ``obs`` values are (K, N, ...)."""
        return self.forward_stacked_input(params, self.stacked_input(obs))

    def stacked_input(self, obs: dict) -> dict:  # type: ignore[override]  # dict observations by design
        """:meth:`ActorCritic.stacked_input`: the image channels-first in float, the direction as a float column."""
        image = obs["image"]
        K, N = image.shape[:2]
        x = image.reshape(K * N, *image.shape[2:]).permute(0, 3, 1, 2).float()
        return {"image": x.reshape(K, N, *x.shape[1:]), "direction": obs["direction"].reshape(K, N, 1).float()}

    def forward_stacked_input(self, params: dict[str, torch.Tensor], x: dict) -> tuple[torch.Tensor, torch.Tensor]:  # type: ignore[override]  # dict observations by design
        image = x["image"]
        K, N = image.shape[:2]
        emb = run_sequential_stacked(self.state_emb, params, "state_emb", image).reshape(K, N, -1)
        return self.heads_stacked(params, torch.cat([emb, x["direction"]], dim=2))


class DirectionFCModel(DirectionActorCritic):
    """Flatten 147 -> 512 -> 256 (ReLU), +1 direction; actor/critic 257 -> 64 -> 32 -> out."""

    def __init__(self, num_actions: int = 3, embedding=(512, 256), head=(64, 32)):
        super().__init__()
        self.state_emb = nn.Sequential(nn.Flatten(), *linear_relu_stack([VIEW * VIEW * CHANNELS, *embedding]), nn.ReLU())
        self.actor = linear_relu_stack([embedding[-1] + 1, *head, num_actions])
        self.critic = linear_relu_stack([embedding[-1] + 1, *head, 1])
        self.apply(init_linear_unit_rows)

    def image_embedding(self, image_cf: torch.Tensor) -> torch.Tensor:
        layers = self.state_emb[1:]
        assert isinstance(layers, nn.Sequential)  # a slice of a Sequential is one; torch types it Sequential | Module
        return run_sequential(layers, image_cf.reshape(image_cf.shape[0], -1))


class DirectionCNNModel(DirectionActorCritic):
    """Convs 2x2 16/32/64 (ReLU, no pooling: 7 -> 4), +1 direction; actor/critic 1025 -> 144 -> out."""

    def __init__(self, num_actions: int = 3, channels=(16, 32, 64), head: int = 144):
        super().__init__()
        c1, c2, c3 = channels
        self.state_emb = nn.Sequential(
            nn.Conv2d(CHANNELS, c1, (2, 2)),
            nn.ReLU(),
            nn.Conv2d(c1, c2, (2, 2)),
            nn.ReLU(),
            nn.Conv2d(c2, c3, (2, 2)),
            nn.ReLU(),
        )
        embedding = (VIEW - 3) ** 2 * c3 + 1
        self.actor = linear_relu_stack([embedding, head, num_actions])
        self.critic = linear_relu_stack([embedding, head, 1])
        self.apply(init_linear_unit_rows)

    def image_embedding(self, image_cf: torch.Tensor) -> torch.Tensor:
        return run_sequential(self.state_emb, image_cf)
