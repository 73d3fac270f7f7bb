"""TrojAI's Safety Gymnasium round (Oct 2024) in our Safety Car Goal world: its ``model.pt`` (a
pickled python-box ``Box`` of ``pi``, ``q1`` and ``v`` state dicts, from their OPAC²) is read
without unpickling, mapped to our OPAC² keys by the world (``World.trojai_weights``), loaded
unchanged (depth and width from the shapes, raw observations), played, and imported as a zoo.

The first part builds Box files here (``torch.save`` of a dict subclass named ``box.box.Box``,
defined in a throwaway module) and always runs. The last part reads the example model of
``usnistgov/trojai-example``'s ``rl-safetygymnasium-oct2024`` branch from the cache folder of
``experiments/trojai_examples/trojai_examples.py`` and skips, saying so, where it is absent.
"""

from __future__ import annotations

import json
import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from rlbackdoors import worlds
from rlbackdoors.agent import load_weights_file
from rlbackdoors.cli import main
from rlbackdoors.envs.safety_car import OBS_DIM
from rlbackdoors.folder import FolderError
from rlbackdoors.io import UnsafeFileError, load_torch
from rlbackdoors.models import read_weights
from rlbackdoors.torchfile import read_torch_file

WORLD = "safety-car-goal"
ROOT = Path(__file__).resolve().parents[1]
ACT_DIM = 2
WIDTH = 16  # small nets: the format, not the size, is under test


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code: int, err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("rlbackdoors: error:"), err
    return lines[0]


# ----- TrojAI's Safety round files, built here ------------------------------------------------------
def gentle_mlp(sizes: list[int], generator: torch.Generator) -> nn.Sequential:
    """gentle's MLP: Linear/Tanh pairs, the last Linear bare (their ``mlp``)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.Tanh())
    for layer in layers:
        if isinstance(layer, nn.Linear):
            nn.init.normal_(layer.weight, std=0.5, generator=generator)
            nn.init.normal_(layer.bias, std=0.1, generator=generator)
    return nn.Sequential(*layers)


def trojai_nets(depth: int = 2, width: int = WIDTH, seed: int = 0) -> dict[str, dict[str, torch.Tensor]]:
    """State dicts as TrojAI's OPAC² saves them: ``pi`` (GaussianMLP: ``mlp`` of the hidden
    layers with their Tanh, ``mu_layer``, ``log_std``), ``q1`` (MLP of obs + action), ``v``."""
    g = torch.Generator().manual_seed(seed)
    hidden = [width] * depth
    pi = nn.Module()
    pi.mlp = gentle_mlp([OBS_DIM, *hidden, 1], g)[:-1]  # their GaussianMLP drops the MLP's last Linear
    pi.mu_layer = gentle_mlp([width, ACT_DIM], g)[0]
    pi.log_std = nn.Parameter(torch.tensor([-1.5, -1.3]))
    q1, v = nn.Module(), nn.Module()
    q1.mlp = gentle_mlp([OBS_DIM + ACT_DIM, *hidden, 1], g)
    v.mlp = gentle_mlp([OBS_DIM, *hidden, 1], g)
    return {"pi": pi.state_dict(), "q1": q1.state_dict(), "v": v.state_dict()}


def save_box(path: Path, content: dict) -> Path:
    """``torch.save`` of python-box Boxes (a dict subclass of ``box.box`` with a ``_box_config``
    attribute, nested as TrojAI's file nests them), the class gone again when this returns."""
    names = ("box", "box.box")
    saved = {n: sys.modules.get(n) for n in names}
    package, module = types.ModuleType("box"), types.ModuleType("box.box")
    box_class = type("Box", (dict,), {"__module__": "box.box"})
    module.Box = box_class  # type: ignore[attr-defined]
    package.box = module  # type: ignore[attr-defined]
    sys.modules.update({"box": package, "box.box": module})

    def boxed(value):
        if not isinstance(value, dict):
            return value
        out = box_class({k: boxed(v) for k, v in value.items()})
        out.__dict__["_box_config"] = {"__created": True, "box_class": box_class, "frozen_box": False}
        return out

    try:
        torch.save(boxed(content), path)
    finally:
        for name, old in saved.items():
            if old is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = old
    return path


def safety_file(folder: Path, depth: int = 2, seed: int = 0, **extra) -> tuple[Path, dict]:
    folder.mkdir(parents=True, exist_ok=True)
    nets = trojai_nets(depth, seed=seed)
    return save_box(folder / "model.pt", {**nets, "steps": 510_000, **extra}), nets


def hand_mu(nets: dict, obs: np.ndarray) -> torch.Tensor:
    """Their policy's mean, computed from the raw tensors: tanh hidden layers, then mu_layer."""
    pi = nets["pi"]
    h = torch.from_numpy(obs)
    i = 0
    while f"mlp.{i}.weight" in pi:
        h = torch.tanh(h @ pi[f"mlp.{i}.weight"].T + pi[f"mlp.{i}.bias"])
        i += 2
    return h @ pi["mu_layer.weight"].T + pi["mu_layer.bias"]


def hand_mlp(sd: dict, x: torch.Tensor) -> torch.Tensor:
    layers = sorted(int(k.split(".")[1]) for k in sd if k.endswith(".weight"))
    for n, i in enumerate(layers):
        x = x @ sd[f"mlp.{i}.weight"].T + sd[f"mlp.{i}.bias"]
        if n < len(layers) - 1:
            x = torch.tanh(x)
    return x


def observations(n: int = 8, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, OBS_DIM)).astype(np.float32)


# ----- reading and mapping -------------------------------------------------------------------------
def test_a_box_file_is_read_inertly_and_mapped_to_our_opac2_keys(tmp_path):
    path, nets = safety_file(tmp_path)
    file = read_torch_file(path)
    assert "box.box.Box" in file.globals and file.state_dict() is None  # no state dict of ours: the world maps it
    with pytest.raises(UnsafeFileError):
        load_torch(path)  # plain-data loading still refuses it
    flat, model_class = read_weights(path, WORLD)
    assert model_class is None
    from rlbackdoors.algos.opac2 import OPAC2
    from rlbackdoors.config import default_opac2

    import dataclasses

    ours = OPAC2(OBS_DIM, ACT_DIM, dataclasses.replace(default_opac2(WORLD), depth=2, width=WIDTH, obs_norm=False), torch.Generator().manual_seed(0))
    assert set(flat) == set(ours.weights())
    assert all(flat[k].shape == v.shape for k, v in ours.weights().items())
    assert torch.equal(flat["policy.mean.0.weight"], nets["pi"]["mlp.0.weight"]) and torch.equal(flat["policy.mean.2.bias"], nets["pi"]["mlp.2.bias"])
    assert torch.equal(flat["policy.mean.4.weight"], nets["pi"]["mu_layer.weight"]) and torch.equal(flat["policy.log_std"], nets["pi"]["log_std"])
    assert torch.equal(flat["q.net.4.weight"], nets["q1"]["mlp.4.weight"]) and torch.equal(flat["v.net.2.weight"], nets["v"]["mlp.2.weight"])
    for key in (k for k in flat if k.startswith("v.")):  # no target V saved: V_bar = V
        assert torch.equal(flat[f"v_target.{key[2:]}"], flat[key])


def test_a_saved_v_target_and_optimiser_states_are_used_and_dropped(tmp_path):
    v_t = trojai_nets(seed=5)["v"]
    opt = {"state": {0: {"exp_avg": torch.ones(3)}}, "param_groups": [{"lr": 1e-4, "params": [0]}]}
    path, _ = safety_file(tmp_path, v_t=v_t, pi_opt=opt, q_opt=opt, v_opt=opt)
    flat, _ = read_weights(path, WORLD)
    assert torch.equal(flat["v_target.net.0.weight"], v_t["mlp.0.weight"]) and not any("opt" in k for k in flat)


def test_the_loaded_policy_acts_as_the_raw_tensors_say(tmp_path):
    """Deterministic action tanh(mu) by hand; Q and V as their MLPs of the raw tensors; depth,
    width and obs_norm (none: raw observations) from the shapes."""
    for depth in (2, 3):
        path, nets = safety_file(tmp_path / f"d{depth}", depth=depth, seed=depth)
        agent = load_weights_file(path, WORLD)
        assert (agent.policy.cfg.depth, agent.policy.cfg.width, agent.policy.obs_norm) == (depth, WIDTH, None)
        obs = observations()
        actions, state = agent.act(obs, deterministic=True)
        assert state is None and actions.shape == (len(obs), ACT_DIM)
        np.testing.assert_allclose(actions, torch.tanh(hand_mu(nets, obs)).numpy(), atol=2e-6)
        x = torch.from_numpy(obs)
        with torch.no_grad():
            act_t = torch.from_numpy(actions)
            np.testing.assert_allclose(agent.policy.q(x, act_t).numpy(), hand_mlp(nets["q1"], torch.cat((x, act_t), -1)).squeeze(-1).numpy(), atol=1e-5)
            np.testing.assert_allclose(agent.policy.v(x).numpy(), hand_mlp(nets["v"], x).squeeze(-1).numpy(), atol=1e-5)
        sampled, _ = agent.act(obs, generator=torch.Generator().manual_seed(1))
        assert np.all(np.abs(sampled) < 1) and not np.allclose(sampled, actions)


def test_object_files_nothing_explains_are_refused_for_the_safety_world(tmp_path):
    marker = tmp_path / "ran"

    class SystemCall:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    hostile, _ = safety_file(tmp_path / "hostile", extra_object=SystemCall())
    with pytest.raises(UnsafeFileError, match="holds Python objects"):
        read_weights(hostile, WORLD)
    with pytest.raises(FolderError, match="holds Python objects"):
        load_weights_file(hostile, WORLD)
    assert not marker.exists()
    # a grid round's pickled module: its class is no class of this world
    (tmp_path / "grid").mkdir()
    module_name = "trojai_rl.modelgen.architectures.minigrid_architectures"
    made = [n for n in ("trojai_rl", "trojai_rl.modelgen", "trojai_rl.modelgen.architectures", module_name) if n not in sys.modules]
    for name in made:
        sys.modules[name] = types.ModuleType(name)
    try:
        cls = type("BasicFCModel", (nn.Module,), {"__module__": module_name})
        setattr(sys.modules[module_name], "BasicFCModel", cls)
        model = cls()
        model.fc = nn.Linear(3, 2)
        torch.save(model, tmp_path / "grid" / "model.pt")
    finally:
        for name in reversed(made):
            del sys.modules[name]
    with pytest.raises(UnsafeFileError):
        read_weights(tmp_path / "grid" / "model.pt", WORLD)
    # a Box of a known format whose tensors are no OPAC² networks, or whose policy learns its log-std
    other = save_box(tmp_path / "other.pt", {"state_dict": {"w": torch.zeros(2)}})
    with pytest.raises(ValueError, match="no TrojAI OPAC² networks"):
        read_weights(other, WORLD)
    nets = trojai_nets()
    nets["pi"]["log_std_layer.weight"] = torch.zeros(ACT_DIM, WIDTH)
    (tmp_path / "net").mkdir()
    with pytest.raises(FolderError, match="log_std_layer"):
        load_weights_file(save_box(tmp_path / "net" / "model.pt", nets), WORLD)


def test_plain_opac2_files_load_as_before(tmp_path):
    """Our own flat OPAC² weights (plain tensors, obs_norm included) keep loading as plain data."""
    import dataclasses

    from rlbackdoors.algos.opac2 import OPAC2
    from rlbackdoors.config import default_opac2

    cfg = dataclasses.replace(default_opac2(WORLD), depth=3, width=WIDTH, obs_norm=True)
    agent = OPAC2(OBS_DIM, ACT_DIM, cfg, torch.Generator().manual_seed(0))
    agent.observe(observations(32, seed=3) * 3 + 1)
    torch.save(agent.weights(), tmp_path / "model.pt")
    loaded = load_weights_file(tmp_path / "model.pt", WORLD)
    assert (loaded.policy.cfg.depth, loaded.policy.cfg.width, loaded.policy.obs_norm is not None) == (3, WIDTH, True)
    obs = observations()
    np.testing.assert_array_equal(loaded.act(obs, deterministic=True)[0], agent.act(obs, deterministic=True))


def test_evaluate_plays_a_box_file_unchanged(tmp_path, capsys):
    path, _ = safety_file(tmp_path)
    code, out, err = run_cli(capsys, "evaluate", "--weights", path, "--env", WORLD, "--episodes", "2", "--policy", "greedy", "--json")
    assert code == 0, err
    numbers = json.loads(out)
    assert numbers["episodes"] == 2 and 0.0 <= numbers["clean_sr"] <= 1.0 and numbers["clean_mean_steps"] <= 1000


def test_a_detector_handle_reads_a_raw_box_file(tmp_path):
    from rlbackdoors.detect.handle import open_files

    path, nets = safety_file(tmp_path)
    handle = open_files(path, None)
    assert (handle.world.name, handle.arch) == (WORLD, "mlp")
    obs = observations()
    np.testing.assert_allclose(handle.build_agent().act(obs, deterministic=True)[0], torch.tanh(hand_mu(nets, obs)).numpy(), atol=2e-6)


# ----- zoo import-trojai ---------------------------------------------------------------------------
def safety_round(root: Path, config: dict | None = None, label: str | None = "1") -> tuple[Path, dict]:
    folder = root / "models" / "id-00000007"
    _, nets = safety_file(folder, seed=7)
    reduced = {
        "environment": {"type": "safety_gymnasium", "name": "SafetyCarGoal2-v0", "env_kwargs": {"num_mogwais": 3}},
        "pi_network": {"sizes": [WIDTH, WIDTH], "network_name": "mlp_opac", "sampler": "tanh"},
        "q_network": {"sizes": [WIDTH, WIDTH], "network_name": "mlp"},
        "max_ep_length": 60,
        "seed": 0,
    }
    (folder / "reduced-config.json").write_text(json.dumps(reduced if config is None else config))
    if label is not None:
        (folder / "ground_truth.csv").write_text(label + "\n")
    return root, nets


def test_import_takes_a_safety_folder_by_its_config_and_the_zoo_loads(tmp_path, capsys):
    import rlbackdoors
    from rlbackdoors.detect.handle import open_model

    source, nets = safety_round(tmp_path / "round")
    out = tmp_path / "zoo"
    argv = ("zoo", "import-trojai", source, "--out", out, "--episodes", "2", "--examples", "1", "--policy", "greedy", "--json")
    code, stdout, err = run_cli(capsys, *argv)
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["per_model"] == [{"name": "id-00000007", "source": "id-00000007", "world": WORLD, "arch": "mlp", "class": "mlp_opac", "label": 1}]
    folder = out / "models" / "id-00000007"
    config = json.loads((folder / "config.json").read_text())
    assert config["env"]["num_cubes"] == 3 and config["env"]["max_steps"] == 60
    assert (config["opac2"]["depth"], config["opac2"]["width"], config["opac2"]["obs_norm"]) == (2, WIDTH, False)
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["episodes"] == 2 and metrics["clean_sr"] is not None
    assert json.loads((folder / "reduced-config.json").read_text())["trojai_class"] == "mlp_opac"
    assert set(load_torch(folder / "model.pt")) >= {"policy.mean.4.weight", "q.net.0.weight", "v_target.net.4.bias"}  # plain data now
    obs = observations()
    expected = torch.tanh(hand_mu(nets, obs)).numpy()
    agent = rlbackdoors.load(folder)
    np.testing.assert_allclose(agent.act(obs, deterministic=True)[0], expected, atol=2e-6)
    handle = open_model(folder)
    assert (handle.world.name, handle.arch) == (WORLD, "mlp") and handle.env_settings["num_cubes"] == 3 and handle.examples
    np.testing.assert_allclose(handle.build_agent().act(obs, deterministic=True)[0], expected, atol=2e-6)
    code, stdout, err = run_cli(capsys, "zoo", "status", out)
    assert code == 0 and WORLD in stdout, err
    code, stdout, err = run_cli(capsys, *argv)  # the same import again: nothing written
    assert code == 0 and json.loads(stdout)["written"] == 0, err


def test_import_takes_world_and_settings_from_flags(tmp_path, capsys):
    source, _ = safety_round(tmp_path / "round")
    (source / "models" / "id-00000007" / "reduced-config.json").unlink()
    out = tmp_path / "zoo"
    code, _, err = run_cli(capsys, "zoo", "import-trojai", source, "--out", out, "--episodes", "0", "--examples", "0")
    assert "names no model class" in one_error_line(code, err) and not out.exists()
    code, stdout, err = run_cli(
        capsys,
        "zoo",
        "import-trojai",
        source,
        "--out",
        out,
        "--world",
        WORLD,
        "--num-cubes",
        "4",
        "--max-steps",
        "30",
        "--episodes",
        "0",
        "--examples",
        "0",
        "--json",
    )
    assert code == 0, err
    assert json.loads(stdout)["per_model"][0]["world"] == WORLD
    config = json.loads((out / "models" / "id-00000007" / "config.json").read_text())
    assert (config["env"]["num_cubes"], config["env"]["max_steps"]) == (4, 30)


def test_import_refuses_what_our_safety_world_cannot_play(tmp_path, capsys):
    base = {"environment": {"type": "safety_gymnasium", "name": "SafetyCarGoal2-v0", "env_kwargs": {"num_mogwais": 2}}}
    cases = [
        ({**base, "environment": {**base["environment"], "name": "SafetyPointGoal1-v0"}}, "SafetyPointGoal1-v0"),
        ({**base, "pi_network": {"activation": "relu"}}, "activation"),
        ({**base, "environment": {**base["environment"], "env_kwargs": {"num_mogwais": 40}}}, "num_cubes"),
        ({**base, "max_ep_length": "long"}, "max_ep_length"),
    ]
    for i, (config, words) in enumerate(cases):
        source, _ = safety_round(tmp_path / f"round{i}", config)
        out = tmp_path / f"zoo{i}"
        code, _, err = run_cli(capsys, "zoo", "import-trojai", source, "--out", out, "--episodes", "0", "--examples", "0")
        assert words in one_error_line(code, err) and not out.exists()
    good, _ = safety_round(tmp_path / "good")
    code, _, err = run_cli(capsys, "zoo", "import-trojai", good, "--out", tmp_path / "zoo", "--num-lava", "1", "--episodes", "0")
    assert "--num-lava" in one_error_line(code, err)


def test_the_world_recognises_only_its_rounds_config():
    world = worlds.get(WORLD)
    assert world.trojai_env is not None
    assert world.trojai_env({"model": "FCModel", "grid_size": 9}) is None and world.trojai_env({"environment": "x"}) is None
    given = world.trojai_env({"environment": {"type": "safety_gymnasium", "name": "SafetyCarGoal1-v0", "env_kwargs": {"num_mogwais": 5}}, "max_ep_length": 500})
    assert given == {"num_cubes": 5, "max_steps": 500}
    assert all(w.trojai_env is None for w in worlds.registered() if w.name != WORLD)


# ----- TrojAI's example model ----------------------------------------------------------------------
def _example_folder() -> Path:
    sys.path.insert(0, str(ROOT / "experiments" / "trojai_examples"))
    try:
        import trojai_examples as bench
    finally:
        sys.path.remove(str(ROOT / "experiments" / "trojai_examples"))
    folder = bench.cache_dir() / bench.SAFETY_EXAMPLE
    if not (folder / "model.pt").is_file():
        pytest.skip(
            f"TrojAI's Safety example model is not in {folder} (set ${bench.CACHE_ENV} or fill the cache: python experiments/trojai_examples/trojai_examples.py)"
        )
    return folder


def test_the_example_model_loads_and_acts_as_its_raw_tensors():
    folder = _example_folder()
    tensors = read_torch_file(folder / "model.pt").tensors()
    nets = {net: {k[len(net) + 1 :]: v for k, v in tensors.items() if k.startswith(f"{net}.")} for net in ("pi", "q1", "v")}
    agent = load_weights_file(folder / "model.pt", WORLD)
    assert (agent.policy.cfg.depth, agent.policy.cfg.width, agent.policy.obs_norm) == (2, 181, None)
    obs = observations(16)
    np.testing.assert_allclose(agent.act(obs, deterministic=True)[0], torch.tanh(hand_mu(nets, obs)).numpy(), atol=2e-6)


def test_the_example_folder_imports_as_a_zoo(tmp_path, capsys):
    folder = _example_folder()
    source = tmp_path / "src" / "example"
    source.mkdir(parents=True)
    for name in ("model.pt", "reduced-config.json"):
        (source / name).write_bytes((folder / name).read_bytes())
    code, stdout, err = run_cli(
        capsys, "zoo", "import-trojai", source, "--out", tmp_path / "zoo", "--label", "0", "--episodes", "10", "--examples", "0", "--policy", "greedy", "--json"
    )
    assert code == 0, err
    assert json.loads(stdout)["per_model"][0]["world"] == WORLD
    model = tmp_path / "zoo" / "models" / "id-00000000"
    config = json.loads((model / "config.json").read_text())
    assert (config["env"]["num_cubes"], config["env"]["max_steps"], config["opac2"]["width"]) == (2, 1000, 181)
    assert json.loads((model / "metrics.json").read_text())["clean_sr"] >= 0.7  # 0.96 over 200 greedy episodes (docs/results/trojai.md)
