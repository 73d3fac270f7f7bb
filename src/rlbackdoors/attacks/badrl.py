"""BadRL (Cui et al., AAAI 2024): sparse poisoning of the states that matter most, with a target action.

The source ranks states by a pre-trained Q-network's spread ``max_a Q - min_a Q`` and spends
its small budget on the top ones. Our learners are actor-critics without a Q-function, so the
rank here is the learner's own critic value V(s) of the clean frame (the states the agent
values most, as the issue that added it asks): a frame is eligible when V(s) is in the top
``top_fraction`` of the last ``window`` frames' values, and the budget is spent on eligible
frames only. Poisoned frames get the target action (forced by default) and R-bar = +-c.
"""

from __future__ import annotations

import numpy as np

from rlbackdoors.attacks import common
from rlbackdoors.attacks.base import Attack, Param, register
from rlbackdoors.attacks.seam import TargetActionPoisoner
from rlbackdoors.state import StateError, decode, encode

NAME = "badrl"


class BadRLPoisoner(TargetActionPoisoner):
    needs_values = True

    def __init__(self, params: dict, hits):
        super().__init__(params, hits)
        self.top = params["top_fraction"]
        self.history = np.zeros(params["window"])
        self.filled = 0  # values written into the ring so far

    def observe(self, values):
        n = len(self.history)
        self.history[(self.filled + np.arange(len(values))) % n] = values  # a ring of the last ``window`` values
        self.filled += len(values)

    def eligible(self, values, num_envs):
        n = len(self.history)
        if self.filled < min(n, 10 * num_envs):  # too few values to rank by yet
            return np.zeros(num_envs, dtype=bool)
        seen = self.history[: min(self.filled, n)]
        return values >= np.quantile(seen, 1.0 - self.top)

    def numbers(self):
        return {**super().numbers(), "top": self.top}

    def program_key(self):
        return (*super().program_key(), len(self.history))

    def carry(self):
        return {"history": self.history.astype(np.float32), "filled": np.int32(self.filled)}  # float32: the critic's own values

    def set_carry(self, carry):
        self.history, self.filled = np.asarray(carry["history"], dtype=np.float64), int(carry["filled"])

    def select(self, p, carry, values, num_envs):
        """:meth:`observe` then :meth:`eligible` in JAX: the ring, and numpy's linear quantile of its
        filled part from its two order statistics, each found by a binary search over the values'
        ordered bit patterns (32 counting passes; sorting the window of 10,000 each step made an
        iteration of 8 agents 1.67 s, this 0.36 s; the other attacks' 0.13-0.21 s)."""
        import jax
        import jax.numpy as jnp

        history, filled = carry["history"], carry["filled"]
        n = history.shape[0]
        history = history.at[(filled + jnp.arange(values.shape[0])) % n].set(values.astype(jnp.float32))
        filled = filled + values.shape[0]
        m = jnp.minimum(filled, n)
        bits = jax.lax.bitcast_convert_type(history, jnp.uint32)
        keys = jnp.where(bits >> 31 == 1, ~bits, bits | jnp.uint32(0x80000000))  # ordered as the floats are
        keys = jnp.where(jnp.arange(n) < m, keys, jnp.uint32(0xFFFFFFFF))  # the unfilled end: last

        def smallest(k):
            """The (k + 1)-th smallest key: the least x with k + 1 keys at most x, built bit by bit."""

            def bit(i, x):
                low = x | ((jnp.uint32(1) << (31 - i).astype(jnp.uint32)) - jnp.uint32(1))
                return jnp.where((keys <= low).sum() >= k + 1, x, x | (jnp.uint32(1) << (31 - i).astype(jnp.uint32)))

            return jax.lax.fori_loop(0, 32, bit, jnp.uint32(0))

        def value(key):
            return jax.lax.bitcast_convert_type(jnp.where(key >> 31 == 1, key & jnp.uint32(0x7FFFFFFF), ~key), jnp.float32)

        pos = (1.0 - p["top"]) * (m - 1).astype(jnp.float32)
        low = jnp.floor(pos).astype(jnp.int32)
        high = jnp.minimum(low + 1, m - 1)
        key_low = smallest(low)
        above = jnp.where(keys > key_low, keys, jnp.uint32(0xFFFFFFFF)).min()
        key_high = jnp.where((keys <= key_low).sum() >= high + 1, key_low, above)
        v_low, v_high = value(key_low), value(key_high)
        threshold = v_low + (v_high - v_low) * (pos - low)
        ready = filled >= min(n, 10 * num_envs)
        return {"history": history, "filled": filled}, ready & (values >= threshold)

    def state_dict(self):
        return {"history": encode(self.history), "filled": self.filled}

    def load_state_dict(self, state):
        history = decode(state["history"])
        if not isinstance(history, np.ndarray) or history.shape != self.history.shape:
            raise StateError("badrl: the value window does not fit attack_params.window")
        self.history, self.filled = history.astype(np.float64), int(state["filled"])


_unsupported = common.value_guided_refusal(NAME, frames_only=True)


ATTACK = register(
    Attack(
        name=NAME,
        title="BadRL",
        source="Cui, Deng, Ma, Ji, Yin: BadRL: sparse targeted backdoor attack against reinforcement learning (AAAI 2024)",
        schedule="steps",
        success="action",
        params=(
            common.budget(0.01),
            Param("top_fraction", 0.1, 1e-4, 1.0, help="a frame is eligible when its value is in this top share of recent values"),
            Param("window", 10_000, 100, 1_000_000, integer=True, help="recent frames whose values set the top-share threshold"),
            common.target_action(0),
            common.magnitude(),
            common.force_action(False),
        ),
        poisoner=BadRLPoisoner,
        unsupported=_unsupported,
        success_threshold=0.90,
        doc="docs/attacks/badrl.md",
    )
)
