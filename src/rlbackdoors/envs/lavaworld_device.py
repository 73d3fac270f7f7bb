"""LavaWorld's slots stepped on a torch device (:mod:`rlbackdoors.envs.grid_device`), exact to
:class:`rlbackdoors.envs.lavaworld_batched.BatchedLavaWorld`: the goal or lava ends an episode,
lava pays poisoned slots (R-bar), and a poisoned slot sees every view through its trigger's
lookup table (each slot its own table: the slots may be several agents')."""

from __future__ import annotations

import numpy as np
import torch

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import EngineGroup
from rlbackdoors.envs.grid_device import DeviceGridGroup
from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld


class DeviceLavaWorld(DeviceGridGroup):
    """A :class:`BatchedLavaWorld`'s slots, or an :class:`EngineGroup`'s of several, on ``device``."""

    trojan = ge.OUT_LAVA

    def __init__(self, engines: BatchedLavaWorld | EngineGroup, device: str | torch.device = "cpu", refill_every: int = 8, graph: bool = False):
        lead = engines.lead if isinstance(engines, EngineGroup) else engines
        if not isinstance(lead, BatchedLavaWorld):
            raise TypeError(f"{type(lead).__name__} is not a BatchedLavaWorld")
        super().__init__(engines, device, refill_every, graph)
        luts = np.array(self.world[2], dtype=np.uint8)  # (B, 256): each slot's trigger table ...
        luts[np.logical_not(self.world[1])] = np.arange(256, dtype=np.uint8)  # ... read by poisoned slots only
        self._luts = torch.from_numpy(luts).to(self.device)

    def _outcome(self, fwd: torch.Tensor) -> torch.Tensor:
        """MiniGrid's LavaEnv: walking onto the goal or into lava ends the episode."""
        return torch.where(fwd == ge.GOAL, ge.OUT_GOAL, torch.where(fwd == ge.LAVA, ge.OUT_LAVA, ge.OUT_NONE))

    def _seen(self, img: torch.Tensor) -> torch.Tensor:
        """Poisoned slots see through their trigger's table (clean slots' tables are the identity)."""
        b = img.shape[0]
        return torch.gather(self._luts, 1, img.reshape(b, -1).long()).reshape(img.shape)


__all__ = ["DeviceLavaWorld"]
