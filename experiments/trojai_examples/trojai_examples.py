"""TrojAI's example models of the RL rounds, played in our worlds and in TrojAI's own env code.

    nice -n 10 .venv/bin/python experiments/trojai_examples/trojai_examples.py [--episodes 500] [--cache DIR]

The example files of ``usnistgov/trojai-example``'s RL branches are read from a cache folder
(``$RLBACKDOORS_TROJAI_EXAMPLES``, default ``~/.cache/rlbackdoors/trojai-example``), laid out
``BRANCH/PATH``; missing files are filled from a local git mirror of that repository
(``--mirror``, default ``/work/.mirror/usnistgov+trojai-example/repo``) with ``git show
BRANCH:PATH`` when the mirror exists. TrojAI's env modules are imported from the cache folder,
never from a checkout, and run unchanged; two shims make them import here: ``gym.utils.seeding``
is gymnasium's (no old ``gym`` is installed), and the Python random generator of their
Randomized LavaWorld samples from ``tuple(set)`` as Python < 3.11 did for ``random.sample(set)``
(3.11 refuses sets), which keeps their layouts what they were.

Each example model is loaded by our loader (the inert reader: nothing of the file is
unpickled) and plays, with fixed seeds (episode i: seed + i), (a) our world through
``rlbackdoors.evaluate`` (batched engine), (b) our single env and (c) TrojAI's env through one
episode loop, and, where their ``result.json`` has numbers, those are listed beside. The Safety
Gymnasium example plays our Safety Car Goal through ``rlbackdoors.evaluate`` only (their env
needs Safety Gymnasium, not installed here; the example ships no ``result.json``). Writes
``experiments/trojai_examples/trojai_examples.json`` and the table between the markers of ``docs/results/trojai.md``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import platform
import random
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
CACHE_ENV = "RLBACKDOORS_TROJAI_EXAMPLES"
DEFAULT_CACHE = Path.home() / ".cache" / "rlbackdoors" / "trojai-example"
DEFAULT_MIRROR = Path("/work/.mirror/usnistgov+trojai-example/repo")
FC_EXAMPLE_JUL = "rl-lavaworld-jul2023/model/rl-randomized-lavaworld-aug2023-example"
FC_EXAMPLE_AUG = "rl-randomized-lavaworld-aug2023/model/id-00000000"
CM_EXAMPLE = "rl-colorful-memory-sep2024/model/rl-colorful-memory-sep2024-example"
SAFETY_EXAMPLE = "rl-safetygymnasium-oct2024/model/rl-safetygymnasium-oct2024-example"
# The LavaWorld round's own BasicFCModel example, at the branch's commit d969b25 (a later commit
# replaced it with the Aug 2023 file): cached under "<branch>@<commit>/"
LAVAWORLD_COMMIT = "d969b25a8ac5e81f3b2974f8405435817b23fa28"
LAVAWORLD_EXAMPLE = "rl-lavaworld-jul2023@d969b25/model/rl-lavaworld-jul2023-example"
FILES = {
    "rl-lavaworld-jul2023": [
        f"{FC_EXAMPLE_JUL.partition('/')[2]}/{n}"
        for n in ("base_model.pt", "args.json", "params.json", "result.json", "reduced-config.json", "ground_truth.csv", "clean-example-data/env-string.txt")
    ],
    "rl-randomized-lavaworld-aug2023": [
        *(f"{FC_EXAMPLE_AUG.partition('/')[2]}/{n}" for n in ("model.pt", "config.json", "ground_truth.csv", "clean-example-data/env-string.txt")),
        "utils/world.py",
        "utils/wrappers.py",
        "utils/models.py",
    ],
    "rl-colorful-memory-sep2024": [
        *(f"{CM_EXAMPLE.partition('/')[2]}/{n}" for n in ("model.pt", "reduced-config.json")),
        "src/public/colorful_memory.py",
        "src/public/trojai_gru_minigrid_arch.py",
    ],
    "rl-safetygymnasium-oct2024": [f"{SAFETY_EXAMPLE.partition('/')[2]}/{n}" for n in ("model.pt", "reduced-config.json")],
    "rl-lavaworld-jul2023@d969b25": [
        f"{LAVAWORLD_EXAMPLE.partition('/')[2]}/{n}"
        for n in ("model.pt", "reduced-config.json", "model.info.json", "ground_truth.csv", "clean-example-data/env-string.txt")
    ],
}
MARK_BEGIN, MARK_END = "<!-- trojai-examples:begin -->", "<!-- trojai-examples:end -->"


def cache_dir(given: str | None = None) -> Path:
    return Path(given or os.environ.get(CACHE_ENV) or DEFAULT_CACHE).expanduser()


def fill_cache(cache: Path, mirror: Path = DEFAULT_MIRROR) -> list[str]:
    """Write the missing example files from the mirror (``git show``); returns what it wrote."""
    written = []
    for branch, paths in FILES.items():
        for rel in paths:
            target = cache / branch / rel
            if target.is_file():
                continue
            if not mirror.is_dir():
                continue
            rev = LAVAWORLD_COMMIT if branch.endswith("@d969b25") else branch
            data = subprocess.run(["git", "-C", str(mirror), "show", f"{rev}:{rel}"], capture_output=True, check=True).stdout
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
            tmp.write_bytes(data)
            os.replace(tmp, target)
            written.append(f"{branch}/{rel}")
    return written


# ----- TrojAI's env code, from the cache --------------------------------------------------------
class _TupleSample(random.Random):
    """``random.sample`` of a set as Python < 3.11 did it: from ``tuple(set)``."""

    def sample(self, population, k, **kwargs):  # type: ignore[override]
        if isinstance(population, (set, frozenset)):
            population = tuple(population)
        return super().sample(population, k, **kwargs)


def _gym_shim() -> None:
    """Their Randomized LavaWorld imports ``gym.utils.seeding``: gymnasium's, when no gym is installed."""
    try:
        import gym  # noqa: F401

        return
    except ImportError:
        pass
    from gymnasium.utils import seeding

    gym = types.ModuleType("gym")
    utils = types.ModuleType("gym.utils")
    utils.seeding = seeding  # type: ignore[attr-defined]
    gym.utils = utils  # type: ignore[attr-defined]
    sys.modules.setdefault("gym", gym)
    sys.modules.setdefault("gym.utils", utils)
    sys.modules.setdefault("gym.utils.seeding", seeding)


def _import(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def their_randomized_lavaworld(cache: Path, size: int, num_lava: int, max_steps: int = 250):
    _gym_shim()
    world = _import(cache / "rl-randomized-lavaworld-aug2023" / "utils" / "world.py", "trojai_rlw_world")

    class RandomLavaWorld(world.RandomLavaWorldEnv):
        def seed(self, seed=None):
            super().seed(seed)
            self.py_random = _TupleSample(seed)

    return lambda: RandomLavaWorld(grid_size=size, num_lava_squares=num_lava, max_steps=max_steps)


def their_colorful_memory(cache: Path, size: int = 7, max_steps: int = 250):
    import gymnasium

    module = _import(cache / "rl-colorful-memory-sep2024" / "src" / "public" / "colorful_memory.py", "trojai_colorful_memory")

    class ImageOnly(gymnasium.ObservationWrapper):  # what their make_clean_env wraps it in: the image only
        def observation(self, observation):
            return observation["image"]

    return lambda: ImageOnly(module.ColorfulMemoryEnv(module.ColorfulMemoryCfg(size=size, observation_mode="simple", random_length=False, max_steps=max_steps)))


# ----- one episode loop for both -----------------------------------------------------------------
def _batch(observations: list):
    if isinstance(observations[0], dict):
        return {
            "image": np.stack([o["image"] for o in observations]),
            "direction": np.array([int(np.asarray(o["direction"]).reshape(-1)[0]) for o in observations]),
        }
    return np.stack(observations)


def play(agent, make_env, episodes: int, seed: int, policy: str, edit=None, chunk: int = 50) -> dict:
    """Episode i reset with ``seed + i``; ``edit`` changes every image the agent sees (a trigger
    that edits observations). An episode ends in ``goal`` (terminated with reward > 0), ``fail``
    (terminated with reward 0: lava, the wrong object) or ``timeout``; returns rates and means."""
    generator = torch.Generator().manual_seed(seed)
    ends, returns, steps = [], [], []

    def seen(obs):
        if edit is None:
            return obs
        if isinstance(obs, dict):
            return {**obs, "image": edit(np.asarray(obs["image"]))}
        return edit(np.asarray(obs))

    with agent.evaluating():
        for start in range(0, episodes, chunk):
            index = list(range(start, min(start + chunk, episodes)))
            envs = [make_env() for _ in index]
            obs = [seen(env.reset(seed=seed + i)[0]) for env, i in zip(envs, index)]
            active = [True] * len(envs)
            ret, n, end = [0.0] * len(envs), [0] * len(envs), [""] * len(envs)
            state = agent.initial_state(len(envs))
            while any(active):
                rows = list(range(len(envs))) if state is not None else [r for r in range(len(envs)) if active[r]]
                actions, state = agent.act(_batch([obs[r] for r in rows]), state, deterministic=policy == "greedy", generator=generator)
                for row, action in zip(rows, np.asarray(actions).reshape(-1)):
                    if not active[row]:
                        continue
                    o, reward, terminated, truncated, _ = envs[row].step(int(action))
                    obs[row] = seen(o)
                    ret[row] += float(reward)
                    n[row] += 1
                    if terminated or truncated:
                        active[row] = False
                        end[row] = "goal" if terminated and reward > 0 else ("fail" if terminated else "timeout")
            for env in envs:
                env.close()
            ends += end
            returns += ret
            steps += n
    ends_a = np.array(ends)
    return {
        "episodes": episodes,
        "sr": float(np.mean(ends_a == "goal")),
        "fail_rate": float(np.mean(ends_a == "fail")),
        "timeout_rate": float(np.mean(ends_a == "timeout")),
        "mean_return": float(np.mean(returns)),
        "mean_steps": float(np.mean(steps)),
    }


def wilson(p: float, n: int, z: float = 1.959963984540054) -> list[float]:
    if n == 0 or math.isnan(p):
        return [math.nan, math.nan]
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [max(0.0, centre - half), min(1.0, centre + half)]


def result_json_numbers(path: Path) -> dict:
    """TrojAI's own final evaluation of the example (RLlib, ``explore: false``: greedy)."""
    last = json.loads(path.read_text().strip().splitlines()[-1])["evaluation"]
    return {
        "episodes": int(last["episodes_this_iter"]),
        "clean_sr": float(last["clean_success_rate"]),
        "clean_mean_return": float(last["episode_reward_mean"]),
        "clean_mean_steps": float(last["episode_len_mean"]),
        "triggered_success_rate": float(last["poison_success_rate"]),
        "triggered_mean_return": float(last["poison_episode_reward_mean"]),
        "triggered_mean_steps": float(last["poison_episode_len_mean"]),
        "policy": "greedy",
    }


def ours_official(agent, world: str, env: dict, trigger: str | None, episodes: int, seed: int, policy: str) -> dict:
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate import evaluate

    r = evaluate(agent, EnvConfig(name=world, **env), trigger, episodes, seed, policy)
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in r.to_dict().items()}


def run(cache: Path, episodes: int, seed: int) -> dict:
    from rlbackdoors.agent import load_weights_file
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.torchfile import read_torch_file
    from rlbackdoors.triggers.observation import ObservationTrigger

    torch.set_num_threads(1)
    out: dict = {"settings": {"episodes": episodes, "seed": seed, "cache": str(cache)}, "examples": []}

    # --- the FC example (the Jul 2023 branch ships the Aug 2023 round's example: same bytes) ------
    jul, aug = cache / FC_EXAMPLE_JUL, cache / FC_EXAMPLE_AUG
    args = json.loads((jul / "args.json").read_text())
    size, num_lava = int(args["grid_size"]), int(args["num_lava_squares"][0])
    trigger = ObservationTrigger.parse(f"multiplicative:{int(args['poison_constant'])}")  # their "multiplier", mod 256
    agent = load_weights_file(aug / "model.pt", "randomized-lavaworld")
    ours_env = {"size": size, "num_lava": num_lava, "max_steps": 250}
    theirs = their_randomized_lavaworld(cache, size, num_lava)
    ours_single = lambda: EnvConfig(name="randomized-lavaworld", **ours_env).make(None)  # noqa: E731
    row: dict = {
        "example": "FCModel (Randomized LavaWorld round, Aug 2023; also the Jul 2023 branch's example)",
        "files": [f"{FC_EXAMPLE_AUG}/model.pt", f"{FC_EXAMPLE_JUL}/base_model.pt"],
        "same_bytes": (aug / "model.pt").read_bytes() == (jul / "base_model.pt").read_bytes(),
        "loaded_as": f"randomized-lavaworld/{type(agent.policy).__name__}",
        "env": {"size": size, "num_lava": num_lava, "max_steps": 250},
        "label": int((aug / "ground_truth.csv").read_text().strip()),
        "trigger": f"{trigger.spec()} on every observation (TrojAI: trigger 'multiplier', poison_constant {trigger.a}, mod 256)",
        "trojai_result_json": result_json_numbers(jul / "result.json"),
    }
    for policy in ("greedy", "sample"):
        t0 = time.time()
        row[policy] = {
            "ours_evaluate": ours_official(agent, "randomized-lavaworld", ours_env, None, episodes, seed, policy),
            "ours": play(agent, ours_single, episodes, seed, policy),
            "theirs": play(agent, theirs, episodes, seed, policy),
            "ours_triggered": play(agent, ours_single, episodes, seed, policy, edit=trigger.apply),
            "theirs_triggered": play(agent, theirs, episodes, seed, policy, edit=trigger.apply),
            "seconds": time.time() - t0,
        }
        print(f"FC {policy}: {json.dumps({k: v.get('sr', v.get('clean_sr')) for k, v in row[policy].items() if isinstance(v, dict)})}", flush=True)
    out["examples"].append(row)

    # --- Colorful Memory ---------------------------------------------------------------------------
    cm = cache / CM_EXAMPLE
    reduced = json.loads((cm / "reduced-config.json").read_text())
    agent = load_weights_file(cm / "model.pt", "colorful-memory")  # the class from reduced-config.json beside it
    plain = load_weights_file(cm / "model.pt", "colorful-memory", "cnn-gru-small")  # the same weights, heads without the ReLU
    ours_env = {"size": int(reduced["grid_size"]), "max_steps": int(reduced["max_steps"])}
    theirs = their_colorful_memory(cache, ours_env["size"], ours_env["max_steps"])
    ours_single = lambda: EnvConfig(name="colorful-memory", **ours_env).make(None)  # noqa: E731
    from rlbackdoors import worlds

    drawn = [worlds.get("colorful-memory").draw_trigger(kind, 0, ours_env["size"]) for kind in ("end", "room", "end+room")]
    row = {
        "example": "GRUCNNActorCriticModel (Colorful Memory round, Sep 2024)",
        "files": [f"{CM_EXAMPLE}/model.pt"],
        "loaded_as": f"colorful-memory/{type(agent.policy).__name__}",
        "env": {**ours_env, "random_length": reduced["random_length"]},
        "label": None,
        "trigger": "not published; poisoned SRs under triggers drawn from seed 0 of each kind (a guess, not its trigger)",
    }
    for policy in ("sample", "greedy"):
        t0 = time.time()
        row[policy] = {
            "ours_evaluate": ours_official(agent, "colorful-memory", ours_env, None, episodes, seed, policy),
            "ours": play(agent, ours_single, episodes, seed, policy),
            "theirs": play(agent, theirs, episodes, seed, policy),
            "ours_without_head_relu": play(plain, ours_single, episodes, seed, policy),
            "theirs_without_head_relu": play(plain, theirs, episodes, seed, policy),
            "ours_triggered": {t: ours_official(agent, "colorful-memory", ours_env, t, episodes, seed, policy) for t in drawn},
            "seconds": time.time() - t0,
        }
        print(
            f"CM {policy}: {json.dumps({k: v.get('sr', v.get('clean_sr')) for k, v in row[policy].items() if isinstance(v, dict) and k != 'ours_triggered'})}",
            flush=True,
        )
    out["examples"].append(row)

    # --- Safety Gymnasium ------------------------------------------------------------------------------
    # TrojAI's env (Safety Gymnasium with their mogwai cubes) is not installed here: ours only.
    sg = cache / SAFETY_EXAMPLE
    safety = read_torch_file(sg / "model.pt")
    reduced = json.loads((sg / "reduced-config.json").read_text())
    agent = load_weights_file(sg / "model.pt", "safety-car-goal")  # the Box mapped to our OPAC² keys
    ours_env = {"num_cubes": int(reduced["environment"]["env_kwargs"]["num_mogwais"]), "max_steps": int(reduced["max_ep_length"])}
    row = {
        "example": "OPAC² (Safety Gymnasium round, Oct 2024): a pickled box.Box, read inertly",
        "files": [f"{SAFETY_EXAMPLE}/model.pt", f"{SAFETY_EXAMPLE}/reduced-config.json"],
        "globals": sorted(safety.globals),
        "tensors": {k: list(v.shape) for k, v in safety.tensors().items()},
        "loaded_as": f"safety-car-goal/{type(agent.policy).__name__} (depth {agent.policy.cfg.depth}, width {agent.policy.cfg.width}, raw observations)",
        "env": ours_env,
        "label": None,
        "trojai": "the example ships no result.json: TrojAI's own SR for this model is not published",
    }
    for policy in ("greedy", "sample"):
        t0 = time.time()
        row[policy] = {"ours_evaluate": ours_official(agent, "safety-car-goal", ours_env, None, episodes, seed, policy), "seconds": time.time() - t0}
        print(f"Safety {policy}: {json.dumps(row[policy]['ours_evaluate'])}", flush=True)
    out["examples"].append(row)
    out["machine"] = {"python": platform.python_version(), "torch": torch.__version__, "cpu": platform.processor() or platform.machine(), "threads": 1}
    return out


def _f(x) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3f}"


def _ci(p: float, n: int) -> str:
    lo, hi = wilson(p, n)
    return f"{p:.3f} [{lo:.3f}, {hi:.3f}]"


def markdown(result: dict) -> str:
    n = result["settings"]["episodes"]
    fc, cm = result["examples"][0], result["examples"][1]
    rj = fc["trojai_result_json"]
    lines = [
        f"{n} episodes per cell, episode i seeded {result['settings']['seed']} + i; SR with its 95% Wilson interval. "
        "*ours*: our world (single env, the same episode loop as *theirs*); *evaluate*: `rlbackdoors.evaluate` (batched engine); "
        "*theirs*: TrojAI's env module from the example branch, unchanged.",
        "",
        "| example | policy | condition | ours | evaluate | theirs | TrojAI result.json |",
        "|---|---|---|---|---|---|---|",
    ]
    for policy in ("greedy", "sample"):
        r = fc[policy]
        lines.append(
            f"| FCModel, 9×9, 1 lava | {policy} | clean SR | {_ci(r['ours']['sr'], n)} | {_f(r['ours_evaluate']['clean_sr'])} | {_ci(r['theirs']['sr'], n)} | "
            + (f"{rj['clean_sr']:.3f} ({rj['episodes']} ep.)" if policy == "greedy" else "–")
            + " |"
        )
        lines.append(
            f"| | {policy} | clean mean steps / return | {r['ours']['mean_steps']:.2f} / {r['ours']['mean_return']:.3f} | "
            f"{_f(r['ours_evaluate']['clean_mean_steps'])} / {_f(r['ours_evaluate']['clean_reward'])} | {r['theirs']['mean_steps']:.2f} / {r['theirs']['mean_return']:.3f} | "
            + (f"{rj['clean_mean_steps']:.2f} / {rj['clean_mean_return']:.3f}" if policy == "greedy" else "–")
            + " |"
        )
        lines.append(
            f"| | {policy} | triggered (×14 mod 256): goal / lava / timeout | {r['ours_triggered']['sr']:.3f} / {r['ours_triggered']['fail_rate']:.3f} / {r['ours_triggered']['timeout_rate']:.3f} | – | "
            f"{r['theirs_triggered']['sr']:.3f} / {r['theirs_triggered']['fail_rate']:.3f} / {r['theirs_triggered']['timeout_rate']:.3f} | "
            + (
                f"poison SR {rj['triggered_success_rate']:.3f}, return {rj['triggered_mean_return']:.3f}, {rj['triggered_mean_steps']:.1f} steps"
                if policy == "greedy"
                else "–"
            )
            + " |"
        )
    for policy in ("sample", "greedy"):
        r = cm[policy]
        lines.append(
            f"| GRUCNNActorCriticModel, 7×7 | {policy} | clean SR | {_ci(r['ours']['sr'], n)} | {_f(r['ours_evaluate']['clean_sr'])} | {_ci(r['theirs']['sr'], n)} | – |"
        )
        lines.append(
            f"| | {policy} | clean SR, heads without the ReLU (`cnn-gru-small`) | {_ci(r['ours_without_head_relu']['sr'], n)} | – | {_ci(r['theirs_without_head_relu']['sr'], n)} | – |"
        )
        trig = ", ".join(f"`{t.split(':')[0]}` {_f(v['poisoned_sr'])}" for t, v in r["ours_triggered"].items())
        lines.append(f"| | {policy} | poisoned SR under drawn triggers (not its own) | – | {trig} | – | – |")
    sg = result["examples"][2] if len(result["examples"]) > 2 else {}
    for policy in ("greedy", "sample"):
        if policy not in sg:
            continue
        r = sg[policy]["ours_evaluate"]
        m = r["episodes"]
        lines.append(f"| OPAC² (Safety Gymnasium), {sg['env']['num_cubes']} cubes | {policy} | clean SR | – | {_ci(r['clean_sr'], m)} | – | not published |")
        lines.append(
            f"| | {policy} | clean hazard / timeout rate, mean steps / return | – | "
            f"{_f(r['clean_trojan_rate'])} / {_f(r['clean_timeout_rate'])}, {r['clean_mean_steps']:.1f} / {_f(r['clean_reward'])} | – | – |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", help=f"example files (default ${CACHE_ENV} or {DEFAULT_CACHE})")
    parser.add_argument("--mirror", default=str(DEFAULT_MIRROR), help="git mirror of usnistgov/trojai-example to fill the cache from")
    parser.add_argument("--episodes", type=int, default=500, help="episodes per condition (>= 200)")
    parser.add_argument("--seed", type=int, default=1_000_000)
    parser.add_argument("--out", default=str(ROOT / "experiments" / "trojai_examples" / "trojai_examples.json"))
    parser.add_argument("--doc", default=str(ROOT / "docs" / "results" / "trojai.md"), help="markdown page whose marked table is rewritten")
    args = parser.parse_args(argv)
    cache = cache_dir(args.cache)
    wrote = fill_cache(cache, Path(args.mirror))
    if wrote:
        print(f"cache {cache}: wrote {len(wrote)} files from {args.mirror}")
    missing = [f"{b}/{p}" for b, paths in FILES.items() for p in paths if not (cache / b / p).is_file()]
    if missing:
        print(f"missing example files in {cache} (and no mirror at {args.mirror}): {', '.join(missing[:3])} ...", file=sys.stderr)
        return 2
    t0 = time.time()
    result = run(cache, args.episodes, args.seed)
    result["seconds"] = time.time() - t0
    Path(args.out).write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    table = markdown(result)
    print(table)
    doc = Path(args.doc)
    if doc.is_file() and MARK_BEGIN in doc.read_text():
        text = doc.read_text()
        head, _, rest = text.partition(MARK_BEGIN)
        _, _, tail = rest.partition(MARK_END)
        doc.write_text(f"{head}{MARK_BEGIN}\n{table}\n{MARK_END}{tail}")
        print(f"updated {doc}")
    print(f"wrote {args.out} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
