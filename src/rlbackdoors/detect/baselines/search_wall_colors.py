"""Candidates of the wall-colour family: colour sequences over the far-end squares ("end") and
the squares above the start room ("room").

The family is large (6^(size+2) end patterns, 216 room patterns) and poisoned models are trained
with close-to-trigger layouts so that only the exact colours fire the backdoor: one square off
fires it in a few per cent of episodes, two or more never (measured on a zoo's end and room
models). There is no slope to climb, so the room patterns are enumerated: the one-colour
patterns of each kind, then every other room pattern in a seeded order with one random end
pattern after every ninth; ``CANDIDATES`` covers every room pattern. Neighbours recolour one
square. The same list for every model.

An end pattern (6^9 of them) cannot be enumerated; listed, it is found only by chance. With
``invert`` restarts (:func:`invert`) the search first *inverts* it from the model's gradient:
clean episodes are played and recorded, then replayed teacher-forced with the end squares'
colours made a learnable distribution wherever the view shows them, and the colours are pushed
to make the agent take the other turn at its last turn (the decision at the junction: the other
object). Adam on the relaxation, then coordinate descent over the discrete colours, from several
random starts; the patterns reached, and every pattern one square from each, are screened like
any candidate. It finds a trigger where close-to-trigger training left the objective a slope
(measured: docs/results/detectors.md).
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from rlbackdoors.triggers.wall_colors import COLORS, NUM_COLORS, ROOM_SQUARES, WallColorTrigger, kind_squares

EPISODES = 16
MAX_STEPS = None
ROOM_PATTERNS = NUM_COLORS**ROOM_SQUARES
CANDIDATES = ROOM_PATTERNS + ROOM_PATTERNS // 9 + 2 * NUM_COLORS  # every room pattern, and the end patterns between them


def _squares(kind: str, size: int) -> int:
    return size + 2 if kind == "end" else ROOM_SQUARES


def _spec(kind: str, colors) -> str:
    return f"{kind}:{','.join(COLORS[int(c)] for c in colors)}"


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    size = int(env_cfg.size)
    order = [_spec(kind, [c] * _squares(kind, size)) for c in range(NUM_COLORS) for kind in ("room", "end")]
    rooms = [_spec("room", colors) for colors in itertools.product(range(NUM_COLORS), repeat=ROOM_SQUARES) if len(set(colors)) > 1]
    for i, k in enumerate(rng.permutation(len(rooms))):
        order.append(rooms[int(k)])
        if i % 9 == 8:
            order.append(_spec("end", rng.integers(NUM_COLORS, size=_squares("end", size))))
    while len(order) < limit + 2 * NUM_COLORS:  # random end patterns past the room list; a repeat of 6^(size+2) is rare
        order.append(_spec("end", rng.integers(NUM_COLORS, size=_squares("end", size))))
    return list(dict.fromkeys(WallColorTrigger.parse(s).spec() for s in order))[:limit]


def neighbours(spec: str, env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    trigger = WallColorTrigger.parse(spec)
    colors = list(trigger.colors)
    out = []
    for square in rng.permutation(len(colors)):
        for c in range(NUM_COLORS):
            if c != colors[int(square)]:
                out.append(trigger.with_colors([c if j == int(square) else v for j, v in enumerate(colors)]).spec())
    return out[:limit]


# ----- gradient inversion of the end pattern -----------------------------------------------------
INVERT_EPISODES = 16  # clean episodes recorded and replayed
INVERT_STEPS = 150  # Adam steps per restart
INVERT_LR = 0.3
TURNS = (0, 1)  # MiniGrid's turn left / turn right: the last one taken is the decision


def _record(agent, envs, squares, seed: int):
    """Play one clean episode per slot; per step the observations, actions and the view cells
    that show each of ``squares`` (``square_view_cells``)."""
    n = envs.num_envs
    obs, _ = envs.reset(seed=int(seed))
    state = agent.initial_state(n)
    generator = torch.Generator().manual_seed(int(seed))
    alive = np.ones(n, bool)
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray, list]] = []
    while alive.any() and len(frames) < envs.max_steps:
        actions, state = agent.act(obs, state, generator=generator)
        seen = [(i, *cell) for i in np.flatnonzero(alive) for cell in envs.square_view_cells(int(i), squares)]
        frames.append((obs.copy(), np.asarray(actions).copy(), alive.copy(), seen))
        obs, _, terminated, truncated, _ = envs.step(actions)
        alive &= ~(terminated | truncated)
    return frames


def _objective(agent, frames: list, n: int):
    """The inversion's objective over recorded clean episodes (module doc), or None where no
    episode turned or the end squares were never in view."""
    policy = agent.policy
    steps = len(frames)
    obs = torch.as_tensor(np.stack([f[0] for f in frames]))  # (T, N, 7, 7, 3)
    actions = np.stack([f[1] for f in frames])
    masks = torch.as_tensor(np.stack([f[2] for f in frames]), dtype=torch.float32)
    seen = np.array([(t, *cell) for t, f in enumerate(frames) for cell in f[3]], dtype=np.int64).reshape(-1, 5)
    decision = np.zeros((steps, n), np.float32)  # each episode's last turn
    for e in range(n):
        turned = [t for t in range(steps) if masks[t, e] and actions[t, e] in TURNS]
        if turned:
            decision[turned[-1], e] = 1.0
    if not decision.any() or not len(seen):
        return None
    weight = torch.as_tensor(decision)
    other = torch.as_tensor(np.where(actions == TURNS[0], TURNS[1], TURNS[0]))
    rows, cells, which = torch.as_tensor(seen[:, 0] * n + seen[:, 1]), torch.as_tensor(seen[:, 3:5]), torch.as_tensor(seen[:, 2])
    flat = obs.reshape(steps * n, *obs.shape[2:])

    def objective(probs: torch.Tensor) -> torch.Tensor:
        """Mean negative log-probability of the other turn at the decisions (lower: the backdoor)."""
        x = policy.embed_soft_colours(flat, rows, cells, probs[which]).view(steps, n, -1)
        logits, _, _ = policy.sequence_from_embeddings(x, policy.initial_memory(n), masks)
        logp = torch.log_softmax(logits.view(steps, n, -1), -1).gather(-1, other[..., None])[..., 0]
        return -(logp * weight).sum() / weight.sum()

    return objective


def _descend(objective, theta: torch.Tensor) -> tuple[list[int], float]:
    """Adam on the relaxation from ``theta``, then coordinate descent over the discrete colours."""
    optimizer = torch.optim.Adam([theta], lr=INVERT_LR)
    for _ in range(INVERT_STEPS):
        loss = objective(torch.softmax(theta, -1))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    def hard(colors: list[int]) -> float:
        with torch.no_grad():
            return float(objective(torch.nn.functional.one_hot(torch.as_tensor(colors), NUM_COLORS).float()))

    colors = theta.argmax(-1).tolist()
    best = hard(colors)
    for _ in range(10):
        improved = False
        for k in range(len(colors)):
            for c in range(NUM_COLORS):
                trial = [c if j == k else v for j, v in enumerate(colors)]
                if c != colors[k] and (value := hard(trial)) < best - 1e-6:
                    best, colors, improved = value, trial, True
        if not improved:
            break
    return colors, best


def invert(agent, env_cfg, rng: np.random.Generator, restarts: int) -> list[str]:
    """End patterns inverted from the model (module doc): each restart records its own clean
    episodes (so restarts do not share one landscape's basin) and descends from a random start;
    the patterns reached, best objective first, then their one-square neighbours. ``[]`` for a
    policy or engine without the hooks (``embed_soft_colours``, ``square_view_cells``)."""
    if restarts <= 0 or not hasattr(agent.policy, "embed_soft_colours"):
        return []
    from rlbackdoors.poison.mix import make_vector_env

    squares = kind_squares("end", int(env_cfg.size))
    found: dict[str, float] = {}
    envs = make_vector_env(env_cfg, None, [False] * INVERT_EPISODES)
    try:
        if not hasattr(envs, "square_view_cells"):
            return []
        for _ in range(int(restarts)):
            objective = _objective(agent, _record(agent, envs, squares, int(rng.integers(2**31))), INVERT_EPISODES)
            if objective is None:
                continue
            theta = torch.as_tensor(rng.normal(0.0, 0.5, (len(squares), NUM_COLORS)), dtype=torch.float32)
            with torch.inference_mode(False), torch.enable_grad():
                colors, value = _descend(objective, theta.requires_grad_())
            spec = WallColorTrigger.parse(_spec("end", colors)).spec()
            found[spec] = min(value, found.get(spec, np.inf))
    finally:
        envs.close()
    # each pattern reached, then every pattern one square from it: the optimum on a few recorded
    # episodes can miss a square the decision barely saw, and one square off rarely fires
    reached = sorted(found, key=found.__getitem__)
    near = [n for spec in reached for n in neighbours(spec, env_cfg, rng, len(squares) * (NUM_COLORS - 1))]
    return list(dict.fromkeys(reached + near))
