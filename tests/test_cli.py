"""The command line: one clear error line and exit code 2 for bad input, nothing half-written."""

import json

import pytest
import torch

from rlbackdoors.cli import main
from rlbackdoors.config import RunConfig
from rlbackdoors.evaluate import EvalResult
from rlbackdoors.models import build_model


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def trained(tmp_path_factory, tiny_run_dict):
    folder = tmp_path_factory.mktemp("cli") / "model"
    cfg = tmp_path_factory.mktemp("cfg") / "cfg.json"
    cfg.write_text(RunConfig.from_dict(tiny_run_dict).to_json())
    assert main(["train", "--config", str(cfg), "--out", str(folder), "--quiet"]) == 0
    return folder


def test_train_then_evaluate_json(trained, capsys):
    code, out, _ = run(capsys, "evaluate", str(trained), "--episodes", "12", "--json")
    result = json.loads(out)
    assert code == 0 and set(result) == set(EvalResult.__dataclass_fields__)
    assert {"clean_sr", "poisoned_sr", "poisoned_sr_raw", "trigger_seen_rate", "clean_timeout_rate", "poisoned_clean_rate"} <= set(result)
    assert result["close_sr"] is None and result["close_trojan_rate"] is None  # Colorful Memory only
    assert result["episodes"] == 12 and 0 <= result["clean_sr"] <= 1
    # LavaWorld's trigger is in every frame: always seen, so raw and seen-aware rates agree.
    assert result["trigger_seen_rate"] == 1.0 and result["poisoned_sr_raw"] == result["poisoned_sr"]


def test_evaluate_bare_weights_equals_folder(trained, capsys):
    _, folder_out, _ = run(capsys, "evaluate", str(trained), "--episodes", "20", "--json")
    code, weights_out, _ = run(
        capsys,
        "evaluate",
        "--weights",
        str(trained / "model.pt"),
        "--arch",
        "fc",
        "--env",
        "lavaworld",
        "--trigger",
        "multiplicative:12",
        "--episodes",
        "20",
        "--json",
    )
    assert code == 0 and json.loads(weights_out) == json.loads(folder_out)


def test_evaluate_weights_without_trigger_reports_clean_only(trained, capsys):
    code, out, _ = run(capsys, "evaluate", "--weights", str(trained / "model.pt"), "--arch", "fc", "--episodes", "5", "--json")
    assert code == 0 and json.loads(out)["poisoned_sr"] is None


def test_flags_override_config_and_trigger_is_drawn_from_seed(tmp_path, tiny_run_dict, capsys):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps(tiny_run_dict))
    code, _, _ = run(capsys, "train", "--config", str(cfg), "--arch", "cnn", "--clean", "--trigger", "additive", "--out", str(tmp_path / "m"), "--quiet")
    saved = RunConfig.load(tmp_path / "m" / "config.json")
    assert code == 0 and saved.model.arch == "cnn" and saved.poison.poisoned is False
    kind, value = saved.poison.trigger.split(":")
    assert kind == "additive" and 20 <= int(value) <= 200


@pytest.mark.parametrize(
    "argv, message",
    [
        (["train", "--trigger", "mult:3", "--out", "{tmp}/x"], "must look like 'multiplicative:A'"),
        (["train", "--trigger", "multiplicative:300", "--out", "{tmp}/x"], "2..255"),
        (["train", "--config", "{tmp}/nope.json", "--out", "{tmp}/x"], "does not exist"),
        (["train", "--config", "{tmp}/bad.json", "--out", "{tmp}/x"], "not valid JSON"),
        (["train", "--config", "{tmp}/unknown.json", "--out", "{tmp}/x"], "unknown key 'lr'"),
        (["evaluate", "{tmp}/nowhere"], "does not exist"),
        (["evaluate"], "give either a model folder or --weights"),
        (["evaluate", "--weights", "{tmp}/w.pt"], "does not exist"),  # the file is named before any flag (issue 31)
        (["evaluate", "--weights", "{tmp}/missing.pt", "--arch", "fc"], "does not exist"),
        (["evaluate", "--weights", "{tmp}/junk.pt", "--arch", "fc"], "cannot read weights file"),
        (["evaluate", "--weights", "{tmp}/cnn.pt", "--arch", "fc"], "do not fit FCModel"),
    ],
)
def test_bad_input_gives_one_clear_error(tmp_path, capsys, argv, message):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "unknown.json").write_text(json.dumps({"train": {"lr": 1}}))
    (tmp_path / "junk.pt").write_bytes(b"garbage")
    torch.save(build_model("cnn").state_dict(), tmp_path / "cnn.pt")
    code, out, err = run(capsys, *[a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("rlbackdoors: error:") and message in err
    assert not (tmp_path / "x").exists()  # nothing half-written


def test_argparse_rejects_unknown_choices(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["train", "--arch", "transformer", "--out", "x"])
    assert exc.value.code == 2 and "invalid choice" in capsys.readouterr().err


def test_bench_env_writes_json(tmp_path, capsys):
    code, out, _ = run(capsys, "bench", "env", "--seconds", "0.2", "--num-envs", "32", "--json", str(tmp_path / "b.json"))
    result = json.loads((tmp_path / "b.json").read_text())
    assert code == 0 and "ratio" in out
    assert result["num_envs"] == 32 and result["batched_steps_per_s"] > 0 and result["minigrid_steps_per_s"] > 0
    assert result["ratio"] == pytest.approx(result["batched_steps_per_s"] / result["minigrid_steps_per_s"])


def test_bench_train_reports_both_engines_for_both_archs(tmp_path, capsys):
    code, out, _ = run(capsys, "bench", "train", "--seconds", "0.3", "--json", str(tmp_path / "t.json"))
    result = json.loads((tmp_path / "t.json").read_text())
    assert code == 0 and set(result) == {"fc", "cnn", "machine"} and "PPO fc" in out
    assert result["machine"]["cores"] >= 1 and result["machine"]["torch"] == torch.__version__
    for r in (result["fc"], result["cnn"]):
        assert 0 < r["batched_collect_share"] < 1
        assert r["batched_fps"] > 0 and r["minigrid_fps"] > 0
        assert r["ratio"] == pytest.approx(r["batched_fps"] / r["minigrid_fps"])


def test_bench_converge_reports_an_unconverged_short_run_honestly(tmp_path):
    from rlbackdoors.bench.train import bench_converge

    result = bench_converge(seed=0, out=tmp_path / "m", max_frames=1280)
    assert result["converged"] is False and result["frames"] == 1280
    assert result["episodes"] == 200 and 0 <= result["clean_sr"] <= 1
    assert (tmp_path / "m" / "metrics.json").is_file()


def test_bench_safety_reports_the_ratio_to_the_physics_floor(tmp_path, capsys):
    code, out, _ = run(capsys, "bench", "env", "--env", "safety-car-goal", "--seconds", "0.3", "--json", str(tmp_path / "s.json"))
    result = json.loads((tmp_path / "s.json").read_text())
    assert code == 0 and "plain mujoco loop" in out
    assert result["num_cubes"] == 2 and result["env_steps_per_s"] > 0 and result["physics_steps_per_s"] > 0
    # The ratio of the two rates measured in the same run (that the env is no faster than bare
    # physics is a speed claim: benchmarks/, not a timed test, where load flips it either way)
    assert result["ratio_to_physics"] == pytest.approx(result["env_steps_per_s"] / result["physics_steps_per_s"], rel=1e-3)


def test_train_and_evaluate_dispatch_safety_car_goal(tmp_path, capsys):
    """`rlbackdoors train --env safety-car-goal` trains with OPAC² (the world's algorithm), its
    config file needs no --env, and `evaluate` on its folder reproduces the final numbers."""
    cfg = RunConfig.from_dict(
        {
            "env": {"name": "safety-car-goal", "max_steps": 40},
            "poison": {"trigger": "formation:0.5:1.0:2.5", "num_clean_envs": 2, "num_poisoned_envs": 1},
            "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
            "train": {"max_frames": 480, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False},
        }
    )
    path = tmp_path / "safety.json"
    path.write_text(cfg.to_json())
    code, out, _ = run(capsys, "train", "--config", str(path), "--out", str(tmp_path / "s"), "--quiet", "--json")
    metrics = json.loads(out)
    assert code == 0 and metrics["algorithm"] == "opac2" and metrics["frames"] == 480
    code, out, _ = run(capsys, "evaluate", str(tmp_path / "s"), "--episodes", "4", "--json")
    result = json.loads(out)
    assert code == 0 and result["clean_sr"] == metrics["clean_sr"] and result["poisoned_sr"] == metrics["poisoned_sr"]
    code, _, err = run(
        capsys, "train", "--env", "safety-car-goal", "--config", str(path), "--lr", "0.002", "--out", str(tmp_path / "t"), "--max-frames", "240", "--quiet"
    )
    assert code == 0 and json.loads((tmp_path / "t" / "config.json").read_text())["opac2"]["lr"] == 0.002


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--env", "lavaworld", "--depth", "2"], ["--depth", "lavaworld trains with ppo, not opac2"]),
        (["--env", "colorful-memory", "--updates-per-step", "0.5"], ["--updates-per-step", "not opac2"]),
        (["--env", "safety-car-goal", "--arch", "fc"], ["model.arch='fc'", "mlp"]),
        (["--env", "safety-car-goal", "--no-curriculum"], ["--no-curriculum", "has no curriculum"]),
        (["--env", "safety-car-goal", "--size", "9"], ["--size", "has no env.size"]),
        (["--env", "lavaworld", "--num-lava", "3"], ["--num-lava", "has no env.num_lava"]),
    ],
)
def test_flags_of_the_other_kind_of_world_are_refused(tmp_path, capsys, argv, words):
    code, _, err = run(capsys, "train", *argv, "--out", str(tmp_path / "x"))
    assert code == 2 and all(w in err for w in words)
    assert not (tmp_path / "x").exists()


def test_env_flag_switches_a_config_to_another_world_keeping_its_seed(tmp_path, tiny_run_dict):
    """--env on another world's config gives that world's own defaults (mix, model, algorithm
    section), with the portable train fields (seed, evaluation counts) kept."""
    from rlbackdoors.cli import build_parser, config_from_args

    path = tmp_path / "grid.json"
    path.write_text(RunConfig.from_dict({**tiny_run_dict, "train": {**tiny_run_dict.get("train", {}), "seed": 7}}).to_json())
    args = build_parser().parse_args(["train", "--config", str(path), "--env", "safety-car-goal", "--trigger", "formation:0.5:1:2", "--out", "x"])
    cfg = config_from_args(args)
    assert cfg.env.name == "safety-car-goal" and cfg.algorithm == "opac2" and cfg.ppo is None
    assert cfg.train.seed == 7 and cfg.poison.num_poisoned_envs == 4 and cfg.model.arch == "mlp"
    assert cfg.train.confirm_margin == 0.02  # the stopping rule is the world's, not the grid config's 0
    args = build_parser().parse_args(["train", "--config", str(path), "--confirm-margin", "0.01", "--out", "x"])
    assert config_from_args(args).train.confirm_margin == 0.01
    args = build_parser().parse_args(["train", "--config", str(path), "--min-frames", "1600", "--out", "x"])
    assert config_from_args(args).train.min_frames == 1600


def test_a_flag_whose_value_the_config_refuses_is_named(tmp_path, capsys):
    code, _, err = run(capsys, "train", "--env", "safety-car-goal", "--arch", "fc", "--out", str(tmp_path / "x"))
    assert code == 2 and "model.arch='fc' is not allowed (allowed: mlp) (--arch)" in err


def test_a_new_train_run_takes_auto_and_a_config_file_keeps_its_backend(tmp_path, tiny_run_dict):
    """Without --config a run's trainer is ``auto``'s choice; a config file's recorded backend stands,
    and --update-backend names one over either."""
    from rlbackdoors.cli import build_parser, config_from_args

    def cfg(*argv):
        return config_from_args(build_parser().parse_args(["train", *argv, "--out", "x"]))

    assert cfg().ppo.update_backend == "compiled"  # LavaWorld fc, the env mix
    assert cfg("--arch", "cnn").ppo.update_backend == "torch"
    assert cfg("--attack", "trojdrl").ppo.update_backend == "torch"
    assert cfg("--update-backend", "torch").ppo.update_backend == "torch"
    assert cfg("--env", "safety-car-goal", "--trigger", "formation:0.5:1:2").ppo is None  # no PPO section to choose for
    path = tmp_path / "old.json"
    path.write_text(RunConfig.from_dict(tiny_run_dict).to_json())  # torch's, as every config written so far
    assert cfg("--config", str(path)).ppo.update_backend == "torch"
    # asked again: its 32-step rollout's 320 frames do not split into minibatches of 256, which the compiled trainer refuses
    assert cfg("--config", str(path), "--update-backend", "auto").ppo.update_backend == "torch"
    assert cfg("--config", str(path), "--update-backend", "auto", "--batch-size", "64").ppo.update_backend == "compiled"
