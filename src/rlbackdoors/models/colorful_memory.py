"""CNN-GRU actor-critics for Colorful Memory (SPEC §3): the LavaWorld CNN embedding, then two
unidirectional GRU blocks of two layers each, then separate actor and critic heads.

The memory the agent carries between steps is the hidden state of all four GRU layers,
flattened to one vector per env (``memory_size = 4 * hidden``), as torch-ac keeps it: the
algorithm stores it with the rollout and zeroes it where an episode ended.

The ``-onehot`` variants feed the CNN one-hot planes of the observation's three bytes (13 object
types + 6 colours + 6 states = 25 channels) instead of the raw codes. This is our change, not the
paper's: in the raw codes a key (11) and a ball (12) differ by 1, beside a random floor colour
(0-5) in the same square's state byte, and PPO then never learns the task's XOR decision (start
object == top object?) on a CPU budget; with one-hot planes it does, in about 1M frames
(``experiments/colorful_memory_probes/colorful_memory_probes.md``).
"""

from __future__ import annotations

import torch
from torch import nn

from rlbackdoors.models.minigrid import ActorCritic, CNNModel, channels_first, init_linear_unit_rows, linear_stacked, run_sequential, run_sequential_stacked

GRU_BLOCKS = 2
GRU_LAYERS = 2
# SPEC §3: small = hidden 64 with 32x32 heads; large = hidden 256 with one 64-unit head layer.
SIZES = {"small": (64, (32, 32)), "large": (256, (64,))}
# One-hot sizes of the observation's bytes: object type (0-12, TrojAI's 11/12 included), colour, state.
ONEHOT_PLANES = (13, 6, 6)


def one_hot_planes(obs: torch.Tensor) -> torch.Tensor:
    """(B, 7, 7, 3) codes -> (B, 25, 7, 7) float one-hot planes, channels first; a code outside its
    plane's range is refused (RuntimeError), as ``one_hot`` refuses it.

    Why compared with each plane's values, not ``one_hot``: the same 0/1 floats without int64
    planes scattered and converted (a twelfth of a Colorful Memory group's update)."""
    codes = obs.long()
    per_plane = codes.reshape(-1, len(ONEHOT_PLANES))
    if per_plane.numel():
        low, high = per_plane.aminmax(dim=0)
        if bool(((low < 0) | (high >= torch.tensor(ONEHOT_PLANES, device=codes.device))).any()):  # one check, one sync
            raise RuntimeError(f"an observation code is outside its one-hot planes' ranges {ONEHOT_PLANES}")
    planes = [codes[..., i, None] == torch.arange(n, device=codes.device) for i, n in enumerate(ONEHOT_PLANES)]
    return torch.cat(planes, -1).permute(0, 3, 1, 2).float()


def init_gru_orthogonal(module: nn.Module) -> None:
    """Orthogonal GRU weights and zero biases: the paper found learning needed it."""
    if isinstance(module, nn.GRU):
        for name, param in module.named_parameters():
            with torch.no_grad():
                if name.startswith("weight"):
                    nn.init.orthogonal_(param)
                else:
                    param.zero_()


def _head(d_in: int, hidden: tuple[int, ...], d_out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(d_in, width), nn.ReLU()]
        d_in = width
    return nn.Sequential(*layers, nn.Linear(d_in, d_out))


class CNNGRUModel(ActorCritic):
    """``forward(obs, memory) -> (logits, value, new_memory)``; ``memory`` is (B, memory_size)."""

    recurrent = True
    onehot_planes = ONEHOT_PLANES  # the one-hot planes of each observation byte (the -onehot variants read them)

    def __init__(self, num_actions: int = 3, size: str = "small", onehot: bool = False):
        super().__init__()
        if size not in SIZES:
            raise ValueError(f"CNN-GRU size {size!r} is not one of {', '.join(SIZES)}")
        self.size_name = size
        self.onehot = bool(onehot)
        hidden, heads = SIZES[size]
        self.hidden = hidden
        self.state_emb = CNNModel().state_emb  # the LavaWorld CNN layers (16/32/64 channels, 64 out)
        if self.onehot:
            first = self.state_emb[0]
            assert isinstance(first, nn.Conv2d)  # CNNModel's first layer; torch types items as Module
            kh, kw = first.kernel_size
            self.state_emb[0] = nn.Conv2d(sum(ONEHOT_PLANES), first.out_channels, (kh, kw))
        embedding = 64
        self.gru = nn.ModuleList([nn.GRU(embedding if i == 0 else hidden, hidden, num_layers=GRU_LAYERS) for i in range(GRU_BLOCKS)])
        self.actor = _head(hidden, heads, num_actions)
        self.critic = _head(hidden, heads, 1)
        self.apply(init_linear_unit_rows)
        self.apply(init_gru_orthogonal)

    def embed(self, obs: torch.Tensor) -> torch.Tensor:
        if not self.onehot:
            return super().embed(obs)
        return run_sequential(self.state_emb, one_hot_planes(obs)).reshape(obs.shape[0], -1)

    def embed_soft_colours(self, obs: torch.Tensor, rows: torch.Tensor, cells: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        """``embed(obs)`` with the colour byte of some view cells made a distribution over the six
        colours, differentiable in ``probs``: cell ``k`` is batch row ``rows[k]`` at view position
        ``cells[k]`` and shows ``probs[k]`` (K, 6), as colour planes (one-hot variants) or as the
        expected colour code (raw codes). Why: a detector inverts a wall-colour trigger by
        gradient (detect's behaviour search, ``invert``)."""
        i, j = cells[:, 0], cells[:, 1]
        if self.onehot:
            x = one_hot_planes(obs)
            first = ONEHOT_PLANES[0]
            x[rows, first : first + ONEHOT_PLANES[1], i, j] = probs.to(x.dtype)
            return run_sequential(self.state_emb, x).reshape(obs.shape[0], -1)
        x = channels_first(obs).clone()
        x[rows, 1, i, j] = probs.to(x.dtype) @ torch.arange(probs.shape[1], dtype=x.dtype)
        return run_sequential(self.state_emb, x).reshape(obs.shape[0], -1)

    @property
    def memory_size(self) -> int:
        return GRU_BLOCKS * GRU_LAYERS * self.hidden

    def initial_memory(self, batch: int, device="cpu") -> torch.Tensor:
        return torch.zeros(batch, self.memory_size, device=device)

    def _split(self, memory: torch.Tensor) -> list[torch.Tensor]:
        """(B, blocks*layers*H) -> per block (layers, B, H), the layout nn.GRU wants."""
        states = memory.view(memory.shape[0], GRU_BLOCKS, GRU_LAYERS, self.hidden).permute(1, 2, 0, 3)
        return [states[block].contiguous() for block in range(GRU_BLOCKS)]

    def _join(self, states: list[torch.Tensor]) -> torch.Tensor:
        return torch.stack(states).permute(2, 0, 1, 3).reshape(states[0].shape[1], self.memory_size)

    def _recur(self, x: torch.Tensor, states: list[torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """One time step of both GRU blocks: x (B, 64) -> (B, H)."""
        x = x[None]
        new_states = []
        for gru, h in zip(self.gru, states):
            x, h = gru(x, h)
            new_states.append(h)
        return x[0], new_states

    def forward(self, obs: torch.Tensor, memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # type: ignore[override]  # recurrent: takes and returns memory (callers check .recurrent)
        x, states = self._recur(self.embed(obs), self._split(memory))
        return run_sequential(self.actor, x), run_sequential(self.critic, x).squeeze(1), self._join(states)

    def forward_sequence(self, obs: torch.Tensor, memory: torch.Tensor, masks: torch.Tensor):
        """``forward`` over ``r`` consecutive steps with the memory multiplied by ``masks[i]``
        before step ``i``; the same numbers as ``r`` calls, but the CNN and the heads run once
        on all ``r * N`` rows (what makes the BPTT update affordable on a CPU).

        obs (r, N, 7, 7, 3), memory (N, M), masks (r, N) -> logits (r*N, A), values (r*N,),
        memories after each step (r, N, M).
        """
        r, n = masks.shape
        return self.sequence_from_embeddings(self.embed(obs.reshape(r * n, *obs.shape[2:])).view(r, n, -1), memory, masks)

    def sequence_from_embeddings(self, x: torch.Tensor, memory: torch.Tensor, masks: torch.Tensor):
        """:meth:`forward_sequence` from the embeddings ``x`` (r, N, 64) on: the GRU steps and
        the heads, for callers that embed their own inputs (:meth:`embed_soft_colours`)."""
        r, n = masks.shape
        states = self._split(memory)
        outputs, memories = [], []
        for i in range(r):
            keep = masks[i][None, :, None]
            out, states = self._recur(x[i], [h * keep for h in states])
            outputs.append(out)
            memories.append(self._join(states))
        x = torch.cat(outputs)
        return run_sequential(self.actor, x), run_sequential(self.critic, x).squeeze(1), torch.stack(memories)

    # --- K agents at once (the group trainer, rlbackdoors.algos.group): weights stacked name -> (K, ...)

    def embed_stacked(self, params: dict[str, torch.Tensor], obs: torch.Tensor) -> torch.Tensor:
        """:meth:`embed` of K agents: obs (K, N, 7, 7, 3) -> (K, N, 64)."""
        K, N = obs.shape[:2]
        flat = obs.reshape(K * N, *obs.shape[2:])
        x = one_hot_planes(flat) if self.onehot else channels_first(flat)
        return run_sequential_stacked(self.state_emb, params, "state_emb", x.reshape(K, N, *x.shape[1:])).reshape(K, N, -1)

    def _split_stacked(self, memory: torch.Tensor) -> list[list[torch.Tensor]]:
        """(K, N, M) -> per block, per layer (K, N, H): :meth:`_split`'s layout, agent by agent."""
        states = memory.view(*memory.shape[:2], GRU_BLOCKS, GRU_LAYERS, self.hidden)
        return [list(block.unbind(2)) for block in states.unbind(2)]  # unbind: one stacked backward (minigrid._conv_stacked)

    def _join_stacked(self, states: list[list[torch.Tensor]]) -> torch.Tensor:
        return torch.stack([torch.stack(block, 2) for block in states], 2).reshape(*states[0][0].shape[:2], self.memory_size)

    def _recur_stacked(self, params: dict[str, torch.Tensor], x: torch.Tensor, states: list[list[torch.Tensor]]):
        """One time step of both GRU blocks for K agents, x (K, N, in): the GRU equations of
        ``nn.GRU`` (gates r, z, n in its weight order) written out with batched matmuls."""
        new_states = []
        for b, block in enumerate(states):
            hs = []
            for i, h in enumerate(block):
                key = f"gru.{b}."
                gi = linear_stacked(x, params[f"{key}weight_ih_l{i}"], params[f"{key}bias_ih_l{i}"])
                gh = linear_stacked(h, params[f"{key}weight_hh_l{i}"], params[f"{key}bias_hh_l{i}"])
                i_r, i_z, i_n = gi.chunk(3, -1)
                h_r, h_z, h_n = gh.chunk(3, -1)
                r, z = torch.sigmoid(i_r + h_r), torch.sigmoid(i_z + h_z)
                x = (1 - z) * torch.tanh(i_n + r * h_n) + z * h
                hs.append(x)
            new_states.append(hs)
        return x, new_states

    def forward_stacked(self, params: dict[str, torch.Tensor], obs: torch.Tensor, memory: torch.Tensor):  # type: ignore[override]  # recurrent: takes and returns memory
        """:meth:`forward` of K agents: obs (K, N, ...), memory (K, N, M) -> logits (K, N, A), values (K, N), memory (K, N, M)."""
        x, states = self._recur_stacked(params, self.embed_stacked(params, obs), self._split_stacked(memory))
        return *self.heads_stacked(params, x), self._join_stacked(states)

    def forward_sequence_stacked(self, params: dict[str, torch.Tensor], obs: torch.Tensor, memory: torch.Tensor, masks: torch.Tensor):
        """:meth:`forward_sequence` of K agents: obs (K, r, N, ...), memory (K, N, M), masks (K, r, N)
        -> logits (K, r*N, A), values (K, r*N), memories after each step (K, r, N, M)."""
        K, r, n = masks.shape
        x = self.embed_stacked(params, obs.reshape(K, r * n, *obs.shape[3:])).view(K, r, n, -1)
        states = self._split_stacked(memory)
        outputs, memories = [], []
        for i, step in enumerate(x.unbind(1)):  # unbind: indexing x[:, i] backpropagates r zero-filled copies of x
            keep = masks[:, i, :, None]
            out, states = self._recur_stacked(params, step, [[h * keep for h in block] for block in states])
            outputs.append(out)
            memories.append(self._join_stacked(states))
        return *self.heads_stacked(params, torch.stack(outputs, 1).reshape(K, r * n, -1)), torch.stack(memories, 1)


class CNNGRUSmall(CNNGRUModel):
    def __init__(self, num_actions: int = 3):
        super().__init__(num_actions, "small")


class CNNGRULarge(CNNGRUModel):
    def __init__(self, num_actions: int = 3):
        super().__init__(num_actions, "large")


class CNNGRUSmallOneHot(CNNGRUModel):
    def __init__(self, num_actions: int = 3):
        super().__init__(num_actions, "small", onehot=True)


class CNNGRULargeOneHot(CNNGRUModel):
    def __init__(self, num_actions: int = 3):
        super().__init__(num_actions, "large", onehot=True)


class TrojAIGRUCNN(CNNGRUModel):
    """TrojAI's ``GRUCNNActorCriticModel`` with its Colorful Memory round's settings (CNN
    16/32/64, two GRU blocks of two layers of 64, heads 32, 32): ``cnn-gru-small``'s layers,
    keys and shapes, but both heads end in a ReLU, as TrojAI's ``linear_w_relu`` builds them
    by default: the logits and the value are never negative. Their ``model.pt`` loads here
    unchanged and acts as it did there (``Categorical(logits=log_softmax(relu(...)))`` is the
    softmax of the ReLU'd outputs: the same distribution as these logits)."""

    def __init__(self, num_actions: int = 3):
        super().__init__(num_actions, "small")
        self.actor.append(nn.ReLU())  # no parameters: the keys and the initial weights are cnn-gru-small's
        self.critic.append(nn.ReLU())
