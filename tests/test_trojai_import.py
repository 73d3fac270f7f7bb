"""TrojAI both ways: their files read without running them, their architectures loaded unchanged,
their model folders imported as a zoo that evaluation, the report and the detectors run on.

The first part builds its own files (hostile pickles, TrojAI's three file formats with random
weights) and always runs. The second reads the example models of ``usnistgov/trojai-example``'s
RL branches from the cache folder of ``experiments/trojai_examples/trojai_examples.py``
(``$RLBACKDOORS_TROJAI_EXAMPLES``, default ``~/.cache/rlbackdoors/trojai-example``; fill it with
that script) and skips, saying so, where they are absent.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import json
import os
import pickle
import shutil
import sys
import types
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from rlbackdoors.agent import load_weights_file
from rlbackdoors.cli import main
from rlbackdoors.io import UnsafeFileError, load_torch
from rlbackdoors.torchfile import Inert, read_torch_file

ROOT = Path(__file__).resolve().parents[1]
pytest_plugins = ("test_detect_helpers",)  # its session fixture lava_zoo: folders that train wrote
MARKER_ENV = "RLBACKDOORS_TEST_MARKER"


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(code: int, err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("rlbackdoors: error:"), err
    return lines[0]


def tree_digest(folder: Path) -> dict[str, str]:
    """Every file's sha256 (the lock file says who held it last, and is left out)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".lock"}


# ----- hostile pickles ------------------------------------------------------------------------------
class SystemCall:
    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class EvalCall:
    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        import builtins

        return (builtins.eval, (f"__import__('pathlib').Path({self.marker!r}).touch()",))


class SetStateCall:
    """BUILD with state on an object whose class would act on it."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path, (self.marker,), {"touch": True})


def test_a_reduce_to_os_system_or_eval_yields_inert_placeholders_and_runs_nothing(tmp_path):
    marker_system, marker_eval = tmp_path / "ran-system", tmp_path / "ran-eval"
    weights = {"w": torch.arange(6, dtype=torch.float32).reshape(2, 3)}
    path = tmp_path / "hostile.pt"
    torch.save({"weights": weights, "a": SystemCall(marker_system), "b": EvalCall(marker_eval), "c": SetStateCall(tmp_path / "p")}, path)
    # (the payloads really would run: a full torch.load executes them)
    file = read_torch_file(path)
    assert not marker_system.exists() and not marker_eval.exists()
    a, b, c = file.root["a"], file.root["b"], file.root["c"]
    assert isinstance(a, Inert) and a.global_name in ("posix.system", "os.system", "nt.system")
    assert a.args == (f"touch {marker_system}",)
    assert isinstance(b, Inert) and b.global_name == "builtins.eval" and "touch" in b.args[0]
    assert isinstance(c, Inert) and c.state == {"touch": True}
    assert {"builtins.eval", a.global_name} <= set(file.globals)
    assert torch.equal(file.tensors()["weights.w"], weights["w"])
    # Reading is not accepting: every loader still refuses a file whose objects no format explains.
    for world in ("lavaworld", "randomized-lavaworld", "colorful-memory"):
        with pytest.raises(ValueError, match="holds Python objects|not a torch file of plain data"):  # UnsafeFileError is one
            load_weights_file(path, world, None)
    with pytest.raises(TypeError, match="placeholder"):
        pickle.dumps(a)
    assert not marker_system.exists() and not marker_eval.exists()


def _archive(data: bytes, storages: dict[str, bytes] | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("archive/data.pkl", data)
        z.writestr("archive/byteorder", "little")
        for key, raw in (storages or {}).items():
            z.writestr(f"archive/data/{key}", raw)
    return buf.getvalue()


@pytest.mark.parametrize("protocol", [0, 1, 2, 4, 5])
def test_every_pickle_protocol_of_a_payload_is_inert(tmp_path, protocol):
    """INST/OBJ (protocols 0-1), REDUCE, NEWOBJ, BUILD, SETITEMS and APPENDS on placeholders."""
    marker = tmp_path / "ran"

    class Evil(dict):  # a dict subclass: pickled with SETITEMS on its (placeholder) instance
        def __reduce_ex__(self, proto):
            return (os.system, (f"touch {marker}",), None, None, iter([("k", 1)]))

    class EvilList(list):
        def __reduce_ex__(self, proto):
            return (eval, (f"__import__('pathlib').Path({str(marker)!r}).touch()",), {"x": 1}, iter([1, 2]), None)

    data = pickle.dumps({"d": Evil(), "l": EvilList(), "s": {1, 2}}, protocol=protocol)
    path = tmp_path / "raw.pt"
    path.write_bytes(_archive(data))
    file = read_torch_file(path)
    assert not marker.exists()
    assert file.root["d"].items == {"k": 1} and file.root["l"].elements == [1, 2] and file.root["l"].state == {"x": 1}
    assert file.root["s"] == {1, 2}


def test_malformed_archives_are_one_clear_value_error(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a torch zip archive"):
        read_torch_file(tmp_path / "junk.pt")
    (tmp_path / "cut.pt").write_bytes(_archive(pickle.dumps({"a": [1, 2]})[:-1]))  # a pickle cut short
    with pytest.raises(ValueError, match="cannot read"):
        read_torch_file(tmp_path / "cut.pt")
    torch.save({"w": torch.zeros(4)}, tmp_path / "ok.pt")
    raw = zipfile.ZipFile(tmp_path / "ok.pt")
    entries = {n: raw.read(n) for n in raw.namelist()}
    key = next(n for n in entries if "/data/" in n)
    entries[key] = entries[key][:-4]  # the storage is 4 bytes short
    with zipfile.ZipFile(tmp_path / "short.pt", "w") as z:
        for name, value in entries.items():
            z.writestr(name, value)
    with pytest.raises(ValueError, match="holds 12 bytes"):
        read_torch_file(tmp_path / "short.pt")


def test_tensors_read_inertly_equal_torch_load_bit_for_bit(tmp_path):
    base = torch.randn(6, 5, generator=torch.Generator().manual_seed(0))
    state = {
        "f32": base,
        "view": base[1:4, ::2],  # a strided view sharing the storage
        "f64": base.double(),
        "f16": base.half(),
        "bf16": base.bfloat16(),
        "i64": torch.arange(7),
        "i8": torch.tensor([-3, 4], dtype=torch.int8),
        "u8": torch.tensor([1, 255], dtype=torch.uint8),
        "bool": torch.tensor([True, False, True]),
        "scalar": torch.tensor(3.5),
        "empty": torch.zeros(0, 3),
        "param": nn.Parameter(torch.ones(2)),
    }
    torch.save(state, tmp_path / "s.pt")
    ref = torch.load(tmp_path / "s.pt", weights_only=True)
    got = read_torch_file(tmp_path / "s.pt").state_dict()
    assert got is not None and set(got) == set(ref)
    for key in ref:
        assert got[key].dtype == ref[key].dtype and got[key].shape == ref[key].shape and torch.equal(got[key], ref[key]), key


# ----- TrojAI's three grid formats, built here ------------------------------------------------------
def _fake_module(name: str):
    """A module ``name`` in sys.modules for as long as pickling needs it."""
    parts = name.split(".")
    made = []
    for i in range(1, len(parts) + 1):
        dotted = ".".join(parts[:i])
        if dotted not in sys.modules:
            sys.modules[dotted] = types.ModuleType(dotted)
            made.append(dotted)
    return made


def save_module_as(tmp_path: Path, module_name: str, class_name: str, build) -> Path:
    """``torch.save`` of a whole module whose class lives in ``module_name`` (TrojAI's
    LavaWorld round pickled its models this way); the class is gone again when this returns."""
    made = _fake_module(module_name)
    try:
        cls = type(class_name, (nn.Module,), {"__module__": module_name})
        setattr(sys.modules[module_name], class_name, cls)
        model = cls()
        build(model)
        path = tmp_path / "model.pt"
        torch.save(model, path)
    finally:
        for name in reversed(made):
            del sys.modules[name]
    return path


def basic_fc(model: nn.Module) -> None:
    """trojai_rl's BasicFCModel: 147 -> 100 -> 64 (ReLU), actor/critic 64 -> 32 -> out."""
    torch.manual_seed(3)
    model.state_emb = nn.Sequential(nn.Linear(147, 100), nn.ReLU(), nn.Linear(100, 64), nn.ReLU())
    model.actor = nn.Sequential(nn.Linear(64, 32), nn.ReLU(), nn.Linear(32, 3))
    model.critic = nn.Sequential(nn.Linear(64, 32), nn.ReLU(), nn.Linear(32, 1))
    model.recurrent = False
    model.register_buffer("not_saved", torch.ones(1), persistent=False)


def lavaworld_round_file(tmp_path: Path, class_name: str = "BasicFCModel") -> Path:
    return save_module_as(tmp_path, "trojai_rl.modelgen.architectures.minigrid_architectures", class_name, basic_fc)


def test_a_pickled_basic_fc_module_loads_into_fc_and_acts_as_the_raw_tensors_say(tmp_path):
    path = lavaworld_round_file(tmp_path)
    file = read_torch_file(path)
    assert file.model_class() == "BasicFCModel"
    raw = file.state_dict()
    assert raw is not None and "not_saved" not in raw
    assert set(raw) == {f"{n}.{i}.{p}" for n, idx in (("state_emb", (0, 2)), ("actor", (0, 2)), ("critic", (0, 2))) for i in idx for p in ("weight", "bias")}
    with pytest.raises(UnsafeFileError):
        load_torch(path)  # plain-data loading still refuses it
    agent = load_weights_file(path, "lavaworld")  # no arch: the class names it
    assert type(agent.policy).__name__ == "FCModel"
    obs = torch.randint(0, 11, (5, 7, 7, 3), dtype=torch.uint8)
    x = obs.transpose(1, 3).transpose(2, 3).reshape(5, -1).float()  # BasicFCModel.forward, by hand
    h = torch.relu(torch.relu(x @ raw["state_emb.0.weight"].T + raw["state_emb.0.bias"]) @ raw["state_emb.2.weight"].T + raw["state_emb.2.bias"])
    logits = torch.relu(h @ raw["actor.0.weight"].T + raw["actor.0.bias"]) @ raw["actor.2.weight"].T + raw["actor.2.bias"]
    value = (torch.relu(h @ raw["critic.0.weight"].T + raw["critic.0.bias"]) @ raw["critic.2.weight"].T + raw["critic.2.bias"]).squeeze(1)
    got_logits, got_value = agent.policy(obs)
    assert torch.allclose(got_logits, logits, atol=1e-5) and torch.allclose(got_value, value, atol=1e-5)


def test_a_pickled_module_of_an_unknown_class_or_another_world_is_refused(tmp_path, capsys):
    path = lavaworld_round_file(tmp_path, "SomethingElse")
    with pytest.raises(UnsafeFileError, match="holds Python objects"):
        load_weights_file(path, "lavaworld")
    (tmp_path / "b").mkdir()
    basic = lavaworld_round_file(tmp_path / "b")
    with pytest.raises(UnsafeFileError):  # BasicFCModel is the LavaWorld round's class, no other world's
        load_weights_file(basic, "colorful-memory")
    code, _, err = run_cli(capsys, "evaluate", "--weights", path, "--env", "lavaworld", "--episodes", "2")
    assert "holds Python objects" in one_error_line(code, err)


def direction_fc_file(tmp_path: Path) -> tuple[Path, dict]:
    """TrojAI's Randomized LavaWorld format: {"model": "FCModel", "state_dict": ..., spaces ...}."""
    import gymnasium

    from rlbackdoors.models import build_model

    torch.manual_seed(5)
    model = build_model("fc", "randomized-lavaworld")
    for p in model.parameters():
        nn.init.normal_(p, std=0.2)
    space = gymnasium.spaces.Dict({"image": gymnasium.spaces.Box(0, 255, (7, 7, 3), np.uint8), "direction": gymnasium.spaces.Box(0, 3, (1,), int)})
    state = {k: v.clone() for k, v in model.state_dict().items()}
    path = tmp_path / "model.pt"
    torch.save(
        {
            "obs_space": space,
            "action_space": gymnasium.spaces.Discrete(3, seed=1),
            "linear_embedding_dims": (512, 256),
            "state_dict": state,
            "model": "FCModel",
        },
        path,
    )
    return path, state


def test_the_randomized_round_dict_loads_into_direction_fc_and_matches_a_hand_forward(tmp_path):
    path, raw = direction_fc_file(tmp_path)
    with pytest.raises(UnsafeFileError):
        load_torch(path)
    agent = load_weights_file(path, "randomized-lavaworld")
    assert type(agent.policy).__name__ == "DirectionFCModel"
    image = torch.randint(0, 11, (4, 7, 7, 3), dtype=torch.uint8)
    direction = torch.tensor([0, 1, 2, 3])
    # TrojaiDRLBackbone.forward by hand: image channels-first (their wrapper), flatten, 2 ReLU
    # layers, the direction appended, then the heads without a final ReLU
    x = image.permute(0, 3, 1, 2).reshape(4, -1).float()
    for i in (1, 3):
        x = torch.relu(x @ raw[f"state_emb.{i}.weight"].T + raw[f"state_emb.{i}.bias"])
    x = torch.cat([x, direction[:, None].float()], 1)

    def head(name: str) -> torch.Tensor:
        y = x
        for i in (0, 2, 4):
            y = y @ raw[f"{name}.{i}.weight"].T + raw[f"{name}.{i}.bias"]
            y = torch.relu(y) if i < 4 else y
        return y

    logits, value = agent.policy({"image": image, "direction": direction})
    assert torch.allclose(logits, head("actor"), atol=1e-4) and torch.allclose(value, head("critic").squeeze(1), atol=1e-4)


def status_file(tmp_path: Path, class_name: str | None = "GRUCNNActorCriticModel") -> tuple[Path, dict]:
    """TrojAI's Colorful Memory format: an rl-starter-files status dict, the class named in
    reduced-config.json beside it."""
    from rlbackdoors.models import build_model

    torch.manual_seed(11)
    model = build_model("cnn-gru-small", "colorful-memory")
    for p in model.parameters():
        nn.init.normal_(p, std=0.3)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    tmp_path.mkdir(parents=True, exist_ok=True)
    torch.save({"num_frames": 10, "update": 1, "model_state": state, "optimizer_state": {"state": {}, "param_groups": []}}, tmp_path / "model.pt")
    if class_name is not None:
        (tmp_path / "reduced-config.json").write_text(json.dumps({"model": class_name, "grid_size": 7, "max_steps": 250, "random_length": False}))
    return tmp_path / "model.pt", state


def test_the_colorful_memory_status_dict_loads_with_relu_heads_and_matches_a_hand_forward(tmp_path):
    path, raw = status_file(tmp_path / "m")
    agent = load_weights_file(path, "colorful-memory")  # the class from reduced-config.json beside it
    assert type(agent.policy).__name__ == "TrojAIGRUCNN"
    obs = torch.randint(0, 13, (3, 7, 7, 3), dtype=torch.uint8)
    memory = torch.randn(3, 256, generator=torch.Generator().manual_seed(2))
    # GRUCNNActorCriticModel.forward by hand: CNN, two GRU blocks of two layers (memory: block by
    # block, layer by layer, 64 each), heads that end in a ReLU
    x = obs.float().transpose(1, 3).transpose(2, 3)
    x = torch.relu(nn.functional.conv2d(x, raw["state_emb.0.weight"], raw["state_emb.0.bias"]))
    x = nn.functional.max_pool2d(x, 2)
    x = torch.relu(nn.functional.conv2d(x, raw["state_emb.3.weight"], raw["state_emb.3.bias"]))
    x = torch.relu(nn.functional.conv2d(x, raw["state_emb.5.weight"], raw["state_emb.5.bias"])).reshape(3, -1)
    new = []
    for block in range(2):
        for layer in range(2):
            h = memory[:, (block * 2 + layer) * 64 : (block * 2 + layer + 1) * 64]
            x = _gru(x, h, raw, block, layer)
            new.append(x)

    def head(name: str) -> torch.Tensor:
        y = x
        for i in (0, 2, 4):
            y = torch.relu(y @ raw[f"{name}.{i}.weight"].T + raw[f"{name}.{i}.bias"])
        return y

    logits, value, memory_out = agent.policy(obs, memory)
    assert torch.allclose(logits, head("actor"), atol=1e-4) and torch.allclose(value, head("critic").squeeze(1), atol=1e-4)
    assert torch.allclose(memory_out, torch.cat(new, 1), atol=1e-5)
    assert (logits >= 0).all() and (value >= 0).all()
    # the same tensors in cnn-gru-small (no final ReLU) give other logits: the arch matters
    plain = load_weights_file(path, "colorful-memory", "cnn-gru-small")
    assert not torch.allclose(plain.policy(obs, memory)[0], logits)


def _gru(x, h, raw, block: int, layer: int) -> torch.Tensor:
    keys = {n: raw[f"gru.{block}.{n}_l{layer}"] for n in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")}
    gi, gh = x @ keys["weight_ih"].T + keys["bias_ih"], h @ keys["weight_hh"].T + keys["bias_hh"]
    (ir, iz, inn), (hr, hz, hn) = gi.chunk(3, 1), gh.chunk(3, 1)
    r, z = torch.sigmoid(ir + hr), torch.sigmoid(iz + hz)
    return (1 - z) * torch.tanh(inn + r * hn) + z * h


def test_a_status_dict_without_its_class_needs_arch_by_name(tmp_path, capsys):
    path, _ = status_file(tmp_path / "m", class_name=None)
    code, _, err = run_cli(capsys, "evaluate", "--weights", path, "--env", "colorful-memory", "--episodes", "2")
    line = one_error_line(code, err)
    assert "needs --arch" in line and "cnn-gru-small, cnn-gru-trojai" in line
    code, out, _ = run_cli(capsys, "evaluate", "--weights", path, "--env", "colorful-memory", "--arch", "cnn-gru-trojai", "--episodes", "3", "--json")
    assert code == 0 and 0.0 <= json.loads(out)["clean_sr"] <= 1.0


# ----- the importer ------------------------------------------------------------------------------
def synthetic_round(root: Path) -> Path:
    """A round of four LavaWorld-round models (pickled modules), two clean and two poisoned."""
    for i in range(4):
        folder = root / "models" / f"id-{i:08d}"
        folder.mkdir(parents=True)
        made = _fake_module("trojai_rl.modelgen.architectures.minigrid_architectures")
        try:
            cls = type("BasicFCModel", (nn.Module,), {"__module__": "trojai_rl.modelgen.architectures.minigrid_architectures"})
            setattr(sys.modules["trojai_rl.modelgen.architectures.minigrid_architectures"], "BasicFCModel", cls)
            model = cls()
            basic_fc(model)
            for p in model.parameters():
                nn.init.normal_(p, std=0.1, generator=torch.Generator().manual_seed(i))
            torch.save(model, folder / "model.pt")
        finally:
            for name in reversed(made):
                del sys.modules[name]
        (folder / "ground_truth.csv").write_text(f"{i % 2}\n")
        (folder / "config.json").write_text(json.dumps({"grid_size": 9, "max_steps": 250, "trigger": "multiplier"}))
    return root


def test_import_writes_our_layout_leaves_the_source_alone_and_is_idempotent(tmp_path, capsys):
    import rlbackdoors
    from rlbackdoors.zoo.index import read_metadata

    source = synthetic_round(tmp_path / "round")
    before = tree_digest(source)
    out = tmp_path / "zoo"
    argv = ("zoo", "import-trojai", source, "--out", out, "--episodes", "5", "--examples", "1", "--json")
    code, stdout, err = run_cli(capsys, *argv)
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["written"] == 4 and {m["world"] + "/" + m["arch"] for m in summary["per_model"]} == {"lavaworld/fc"}
    assert tree_digest(source) == before  # the TrojAI folder is only read
    for i in range(4):
        folder = out / "models" / f"id-{i:08d}"
        for name in ("model.pt", "config.json", "reduced-config.json", "ground_truth.csv", "metrics.json", "trojai.json", "trojai/config.json"):
            assert (folder / name).is_file(), name
        weights = load_torch(folder / "model.pt")  # plain tensors now: weights_only loads it
        raw = read_torch_file(source / "models" / f"id-{i:08d}" / "model.pt").state_dict()
        assert raw is not None and set(weights) == set(raw) and all(torch.equal(weights[k], raw[k]) for k in raw)
        assert (folder / "ground_truth.csv").read_text().strip() == str(i % 2)
        reduced = json.loads((folder / "reduced-config.json").read_text())
        assert reduced["world"] == "lavaworld" and reduced["arch"] == "fc" and reduced["trojai_class"] == "BasicFCModel" and reduced["env"]["size"] == 9
        agent = rlbackdoors.load(folder)
        assert agent.config.env.size == 9 and agent.config.poison.poisoned == bool(i % 2)
        assert 0.0 <= json.loads((folder / "metrics.json").read_text())["clean_sr"] <= 1.0
    rows = read_metadata(out / "METADATA.csv")
    assert [r["model_name"] for r in rows] == [f"id-{i:08d}" for i in range(4)]
    assert {r["poison.trigger"] for r in rows} == {"unknown"} and {r["converged"] for r in rows} == {"True"}
    # how TrojAI trained them is not known: no training settings, attempt or frames are made up
    unknown = [k for k in rows[0] if k.split(".")[0] in ("train", "ppo") or k in ("attempt", "metrics.frames", "metrics.wall_time_s")]
    assert "train.max_frames" in unknown and "ppo.lr" in unknown and "attempt" in unknown
    assert all(r[k] == "" for r in rows for k in unknown)
    # again: nothing changes
    after = tree_digest(out)
    code, stdout, _ = run_cli(capsys, *argv)
    assert code == 0 and json.loads(stdout)["written"] == 0 and json.loads(stdout)["skipped"] == 4
    assert tree_digest(out) == after and tree_digest(source) == before
    # other options on the same zoo, or another source: refused, nothing touched
    code, _, err = run_cli(capsys, "zoo", "import-trojai", source, "--out", out, "--episodes", "6")
    assert "episodes differs" in one_error_line(code, err)
    code, _, err = run_cli(capsys, "zoo", "run", out)
    assert "imported from TrojAI" in one_error_line(code, err)
    assert tree_digest(out) == after
    # report, status and detectors run on it
    code, _, err = run_cli(capsys, "zoo", "report", out)
    assert code == 0, err
    report = (out / "report" / "report.md").read_text()
    assert "| lavaworld | fc | clean | 2 |" in report and "imported from trojai" in report.lower()
    # nothing was trained here: no empty curve or frames pictures, and none linked
    assert (out / "report" / "scatter.png").is_file() and "scatter.png" in report
    assert not (out / "report" / "curves.png").exists() and "curves.png" not in report and "frames_hist.png" not in report
    code, stdout, _ = run_cli(capsys, "zoo", "status", out)
    assert code == 0 and "lavaworld" in stdout
    for detector in ("constant", "weights"):
        det = tmp_path / f"det-{detector}"
        code, _, err = run_cli(
            capsys, "detect", "fit", "--detector", detector, "--zoo", out, "--out", det, "--param", "min_per_class=1" if detector == "weights" else "value=0.5"
        )
        assert code == 0, err
        code, stdout, err = run_cli(capsys, "detect", "score", det, "--zoo", out, "--json")
        assert code == 0, err
        scored = json.loads(stdout)
        assert scored["failed"] == 0 and len(scored["models"]) == 4  # every model opened and scored
    assert tree_digest(source) == before


def test_import_refuses_unknowns_with_one_line_and_writes_nothing(tmp_path, capsys):
    source = synthetic_round(tmp_path / "round")
    # an unknown class in one folder: the whole import is refused before anything is written
    bad = source / "models" / "id-00000002"
    (bad / "model.pt").unlink()
    save_module_as(bad, "somewhere.else", "MysteryNet", basic_fc)
    out = tmp_path / "zoo"
    code, _, err = run_cli(capsys, "zoo", "import-trojai", source, "--out", out, "--episodes", "0", "--examples", "0")
    assert "MysteryNet" in one_error_line(code, err)
    assert not out.exists()
    # a hostile object beside a known class: refused as before
    (bad / "model.pt").unlink()
    torch.save({"model": "FCModel", "state_dict": {}, "x": SystemCall(tmp_path / "ran")}, bad / "model.pt")
    code, _, err = run_cli(capsys, "zoo", "import-trojai", source, "--out", out, "--episodes", "0", "--examples", "0")
    assert "holds Python objects" in one_error_line(code, err) and not (tmp_path / "ran").exists() and not out.exists()
    # no label, an unknown world, a zoo that is not an import
    (bad / "model.pt").unlink()
    status_file(bad, class_name=None)
    (bad / "ground_truth.csv").unlink()
    code, _, err = run_cli(capsys, "zoo", "import-trojai", bad, "--out", out, "--world", "colorful-memory", "--episodes", "0", "--examples", "0")
    assert "fits several architectures" in one_error_line(code, err)
    # no ground_truth.csv (a test split; the Sep and Oct 2024 examples): imported unlabelled, never as clean
    unlabelled = tmp_path / "unlabelled"
    code, _, err = run_cli(
        capsys, "zoo", "import-trojai", bad, "--out", unlabelled, "--world", "colorful-memory", "--arch", "cnn-gru-trojai", "--episodes", "0", "--examples", "0"
    )
    assert code == 0, err
    from rlbackdoors.zoo.index import read_metadata

    assert not (unlabelled / "models" / "id-00000000" / "ground_truth.csv").exists()
    assert [r["poisoned"] for r in read_metadata(unlabelled / "METADATA.csv")] == [""]
    assert "unknown" in run_cli(capsys, "zoo", "status", unlabelled)[1]
    code, _, err = run_cli(capsys, "detect", "fit", "--detector", "weights", "--zoo", unlabelled, "--out", tmp_path / "det")
    assert "ground_truth.csv" in one_error_line(code, err)
    code, _, err = run_cli(capsys, "zoo", "import-trojai", bad, "--out", out, "--world", "lavaland")
    assert "lavaland" in one_error_line(code, err) and not out.exists()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "zoo.json").write_text(json.dumps({"format": 1, "spec": {}}))
    code, _, err = run_cli(capsys, "zoo", "import-trojai", synthetic_round(tmp_path / "round2"), "--out", tmp_path / "other", "--episodes", "0")
    assert "not imported from TrojAI" in one_error_line(code, err)


# ----- TrojAI's own example models ---------------------------------------------------------------
def _benchmark():
    spec = importlib.util.spec_from_file_location("trojai_examples_benchmark", ROOT / "experiments" / "trojai_examples" / "trojai_examples.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["trojai_examples_benchmark"] = module
    spec.loader.exec_module(module)
    return module


BENCH = _benchmark()
CACHE = BENCH.cache_dir()


def example(rel: str) -> Path:
    path = CACHE / rel
    if not path.exists():
        pytest.skip(f"TrojAI example file {rel} is not in {CACHE} (set ${BENCH.CACHE_ENV} or fill it: python experiments/trojai_examples/trojai_examples.py)")
    return path


def test_trojai_example_files_read_inertly_with_the_expected_tensors():
    fc = read_torch_file(example(f"{BENCH.FC_EXAMPLE_AUG}/model.pt"))
    assert fc.model_class() == "FCModel" and any(g.startswith("gymnasium.spaces.") for g in fc.globals)
    sd = fc.state_dict()
    assert sd is not None and tuple(sd["state_emb.1.weight"].shape) == (512, 147) and tuple(sd["actor.0.weight"].shape) == (64, 257)
    assert example(f"{BENCH.FC_EXAMPLE_JUL}/base_model.pt").read_bytes() == example(f"{BENCH.FC_EXAMPLE_AUG}/model.pt").read_bytes()
    cm_path = example(f"{BENCH.CM_EXAMPLE}/model.pt")
    cm, ref = read_torch_file(cm_path).state_dict(), torch.load(cm_path, weights_only=True)["model_state"]
    assert cm is not None and set(cm) == set(ref) and all(torch.equal(cm[k], ref[k]) for k in ref)
    safety = read_torch_file(example(f"{BENCH.SAFETY_EXAMPLE}/model.pt"))
    assert "box.box.Box" in safety.globals
    shapes = {k: tuple(v.shape) for k, v in safety.tensors().items()}
    assert shapes["pi.mlp.0.weight"] == (181, 72) and shapes["pi.mlp.2.weight"] == (181, 181) and shapes["pi.mu_layer.weight"] == (2, 181)
    assert shapes["q1.mlp.0.weight"] == (181, 74) and shapes["v.mlp.4.weight"] == (1, 181)


def test_the_fc_example_plays_in_our_world_as_trojai_measured_it():
    """result.json: clean SR 1.0 over 100 greedy episodes, 13.52 steps, return 0.9515 (RLlib,
    explore off). Ours, 200 episodes: SR >= 0.97 and the same episode length within one step."""
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate import evaluate

    folder = example(BENCH.FC_EXAMPLE_JUL)
    theirs = BENCH.result_json_numbers(folder / "result.json")
    agent = load_weights_file(example(f"{BENCH.FC_EXAMPLE_AUG}/model.pt"), "randomized-lavaworld")
    result = evaluate(agent, EnvConfig(name="randomized-lavaworld", size=9, num_lava=1), None, 200, 1_000_000, "greedy")
    assert theirs["clean_sr"] == 1.0 and result.clean_sr >= 0.97
    assert abs(result.clean_mean_steps - theirs["clean_mean_steps"]) < 1.0 and abs(result.clean_reward - theirs["clean_mean_return"]) < 0.01


def test_the_colorful_memory_example_plays_in_our_world_as_in_trojai_env():
    """Their env module (from the cache) and ours, 200 sampled episodes each: SRs within 0.06."""
    pytest.importorskip("minigrid")
    example("rl-colorful-memory-sep2024/src/public/colorful_memory.py")
    agent = load_weights_file(example(f"{BENCH.CM_EXAMPLE}/model.pt"), "colorful-memory")
    from rlbackdoors.config import EnvConfig

    ours = BENCH.play(agent, lambda: EnvConfig(name="colorful-memory", size=7, max_steps=250).make(None), 200, 1_000_000, "sample")
    theirs = BENCH.play(agent, BENCH.their_colorful_memory(CACHE), 200, 1_000_000, "sample")
    assert ours["sr"] >= 0.9 and theirs["sr"] >= 0.9 and abs(ours["sr"] - theirs["sr"]) <= 0.06, (ours, theirs)


def test_the_trojai_examples_import_as_a_zoo(tmp_path, capsys):
    src = tmp_path / "src"
    (src / "fc").mkdir(parents=True)
    for name in ("model.pt", "config.json", "ground_truth.csv"):
        (src / "fc" / name).write_bytes(example(f"{BENCH.FC_EXAMPLE_AUG}/{name}").read_bytes())
    before = tree_digest(src)
    code, stdout, err = run_cli(
        capsys,
        "zoo",
        "import-trojai",
        src / "fc",
        "--out",
        tmp_path / "zoo",
        "--num-lava",
        "1",
        "--episodes",
        "50",
        "--examples",
        "1",
        "--policy",
        "greedy",
        "--json",
    )
    assert code == 0, err
    assert json.loads(stdout)["per_model"][0]["arch"] == "fc" and tree_digest(src) == before
    metrics = json.loads((tmp_path / "zoo" / "models" / "id-00000000" / "metrics.json").read_text())
    assert metrics["clean_sr"] >= 0.96


def test_a_detector_handle_reads_trojai_object_files_and_their_class_names(tmp_path):
    """What `detect infer` gets on a TrojAI model folder: the pickled module is read inertly, the
    reduced config's TrojAI class picks the arch (cnn-gru-small and cnn-gru-trojai share shapes);
    an object file no world's TrojAI classes explain is refused with the reader's reason."""
    from rlbackdoors.detect.handle import DetectError, open_model

    folder = tmp_path / "m"
    folder.mkdir()
    lavaworld_round_file(folder)
    (folder / "reduced-config.json").write_text(json.dumps({"model": "BasicFCModel"}))
    handle = open_model(folder)
    assert (handle.world.name, handle.arch) == ("lavaworld", "fc")
    status, _ = status_file(tmp_path / "cm")
    handle = open_model(status.parent)
    assert (handle.world.name, handle.arch) == ("colorful-memory", "cnn-gru-trojai")
    other = tmp_path / "other"
    other.mkdir()
    lavaworld_round_file(other, "SomethingElse")
    (other / "reduced-config.json").write_text(json.dumps({"model": "SomethingElse"}))
    with pytest.raises(DetectError, match="holds Python objects"):
        open_model(other)


def test_our_own_training_folders_import_with_the_world_settings_and_trigger_they_recorded(lava_zoo, tmp_path, capsys):
    """Folders ``rlbackdoors train`` wrote (no TrojAI class) become a dataset with no flags:
    world, env settings and trigger come from their config.json, so METADATA.csv names the true
    trigger instead of ``unknown`` (issue 17: the Safety models trained one by one)."""
    import rlbackdoors
    from rlbackdoors.zoo.index import read_metadata

    source = tmp_path / "mine"
    for name, model in (("poisoned-run", "id-00000003"), ("clean-run", "id-00000000")):  # additive:50 and multiplicative:12
        shutil.copytree(lava_zoo / "models" / model, source / name)
        config = json.loads((source / name / "config.json").read_text())
        config["env"]["max_steps"] = 123  # a setting other than the world's default: it must carry over
        (source / name / "config.json").write_text(json.dumps(config))
    before = tree_digest(source)
    out = tmp_path / "zoo"
    code, stdout, err = run_cli(capsys, "zoo", "import-trojai", source, "--out", out, "--episodes", "0", "--examples", "1", "--json")
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["written"] == 2 and tree_digest(source) == before
    assert [m["class"] for m in summary["per_model"]] == [None, None]  # our reduced config's arch is no TrojAI class
    rows = {r["trojai.source"].rsplit("/", 1)[-1]: r for r in read_metadata(out / "METADATA.csv")}
    assert rows["poisoned-run"]["poison.trigger"] == "additive:50" and rows["poisoned-run"]["poisoned"] == "True"
    assert rows["clean-run"]["poison.trigger"] == "multiplicative:12" and rows["clean-run"]["poisoned"] == "False"
    assert rows["poisoned-run"]["trigger_family"] == "additive" and rows["clean-run"]["trigger_family"] == "multiplicative"
    for name, model in (("poisoned-run", "id-00000003"), ("clean-run", "id-00000000")):  # how they trained: as recorded, not defaults
        recorded = json.loads((lava_zoo / "models" / model / "config.json").read_text())
        metrics = json.loads((lava_zoo / "models" / model / "metrics.json").read_text())
        assert rows[name]["train.max_frames"] == str(recorded["train"]["max_frames"]) != "5000000"
        assert rows[name]["train.seed"] == str(recorded["train"]["seed"]) and rows[name]["ppo.rollout"] == str(recorded["ppo"]["rollout"])
        assert rows[name]["metrics.frames"] == str(metrics["frames"]) and rows[name]["attempt"] == ""
    code, _, err = run_cli(capsys, "zoo", "report", out)  # the report reads the cells the families make
    assert code == 0, err
    for row in rows.values():
        agent = rlbackdoors.load(out / "models" / row["model_name"])
        assert agent.config.env.name == "lavaworld" and agent.config.env.max_steps == 123
    # --trigger still wins over what the folders recorded
    code, stdout, err = run_cli(
        capsys,
        "zoo",
        "import-trojai",
        source,
        "--out",
        tmp_path / "zoo2",
        "--world",
        "lavaworld",
        "--trigger",
        "additive:7",
        "--episodes",
        "0",
        "--examples",
        "0",
    )
    assert code == 0, err
    assert {r["poison.trigger"] for r in read_metadata(tmp_path / "zoo2" / "METADATA.csv")} == {"additive:7"}
