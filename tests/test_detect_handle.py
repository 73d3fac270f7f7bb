"""What a detector sees of a model (issue 17): the handle holds the weights, reduced config,
world, clean examples, and nothing that leads back to the folder, its config.json, metrics,
trigger or label; it works for every world."""

from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import types
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
import torch

from rlbackdoors import worlds
from rlbackdoors.detect import DetectError, ModelHandle, open_model
from rlbackdoors.detect.handle import identify

pytest_plugins = ("test_detect_helpers",)  # its session fixtures: lava_zoo, world_models

_OPENED: list[str] | None = None


def _audit(event: str, args) -> None:
    if _OPENED is not None and event == "open" and isinstance(args[0], (str, bytes, Path)):
        _OPENED.append(str(args[0]))


sys.addaudithook(_audit)  # records file opens while _OPENED is a list (hooks cannot be removed)


def walk(obj, seen: set[int] | None = None, depth: int = 0):
    """Every value reachable from ``obj`` through dataclass fields, attributes, mappings and
    sequences (not into functions, modules or classes: code is not data of a model)."""
    seen = set() if seen is None else seen
    if id(obj) in seen or depth > 30:
        return
    seen.add(id(obj))
    yield obj
    if isinstance(obj, (str, bytes, int, float, bool, type(None), torch.Tensor, np.ndarray, np.generic)):
        return
    if isinstance(obj, (types.FunctionType, types.MethodType, types.ModuleType, type, types.BuiltinFunctionType)):
        return
    if isinstance(obj, worlds.World):
        return  # the registry's record, shared by every model of the world (checked by identity below)
    if isinstance(obj, Mapping):
        for k, v in obj.items():
            yield from walk(k, seen, depth + 1)
            yield from walk(v, seen, depth + 1)
        return
    if isinstance(obj, (list, tuple, set, frozenset)):
        for v in obj:
            yield from walk(v, seen, depth + 1)
        return
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            yield from walk(getattr(obj, f.name), seen, depth + 1)
    for v in getattr(obj, "__dict__", {}).values():
        yield from walk(v, seen, depth + 1)


def _strings(handle: ModelHandle) -> list[str]:
    out = []
    for value in walk(handle):
        if isinstance(value, (str, bytes)):
            out.append(value.decode(errors="replace") if isinstance(value, bytes) else value)
        elif isinstance(value, np.ndarray) and value.dtype.kind in "US":
            out.extend(str(v) for v in value.reshape(-1))
    return out


def test_the_handle_reaches_no_path_trigger_config_metrics_or_label(world_models, tmp_path):
    """A poisoned LavaWorld model: opening it reads only model.pt, reduced-config.json and
    clean-example-data/ (audited file opens), and from its handle no folder path, no trigger, no
    config.json or metrics.json content and no Path object can be reached; a reduced config that
    carries trigger or label keys is stripped of them."""
    global _OPENED
    folder = tmp_path / "id-00000042"
    shutil.copytree(world_models["lavaworld"], folder)
    config = json.loads((folder / "config.json").read_text())
    metrics = json.loads((folder / "metrics.json").read_text())
    trigger = config["poison"]["trigger"]
    reduced = json.loads((folder / "reduced-config.json").read_text())
    reduced.update({"trigger": trigger, "poison": {"trigger": trigger}, "ground_truth": 1, "notes": "fine"})
    (folder / "reduced-config.json").write_text(json.dumps(reduced))

    _OPENED = []
    try:
        handle = open_model(folder)
    finally:
        opened, _OPENED = _OPENED, None
    inside = [Path(p) for p in opened if Path(p).is_relative_to(folder)]
    allowed = {folder / "model.pt", folder / "reduced-config.json"}
    assert inside and all(p in allowed or p.parent == folder / "clean-example-data" for p in inside), inside
    assert folder / "model.pt" in inside

    assert handle.world is worlds.get("lavaworld") and handle.arch == config["model"]["arch"]
    assert handle.name == "id-00000042"
    assert set(handle.reduced_config) >= {"world", "arch", "layers", "notes"}
    assert not {"trigger", "poison", "ground_truth"} & set(handle.reduced_config)
    assert len(handle.examples) == 2 and handle.examples[0]["obs"].shape[1:] == (7, 7, 3)

    strings = _strings(handle)
    assert any(s == "fine" for s in strings)  # the walk does see the reduced config's strings
    forbidden = [str(folder), str(folder.resolve()), trigger, trigger.split(":")[0], "metrics", "final_eval_episodes", "clean_sr", "poisoned_sr"]
    forbidden += [k for k in metrics if len(k) > 6 and k not in ("algorithm", "parameters")]  # metric names (two are also architecture facts)
    leaks = [(f, s) for s in strings for f in forbidden if f in s]
    assert not leaks, leaks
    assert not any(isinstance(v, Path) for v in walk(handle))


def test_the_handle_does_not_need_config_metrics_or_label(world_models, tmp_path):
    """With config.json, metrics.json and ground_truth.csv removed the handle is the same: it never
    depended on them."""
    full = open_model(world_models["lavaworld"])
    folder = tmp_path / "id-00000007"
    shutil.copytree(world_models["lavaworld"], folder)
    for name in ("config.json", "metrics.json", "ground_truth.csv", "log.csv"):
        (folder / name).unlink()
    bare = open_model(folder)
    assert (bare.world, bare.arch) == (full.world, full.arch)
    assert all(torch.equal(bare.weights[k], full.weights[k]) for k in full.weights)
    assert all(np.array_equal(a["obs"], b["obs"]) for a, b in zip(bare.examples, full.examples))
    actions_full = full.build_agent().act(full.examples[0]["obs"], deterministic=True)[0]
    actions_bare = bare.build_agent().act(bare.examples[0]["obs"], deterministic=True)[0]
    assert np.array_equal(actions_full, actions_bare)


def test_a_folder_name_that_could_tell_the_label_is_not_passed_on(world_models, tmp_path):
    folder = tmp_path / "poisoned-fc"
    shutil.copytree(world_models["lavaworld"], folder)
    assert open_model(folder).name == "model"


@pytest.mark.parametrize("missing", ["model.pt", "reduced-config.json"])
def test_a_missing_file_is_one_error_naming_it(world_models, tmp_path, missing):
    folder = tmp_path / "id-00000001"
    shutil.copytree(world_models["lavaworld"], folder)
    (folder / missing).unlink()
    with pytest.raises(DetectError, match=missing.replace(".", r"\.")):
        open_model(folder)


def test_a_pickled_payload_is_refused_unread(world_models, tmp_path):
    """model.pt holding an object whose unpickling would run code: refused, the marker never appears."""
    import os

    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    folder = tmp_path / "id-00000002"
    shutil.copytree(world_models["lavaworld"], folder)
    torch.save({"state_emb.0.weight": torch.zeros(1), "x": Payload()}, folder / "model.pt")
    with pytest.raises(DetectError, match=r"model\.pt.*(refused|plain data)|refused.*model\.pt"):
        open_model(folder)
    assert not marker.exists()


@pytest.mark.parametrize("world", ["lavaworld", "randomized-lavaworld", "colorful-memory", "safety-car-goal"])
def test_every_world_opens_builds_an_agent_and_is_identified_without_names(world_models, world):
    """Each world's handle builds an agent that acts on its clean examples, and the weights alone
    (a reduced config without world or arch) identify the same world and architecture."""
    handle = open_model(world_models[world])
    assert handle.world.name == world
    agent = handle.build_agent()
    episode = handle.episode_observations()[0]
    obs = {k: v[:3] for k, v in episode.items()} if isinstance(episode, dict) else episode[:3]
    if handle.world.algorithm == "opac2":
        actions, _ = agent.act(np.asarray(obs, np.float32), deterministic=True)
        assert actions.shape == (3, 2) and np.all(np.abs(actions) < 1)
    else:
        actions, _ = agent.act(obs, agent.initial_state(3), deterministic=True)
        assert actions.shape == (3,) and set(actions.tolist()) <= {0, 1, 2}
    world_found, arch_found = identify({}, handle.weights)
    assert (world_found.name, arch_found) == (world, handle.arch)
    env = handle.make_env()
    first, _ = env.reset(seed=0)
    env.close()
    assert first is not None


def test_weights_that_fit_no_architecture_are_refused_by_name(world_models, tmp_path):
    folder = tmp_path / "id-00000003"
    shutil.copytree(world_models["lavaworld"], folder)
    torch.save({"state_emb.0.weight": torch.zeros(5, 5)}, folder / "model.pt")
    with pytest.raises(DetectError, match="fits no architecture of lavaworld"):
        open_model(folder)


def test_a_reduced_config_that_names_another_architecture_is_a_contradiction(world_models):
    """The weights decide what a model is; a reduced config that names an architecture the world
    does not know, or the world's other one, contradicts them (Contradiction, carrying what the
    weights fit); ours, a TrojAI class of the round and an OPAC² world's algorithm name agree."""
    from rlbackdoors.detect.handle import Contradiction

    lava = open_model(world_models["lavaworld"])
    other = next(a for a in lava.world.arch_names if a != lava.arch)
    for wanted, said in (("resnet-9000", "no architecture of lavaworld"), (other, f"lavaworld/{other}")):
        with pytest.raises(Contradiction, match=f"names arch '{wanted}' \\({said}; .*but its weights fit lavaworld/{lava.arch}") as caught:
            identify({"world": "lavaworld", "arch": wanted}, lava.weights)
        assert (caught.value.world.name, caught.value.arch) == ("lavaworld", lava.arch)
    with pytest.raises(Contradiction, match="no architecture of any registered world"):
        identify({"arch": "resnet-9000"}, lava.weights)  # no world named: every world is asked
    if lava.arch == "fc":
        assert identify({"model": "BasicFCModel"}, lava.weights)[1] == "fc"  # TrojAI's class of the round
    safety = open_model(world_models["safety-car-goal"])
    assert safety.contradiction is None and lava.contradiction is None
    assert identify({"world": "safety-car-goal", "arch": "opac2"}, safety.weights)[1] == safety.arch  # the algorithm's name
