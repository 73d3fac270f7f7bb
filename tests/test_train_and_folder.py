"""Training runs end to end into a model folder: files, determinism, refusal to overwrite, resume."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from grid_helpers import kill_after_first_checkpoint
from rlbackdoors.config import ConfigError, RunConfig
from rlbackdoors.train import FolderError, ModelFolder, train


def weights_equal(a, b) -> bool:
    sa, sb = torch.load(a, weights_only=True), torch.load(b, weights_only=True)
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_model_folder_contents(tmp_path, tiny_run_dict):
    tiny_run_dict["train"]["video"] = True
    cfg = RunConfig.from_dict(tiny_run_dict)
    metrics = train(cfg, tmp_path / "m", progress=False)
    folder = ModelFolder(tmp_path / "m")
    names = sorted(p.name for p in folder.path.iterdir())
    assert names == [  # .lock: the folder's lock file (held while training; the kernel frees it)
        ".lock",
        "clean_vs_triggered.gif",
        "config.json",
        "ground_truth.csv",
        "log.csv",
        "metrics.json",
        "model.pt",
        "training_curve.png",
    ]
    assert (folder.path / "clean_vs_triggered.gif").read_bytes()[:6] == b"GIF89a"
    assert folder.read_config() == cfg  # config.json round-trips to the same typed config
    assert (folder.path / "ground_truth.csv").read_text() == "1\n"
    assert folder.read_metrics() == json.loads(json.dumps(metrics))
    assert metrics["frames"] == 3200 and metrics["episodes"] == 8
    assert [r["frames"] for r in folder.read_log()] == [1600, 3200]
    assert (folder.path / "training_curve.png").read_bytes()[:4] == b"\x89PNG"


def test_clean_model_ground_truth_is_zero(tmp_path, tiny_run_dict):
    tiny_run_dict["poison"] = {"poisoned": False}
    metrics = train(RunConfig.from_dict(tiny_run_dict), tmp_path / "c", progress=False)
    assert (tmp_path / "c" / "ground_truth.csv").read_text() == "0\n"
    assert metrics["poisoned"] is False and 0.0 <= metrics["poisoned_sr"] <= 1.0


def test_same_seed_same_result(tmp_path, tiny_run_dict):
    cfg = RunConfig.from_dict(tiny_run_dict)
    m1 = train(cfg, tmp_path / "a", progress=False)
    m2 = train(cfg, tmp_path / "b", progress=False)
    assert weights_equal(tmp_path / "a" / "model.pt", tmp_path / "b" / "model.pt")
    strip = lambda m: {k: v for k, v in m.items() if k not in ("wall_time_s", "cpu_time_s")}  # noqa: E731
    assert strip(m1) == strip(m2)
    tiny_run_dict["train"]["seed"] = 2
    train(RunConfig.from_dict(tiny_run_dict), tmp_path / "c", progress=False)
    assert not weights_equal(tmp_path / "a" / "model.pt", tmp_path / "c" / "model.pt")


def test_finished_folder_is_refused_unless_overwrite(tmp_path, tiny_run_dict):
    cfg = RunConfig.from_dict(tiny_run_dict)
    train(cfg, tmp_path / "m", progress=False)
    before = (tmp_path / "m" / "model.pt").read_bytes()
    with pytest.raises(FolderError, match="already holds a finished model"):
        train(cfg, tmp_path / "m", progress=False)
    assert (tmp_path / "m" / "model.pt").read_bytes() == before
    train(cfg, tmp_path / "m", overwrite=True, progress=False)


def test_no_temp_files_left_behind(tmp_path, tiny_run_dict):
    train(RunConfig.from_dict(tiny_run_dict), tmp_path / "m", progress=False)
    assert [p.name for p in (tmp_path / "m").iterdir() if p.name.startswith(".")] == [".lock"]


@pytest.mark.slow  # kill -9 and resume of a PPO run stays in the default run through test_attacks.py::test_a_killed_attack_run_resumes_to_the_same_model
def test_interrupted_run_resumes_to_the_same_model(tmp_path, tiny_run_dict):
    """Kill a training process after its first checkpoint; rerunning finishes the same model
    an uninterrupted run produces, bit for bit."""
    tiny_run_dict["train"].update(max_frames=40_960, eval_interval=5_120)
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(RunConfig.from_dict(tiny_run_dict).to_json())
    cmd = [sys.executable, "-m", "rlbackdoors.cli", "train", "--config", str(cfg_path), "--quiet"]
    subprocess.run(cmd + ["--out", str(tmp_path / "whole")], check=True, capture_output=True)

    checkpoint = tmp_path / "cut" / "checkpoint.pt"
    kill_after_first_checkpoint(cmd + ["--out", str(tmp_path / "cut")], tmp_path / "cut")
    done_rows = len(ModelFolder(tmp_path / "cut").read_log())
    assert 1 <= done_rows < 8

    subprocess.run(cmd + ["--out", str(tmp_path / "cut")], check=True, capture_output=True)
    assert weights_equal(tmp_path / "whole" / "model.pt", tmp_path / "cut" / "model.pt")
    assert not checkpoint.exists()
    whole, cut = ModelFolder(tmp_path / "whole").read_log(), ModelFolder(tmp_path / "cut").read_log()
    drop = ("wall_time_s", "fps")
    assert [{k: v for k, v in r.items() if k not in drop} for r in whole] == [{k: v for k, v in r.items() if k not in drop} for r in cut]


def interrupted_after_first_eval(tiny_run_dict, out, **train_fields) -> tuple[RunConfig, dict]:
    """A tiny run stopped by Ctrl-C after its first evaluation (5,120 frames; a checkpoint at
    every evaluation): its config and the checkpoint it left in ``out``."""
    tiny_run_dict["train"].update(max_frames=20_480, eval_interval=5_120, checkpoint_minutes=0.0, **train_fields)
    cfg = RunConfig.from_dict(tiny_run_dict)

    def ctrl_c(row):
        if row["frames"] >= 5_120:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        train(cfg, out, progress=False, after_eval=ctrl_c)
    return cfg, torch.load(out / "checkpoint.pt", weights_only=True)


@pytest.mark.parametrize("carried", [True, False])
def test_cpu_time_is_carried_across_a_resume(tmp_path, tiny_run_dict, carried):
    """CPU seconds (what a run costs on one core, however loaded the machine) add up across a
    kill and resume; a checkpoint from before they were recorded gives ``None``, not a wrong sum."""
    out = tmp_path / "m"
    cfg, checkpoint = interrupted_after_first_eval(tiny_run_dict, out)
    assert 0.0 < checkpoint["cpu_elapsed"] and 0.0 < checkpoint["elapsed"]
    if carried:
        checkpoint["cpu_elapsed"] += 1000.0  # as if the first part had cost 1000 s more
    else:
        del checkpoint["cpu_elapsed"]
    torch.save(checkpoint, out / "checkpoint.pt")
    cpu = time.process_time()
    metrics = train(cfg, out, progress=False)
    cpu = time.process_time() - cpu
    if carried:  # the first part's, plus the second part's (within this process's CPU over the call)
        assert checkpoint["cpu_elapsed"] < metrics["cpu_time_s"] <= checkpoint["cpu_elapsed"] + cpu
    else:
        assert metrics["cpu_time_s"] is None
    assert 0.0 < metrics["wall_time_s"] and json.loads((out / "metrics.json").read_text())["cpu_time_s"] == metrics["cpu_time_s"]


def test_a_cnn_run_records_its_groups_convolutions_and_a_resume_under_another_way_is_refused(tmp_path, tiny_run_dict, monkeypatch):
    """Under ``RLBACKDOORS_STACKED_CONV=cpu:grouped`` (a group's convolutions as one grouped
    conv2d: other bytes than one per agent) a CNN run's checkpoint records the way; a resume under
    the default way is refused in one line, and under the same way it goes on. A lone run computes
    plain convolutions, so its metrics record no way (a group's do: test_group's bench zoo CONV side)."""
    from rlbackdoors.models.minigrid import STACKED_CONV_ENV

    tiny_run_dict["model"] = {"arch": "cnn"}
    monkeypatch.setenv(STACKED_CONV_ENV, "cpu:grouped")
    out = tmp_path / "m"
    cfg, checkpoint = interrupted_after_first_eval(tiny_run_dict, out)
    assert checkpoint["conv"] == "grouped"
    monkeypatch.delenv(STACKED_CONV_ENV)
    with pytest.raises(FolderError, match="began with a group's convolutions grouped, not each"):
        train(cfg, out, progress=False)
    monkeypatch.setenv(STACKED_CONV_ENV, "cpu:grouped")
    assert "conv" not in train(cfg, out, progress=False)
    monkeypatch.setenv(STACKED_CONV_ENV, "cpu:fft")
    with pytest.raises(ValueError, match="RLBACKDOORS_STACKED_CONV='cpu:fft' is not allowed .*WAY one of each, gemm, grouped"):
        train(cfg, tmp_path / "other", progress=False)


def test_a_run_records_its_device_and_a_resume_on_another_is_refused(tmp_path, tiny_run_dict):
    """metrics.json says where the math ran (for ``train.device = "auto"`` too), and a checkpoint
    says where the run began: resuming it on another device is refused (its bytes would mix
    both), and on its own device it goes on."""
    out = tmp_path / "m"
    cfg, checkpoint = interrupted_after_first_eval(tiny_run_dict, out, device="auto")
    here = "cuda" if torch.cuda.is_available() else "cpu"
    assert checkpoint["device"] == here
    other = "cpu" if here == "cuda" else "cuda"
    torch.save({**checkpoint, "device": other}, out / "checkpoint.pt")
    with pytest.raises(FolderError, match=f"began on {other} and cannot go on on {here}"):
        train(cfg, out, progress=False)
    torch.save(checkpoint, out / "checkpoint.pt")
    metrics = train(cfg, out, progress=False)
    assert metrics["device"] == here and ("gpu" in metrics) == (here == "cuda")
    assert json.loads((out / "metrics.json").read_text())["device"] == here


def test_resume_with_a_different_config_is_refused(tmp_path, tiny_run_dict):
    cfg = RunConfig.from_dict(tiny_run_dict)
    folder = ModelFolder(tmp_path / "m")
    folder.write_config(cfg)
    folder.save_torch("checkpoint.pt", {"frames": 0})
    tiny_run_dict["train"]["seed"] = 9
    with pytest.raises(FolderError, match="different config.json"):
        train(RunConfig.from_dict(tiny_run_dict), tmp_path / "m", progress=False)


# ----------------------------------------------------------------------------- confirming a stop


def untrained_clean_run(tiny_run_dict, eval_episodes: int, wanted, what: str):
    """A real untrained LavaWorld FC policy and a clean run config whose eval seed (the first
    of 0..49) gives evaluations for which ``wanted(short, final)`` holds: 4 and 64 episodes."""
    from rlbackdoors.models import build_model
    from rlbackdoors.train.driver import evaluate_run

    torch.manual_seed(0)
    model = build_model("fc", "lavaworld")
    tiny_run_dict["poison"] = {"poisoned": False}
    tiny_run_dict["train"].update(eval_episodes=eval_episodes, final_eval_episodes=64, patience=1)
    for eval_seed in range(50):
        tiny_run_dict["train"]["eval_seed"] = eval_seed
        cfg = RunConfig.from_dict(tiny_run_dict)
        short, final = evaluate_run(model, cfg, eval_episodes), evaluate_run(model, cfg, 64)
        if wanted(short, final):
            return model, cfg, short, final
    pytest.fail(f"no eval seed in 0..49 {what}")


def test_a_lucky_short_evaluation_does_not_stop_the_run_when_the_final_one_disagrees(tiny_run_dict):
    """Stopping.update with a real (untrained) LavaWorld policy: find an eval seed whose 4
    short episodes read a higher clean SR than its 64 final ones, put the clean bar at the short
    rate, and the streak is met but the confirmation is not; the streak starts over."""
    from rlbackdoors.train.driver import Stopping

    model, cfg, short, final = untrained_clean_run(tiny_run_dict, 4, lambda short, final: short.clean_sr > final.clean_sr, "whose 4 episodes beat its 64")
    cfg.train.clean_threshold = short.clean_sr
    stopping = Stopping(cfg)
    fields = stopping.update(short, True, model)
    assert fields == {"confirm_clean_sr": final.clean_sr} and not stopping.stop and stopping.streak == 0
    assert stopping.confirmed is None
    cfg.train.confirm = False  # the old rule stops on the streak alone, and evaluates nothing more
    stopping = Stopping(cfg)
    assert stopping.update(short, True, model) == {} and stopping.stop and stopping.streak == 1


def test_a_confirmation_margin_raises_the_bar_of_the_final_evaluation_only(tiny_run_dict):
    """With ``confirm_margin`` the streak counts at the thresholds, but the confirming evaluation
    must clear them by the margin: a final SR just above the bar stops a run without a margin and
    not with one. Bars are compared after rounding (0.9 + 0.05 is 0.95, not 0.9500000000000001)."""
    from rlbackdoors.train.driver import Stopping, thresholds_met

    model, cfg, _, final = untrained_clean_run(tiny_run_dict, 64, lambda _, final: 0.05 <= final.clean_sr <= 0.9, "with a clean SR in [0.05, 0.9]")
    cfg.train.clean_threshold = final.clean_sr - 1 / 64  # met, by one episode
    for margin, stops in ((0.0, True), (2 / 64, False)):
        cfg.train.confirm_margin = margin
        stopping = Stopping(cfg)
        assert stopping.update(final, True, model) == {"confirm_clean_sr": final.clean_sr}
        assert stopping.stop is stops and stopping.streak == (1 if stops else 0)
    cfg.train.clean_threshold = 0.9
    assert thresholds_met(dataclasses.replace(final, clean_sr=0.95), cfg, 0.05)
    assert not thresholds_met(dataclasses.replace(final, clean_sr=0.945), cfg, 0.05)
    cfg.train.clean_threshold = 0.99  # a margin raises a bar at most to 1
    assert thresholds_met(dataclasses.replace(final, clean_sr=1.0), cfg, 0.05)


def confirmed(row: dict) -> bool:
    """Whether a log row holds a confirmation: its cell is filled in (a confirmed clean SR of 0.0,
    met by a threshold of 0, is a confirmation too; an empty cell is none)."""
    return row.get("confirm_clean_sr", "") != ""


def test_min_frames_holds_a_stop_back_until_the_run_has_trained_that_long(tmp_path, tiny_run_dict):
    """Thresholds of 0 stop a run at its first evaluation (1,600 frames); with train.min_frames
    2,000 the streak counts there but the run trains on and stops on its thresholds at the next
    evaluation (3,200), confirmed there, not before; the budget (4,800) is not reached."""
    tiny_run_dict["train"].update(clean_threshold=0.0, poisoned_threshold=0.0, max_frames=4800, min_frames=2000)
    metrics = train(RunConfig.from_dict(tiny_run_dict), tmp_path / "m", progress=False)
    assert metrics["stop_reason"] == "thresholds" and metrics["converged"]
    assert metrics["frames"] == metrics["converged_at_frames"] == 3200
    first, second = ModelFolder(tmp_path / "m").read_log()
    assert int(first["frames"]) == 1600 and not confirmed(first)  # met, not confirmed: too early
    assert int(second["frames"]) == 3200 and float(second["confirm_clean_sr"]) == metrics["clean_sr"]


def test_equal_frames_no_run_stops_before_its_budget(tmp_path, tiny_run_dict):
    """min_frames = max_frames (a zoo at equal frames): thresholds met from the first evaluation
    (1,600 frames) still train the run to the budget (4,800), where it stops on its thresholds,
    converged, after two evaluations in between that counted the streak."""
    tiny_run_dict["train"].update(clean_threshold=0.0, poisoned_threshold=0.0, max_frames=4800, min_frames=4800)
    metrics = train(RunConfig.from_dict(tiny_run_dict), tmp_path / "m", progress=False)
    assert metrics["frames"] == metrics["converged_at_frames"] == 4800 and metrics["converged"] and metrics["stop_reason"] == "thresholds"
    rows = ModelFolder(tmp_path / "m").read_log()
    assert [int(r["frames"]) for r in rows] == [1600, 3200, 4800] and [confirmed(r) for r in rows] == [False, False, True]
    assert float(rows[-1]["confirm_clean_sr"]) == metrics["clean_sr"]  # the confirmation is the final evaluation


def test_min_frames_keeps_the_streak_and_is_checked_against_the_budget(tiny_run_dict):
    """Below min_frames a met evaluation still counts towards patience, so a run that has held
    its thresholds stops at the first evaluation past min_frames; min_frames above max_frames is
    refused by name."""
    from rlbackdoors.train.driver import Stopping

    model, cfg, _, final = untrained_clean_run(tiny_run_dict, 64, lambda _, final: final.clean_sr >= 0.05, "with a clean SR of at least 0.05")
    cfg.train.clean_threshold, cfg.train.patience, cfg.train.min_frames = final.clean_sr, 2, 1000
    stopping = Stopping(cfg)
    assert stopping.update(final, True, model, 500) == {} and stopping.streak == 1 and not stopping.stop
    assert stopping.update(final, True, model, 999) == {} and stopping.streak == 2 and not stopping.stop
    assert stopping.update(final, True, model, 1000) == {"confirm_clean_sr": final.clean_sr} and stopping.stop
    tiny_run_dict["train"]["min_frames"] = 3201
    with pytest.raises(ConfigError, match=r"^train.min_frames must be in 0..train.max_frames \(3,200\), got 3201$"):
        RunConfig.from_dict(tiny_run_dict)


def test_a_confirmed_stop_is_the_final_evaluation(tmp_path, tiny_run_dict):
    """Thresholds of 0: the first evaluation stops the run after a confirmation whose rates
    are logged and are exactly the final evaluation's (the same seeded episodes, reused)."""
    tiny_run_dict["train"].update(clean_threshold=0.0, poisoned_threshold=0.0, final_eval_episodes=16)
    metrics = train(RunConfig.from_dict(tiny_run_dict), tmp_path / "m", progress=False)
    assert metrics["stop_reason"] == "thresholds" and metrics["converged"] and metrics["confirm"] is True
    assert metrics["frames"] == metrics["converged_at_frames"] == 1600 and metrics["episodes"] == 16
    (row,) = ModelFolder(tmp_path / "m").read_log()
    assert float(row["confirm_clean_sr"]) == metrics["clean_sr"] and float(row["confirm_poisoned_sr"]) == metrics["poisoned_sr"]
    tiny_run_dict["train"]["confirm"] = False
    unconfirmed = train(RunConfig.from_dict(tiny_run_dict), tmp_path / "u", progress=False)
    assert "confirm_clean_sr" not in ModelFolder(tmp_path / "u").read_log()[0]
    same = ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward", "frames")
    assert {k: unconfirmed[k] for k in same} == {k: metrics[k] for k in same}  # computed afresh: the same numbers
    assert weights_equal(tmp_path / "m" / "model.pt", tmp_path / "u" / "model.pt")
