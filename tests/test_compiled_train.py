"""Runs on the compiled trainer (``ppo.update_backend = "compiled"``, algos/compiled.py) end to end:
the model folder a detector reads, the same bytes from the same config and group size, a resume
after kill -9 to the same model, groups whose runs' bytes do not depend on their group-mates, and
one-line refusals of what it does not train.

The runs are tiny (rollout 32 x 10 copies, minibatches of 64, 1,280 to 3,840 frames); each
process compiles one program per group size (about 7 s here), which the tests in this file share.
"""

from __future__ import annotations

import json
import re

import pytest
import torch


from grid_helpers import kill_after_first_checkpoint, model_weights, same_weights, stopped_and_resumed_matches  # noqa: E402
from rlbackdoors.config import ConfigError, RunConfig  # noqa: E402
from rlbackdoors.folder import FolderError  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402
from rlbackdoors.train import ModelFolder, train  # noqa: E402
from rlbackdoors.train.group import train_group  # noqa: E402


def run_dict(seed: int = 1, frames: int = 1280, **train_fields) -> dict:
    return {
        "env": {"name": "lavaworld"},
        "poison": {"trigger": "multiplicative:12"},
        "ppo": {"rollout": 32, "batch_size": 64, "update_backend": "compiled"},
        "train": {"seed": seed, "max_frames": frames, "eval_interval": 640, "eval_episodes": 8, "final_eval_episodes": 8, "video": False, **train_fields},
    }


def test_a_compiled_run_writes_the_model_folder_and_repeats_its_bytes(tmp_path):
    """The folder is a torch run's (config, log, metrics, ground truth, curve, model.pt with the
    architecture's keys and shapes); the metrics name the backend and the group size; the same
    config gives the same model.pt bytes and numbers, another seed other weights."""
    cfg = RunConfig.from_dict(run_dict())
    m1 = train(cfg, tmp_path / "a", progress=False)
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == [".lock", "config.json", "ground_truth.csv", "log.csv", "metrics.json", "model.pt", "training_curve.png"]
    folder = ModelFolder(tmp_path / "a")
    assert folder.read_config() == cfg and folder.read_config().ppo.update_backend == "compiled"
    assert [r["frames"] for r in folder.read_log()] == [640, 1280]
    assert m1["frames"] == 1280 and m1["compiled_group"] == 1 and m1["device"] == "cpu"
    reference = build_model("fc", "lavaworld").state_dict()
    got = model_weights(tmp_path / "a")
    assert got.keys() == reference.keys() and all(got[k].shape == reference[k].shape and got[k].dtype == torch.float32 for k in got)
    torch.manual_seed(1)
    initial = build_model("fc", "lavaworld").state_dict()
    assert not all(torch.equal(got[k], initial[k]) for k in got)  # it trained
    m2 = train(cfg, tmp_path / "b", progress=False)
    assert same_weights(tmp_path / "a", tmp_path / "b")
    strip = lambda m: {k: v for k, v in m.items() if k not in ("wall_time_s", "cpu_time_s")}  # noqa: E731
    assert strip(m1) == strip(m2)
    train(RunConfig.from_dict(run_dict(seed=2)), tmp_path / "c", progress=False)
    assert not same_weights(tmp_path / "a", tmp_path / "c")


def test_a_compiled_cnn_run_trains_the_cnn(tmp_path):
    """The CNN (convolutions, max-pool, tanh heads) trains on the compiled trainer into model.pt
    with its own keys and shapes."""
    data = run_dict()
    data["model"] = {"arch": "cnn"}
    metrics = train(RunConfig.from_dict(data), tmp_path / "cnn", progress=False)
    assert metrics["arch"] == "cnn" and metrics["compiled_group"] == 1 and metrics["frames"] == 1280
    reference = build_model("cnn", "lavaworld").state_dict()
    got = model_weights(tmp_path / "cnn")
    assert got.keys() == reference.keys() and all(got[k].shape == reference[k].shape for k in got)
    torch.manual_seed(1)
    initial = build_model("cnn", "lavaworld").state_dict()
    assert not torch.equal(got["state_emb.0.weight"], initial["state_emb.0.weight"])  # the first convolution learnt


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_a_killed_compiled_run_resumes_to_the_same_model(tmp_path):
    """kill -9 after its first checkpoint (one at every evaluation); run again, it finishes the
    model an uninterrupted run makes, bit for bit, with the same log."""
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(RunConfig.from_dict(run_dict(frames=3840, checkpoint_minutes=0.0)).to_json())
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "rlbackdoors.cli", "train", "--config", str(cfg_path), "--quiet"]
    subprocess.run(cmd + ["--out", str(tmp_path / "whole")], check=True, capture_output=True)
    kill_after_first_checkpoint(cmd + ["--out", str(tmp_path / "cut")], tmp_path / "cut")
    assert 1 <= len(ModelFolder(tmp_path / "cut").read_log()) < 6
    subprocess.run(cmd + ["--out", str(tmp_path / "cut")], check=True, capture_output=True)
    assert same_weights(tmp_path / "whole", tmp_path / "cut")
    drop = ("wall_time_s", "fps")
    rows = [json.dumps([{k: v for k, v in r.items() if k not in drop} for r in ModelFolder(tmp_path / side).read_log()]) for side in ("whole", "cut")]
    assert rows[0] == rows[1] and len(json.loads(rows[0])) == 6  # (as text: a NaN training return is no number)


def rlw_dict(frames: int = 1920, **train_fields) -> dict:
    """Randomized LavaWorld's CNN (the direction appended to its embedding), a curriculum whose
    warm-up ends at the first finished episode (a window of 1, a threshold of 0)."""
    data = run_dict(frames=frames, **train_fields)
    data.update(
        {
            "env": {"name": "randomized-lavaworld"},
            "model": {"arch": "cnn"},
            "poison": {"trigger": "cross"},
            "curriculum": {"window": 1, "reward_threshold": 0.0},
        }
    )
    return data


def test_a_randomized_lavaworld_run_switches_from_its_warm_up_and_resumes_to_the_same_model(tmp_path):
    """The CNN trains through the curriculum's switch (the small clean world's program, then the
    full world's), into model.pt with the architecture's keys; stopped at its first evaluation
    (after the switch) and run again, it finishes the uninterrupted run's model, bit for bit."""
    cfg = RunConfig.from_dict(rlw_dict(checkpoint_minutes=0.0))
    metrics = train(cfg, tmp_path / "whole", progress=False)
    assert metrics["compiled_group"] == 1 and metrics["frames"] == 1920 and metrics["curriculum_switch_frames"] == 320
    reference = build_model("cnn", "randomized-lavaworld").state_dict()
    got = model_weights(tmp_path / "whole")
    assert got.keys() == reference.keys() and all(got[k].shape == reference[k].shape for k in got)
    torch.manual_seed(1)
    assert not torch.equal(got["actor.0.weight"], build_model("cnn", "randomized-lavaworld").state_dict()["actor.0.weight"])
    assert stopped_and_resumed_matches(cfg, tmp_path / "whole", tmp_path / "cut") == [640]


def test_a_runs_bytes_depend_on_its_group_size_not_its_group_mates(tmp_path):
    """Three runs in compiled groups of 2 (the third trains alone in a padded program) give each
    run the bytes it has alone in a group of 2, and a resume in a group of another size is
    refused in one line."""
    cfgs = [RunConfig.from_dict(run_dict(seed=s)) for s in (1, 2, 3)]
    together = train_group([(i, cfg, tmp_path / f"g{i}") for i, cfg in enumerate(cfgs)], 2)
    assert not together.errors and all(m["compiled_group"] == 2 for m in together.metrics.values())
    alone = train_group([(0, cfgs[2], tmp_path / "alone")], 2)
    assert not alone.errors
    assert same_weights(tmp_path / "g2", tmp_path / "alone")
    assert not same_weights(tmp_path / "g0", tmp_path / "g1")
    # a group of 2's checkpoint, resumed alone (a group size of 1): refused
    cut = tmp_path / "cut"

    def stop_after_first(row):
        if row["frames"] >= 640:
            raise KeyboardInterrupt

    cfg = RunConfig.from_dict(run_dict(seed=4, checkpoint_minutes=0.0))
    from rlbackdoors.train.driver import StopRequest, train_steps
    from rlbackdoors.train.group import serve_batch

    loop = train_steps(cfg, cut, StopRequest(), progress=False, after_eval=stop_after_first)
    request = next(loop)
    with pytest.raises(KeyboardInterrupt):
        while True:
            request = loop.send(serve_batch([request], capacity=2)[0])
    assert (cut / "checkpoint.pt").exists()
    with pytest.raises(FolderError, match="began in a compiled group of 2 and cannot go on in one of 1"):
        train(cfg, cut, progress=False)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"ppo": {"rollout": 100, "update_backend": "compiled"}}, "must divide a rollout's 1000 frames"),
        ({"env": {"name": "randomized-lavaworld", "engine": "minigrid"}, "poison": {"trigger": "cross"}}, "not env.engine='minigrid'"),
    ],
)
def test_what_the_compiled_trainer_does_not_train_is_refused_in_one_line(change, message):
    data = run_dict()
    data.update(change)
    data["ppo"]["update_backend"] = "compiled"
    with pytest.raises(ConfigError, match=re.escape(message)) as err:
        RunConfig.from_dict(data)
    assert "\n" not in str(err.value) and str(err.value).startswith("ppo.update_backend='compiled'")
    json.dumps(data)  # (the cases are plain configs)
