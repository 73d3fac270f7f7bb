"""Backdoor removal (issue 82): ``rlbackdoors mitigate`` on real packed models of the repository,
judged on the true trigger, which the mitigation never reads (the test does)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rlbackdoors
from rlbackdoors.config import ConfigError, CurriculumConfig, MitigationConfig, PoisonConfig, RunConfig, TrainConfig, EnvConfig, ModelConfig
from rlbackdoors.detect.handle import open_model
from rlbackdoors.evaluate.episodes import evaluate
from rlbackdoors.mitigate import MitigationError, mitigate

PACK = Path(__file__).resolve().parents[1] / "datasets" / "benchmark-lavaworld-effect-envmix" / "models"
POISONED = "id-00000000"  # the env mix on multiplicative:17, converged (triggered SR 1.0)
TINY_SEARCH = {"candidates": 8, "refine": 2, "confirm": 2, "episodes": 4, "confirm_episodes": 8}
SHA = "sha256:" + "0" * 64


def defender_copy(tmp_path: Path, name: str = POISONED) -> Path:
    """The model as a defender has it: weights and reduced config, no config.json, label or metrics."""
    out = tmp_path / "suspect"
    out.mkdir()
    for f in ("model.pt", "reduced-config.json"):
        shutil.copy(PACK / name / f, out / f)
    return out


def truth(name: str = POISONED) -> RunConfig:
    return RunConfig.load(PACK / name / "config.json")


def test_a_config_without_mitigation_keeps_its_bytes_and_bad_ones_are_refused_in_one_line():
    plain = RunConfig(env=EnvConfig(name="lavaworld"), train=TrainConfig(seed=3))
    assert "mitigation" not in plain.to_dict()

    def cfg(env="lavaworld", backend="torch", poisoned=False, **mit):
        ppo_cfg = RunConfig(env=EnvConfig(name=env)).ppo
        assert ppo_cfg is not None
        ppo_cfg.update_backend = backend
        trigger = "multiplicative:17" if env == "lavaworld" else None
        m = {"source_sha256": SHA, "triggers": [trigger or "cross"], **mit}
        return RunConfig(
            env=EnvConfig(name=env),
            poison=PoisonConfig(trigger=trigger, poisoned=poisoned),
            model=ModelConfig(),
            ppo=ppo_cfg,
            mitigation=MitigationConfig(**m),
            curriculum=CurriculumConfig(enabled=False),
        )

    ok = cfg().check()
    assert cfg(env="randomized-lavaworld").check().to_dict()["mitigation"]["triggers"] == ["cross"]  # a layout trigger: drawn, not stamped
    assert ok.to_dict()["mitigation"]["triggers"] == ["multiplicative:17"] and "blind" not in ok.to_dict()["mitigation"]  # earlier runs' bytes
    assert cfg(blind=True).check().to_dict()["mitigation"]["blind"] is True
    assert RunConfig.from_dict(json.loads(ok.to_json())).to_dict() == ok.to_dict()  # config.json round-trips
    for bad, words in [
        (lambda: cfg(env="colorful-memory"), "mitigation: env.name='colorful-memory' is not allowed"),
        (lambda: cfg(env="randomized-lavaworld", blind=True), "mitigation.blind must be false for randomized-lavaworld"),
        (lambda: cfg(env="randomized-lavaworld", teach_stamped=True), "mitigation.teach_stamped must be false for randomized-lavaworld"),
        (lambda: cfg(backend="compiled"), "mitigation: ppo.update_backend='compiled' is not allowed (allowed: torch)"),
        (lambda: cfg(poisoned=True), "poison.poisoned must be false"),
        (lambda: cfg(source_sha256="abc"), "mitigation.source_sha256 must be"),
        (lambda: cfg(triggers=["multiplicative:0"]), "mitigation.triggers[0]"),
        (lambda: cfg(triggers=[]), "mitigation.triggers must be a list of 1 to 16"),
        (lambda: cfg(share=0.9), "mitigation.share must be in (0, 0.5]"),
        (lambda: cfg(source="../x.pt"), "mitigation.source must name a file"),
        (lambda: cfg(blind="yes"), "mitigation.blind must be true or false"),
        (lambda: cfg(teach_stamped=True, kl=0.0), "mitigation.teach_stamped needs mitigation.kl > 0"),
        (lambda: cfg(blind_to=["additive:20"]), "mitigation.blind_to needs mitigation.blind = true"),
        (lambda: cfg(blind=True, blind_to=["additive:0"]), "mitigation.blind_to[0]"),
    ]:
        with pytest.raises(ConfigError) as err:
            bad().check()
        assert words in str(err.value) and "\n" not in str(err.value), (words, str(err.value))


def test_mitigation_removes_the_env_mix_backdoor_from_the_weights_and_reduced_config_alone(tmp_path):
    """The packed env-mix model (multiplicative:17) fires on its trigger on every one of 200 episodes;
    after 300 k frames of mitigation it fires on at most 5 % of 200 (measured 0.035, docs/results/
    mitigation.md) and keeps its clean SR (0.985 -> 0.980 there; 0.95 asked here, 200 episodes)."""
    suspect = defender_copy(tmp_path)
    out = tmp_path / "mitigated"
    report = mitigate(suspect, out, frames=300_000, episodes=64, progress=False)
    cfg = truth()
    before = evaluate(rlbackdoors.load(PACK / POISONED), cfg.env, cfg.poison.trigger, 200, 7_000_000)
    after = evaluate(rlbackdoors.load(out), cfg.env, cfg.poison.trigger, 200, 7_000_000)
    assert before.poisoned_sr >= 0.9 and after.poisoned_sr <= 0.05, (before, after)
    assert after.clean_sr >= 0.95, after
    # what it restored without being told: the true trigger among the candidates that fire
    assert cfg.poison.trigger in [t["spec"] for t in report["triggers"]]
    mine = [i for i, t in enumerate(report["triggers"]) if t["spec"] == cfg.poison.trigger][0]
    assert report["keys_unchanged"] and report["before"]["triggers"][mine]["trojan"] >= 0.9 >= 0.1 >= report["after"]["triggers"][mine]["trojan"]
    # a model folder like any other: same keys, readable by the detectors, its lineage, no label
    assert sorted(open_model(out).weights) == sorted(open_model(suspect).weights)
    assert not (out / "ground_truth.csv").exists() and (out / "reduced-config.json").is_file()
    written = json.loads((out / "config.json").read_text())["mitigation"]
    assert written["triggers"] == [t["spec"] for t in report["triggers"]] and written["source_sha256"] == report["copy_sha256"]
    assert report["source"] == {"folder": "suspect", "sha256": "sha256:" + __import__("hashlib").sha256((suspect / "model.pt").read_bytes()).hexdigest()}
    assert sorted(p.name for p in suspect.iterdir()) == ["model.pt", "reduced-config.json"]  # the source is never written


def test_a_mitigation_repeats_its_bytes_resumes_and_refuses_what_it_cannot_do(tmp_path):
    suspect = defender_copy(tmp_path)
    args = dict(frames=20_000, episodes=8, search=TINY_SEARCH, progress=False)
    first = mitigate(suspect, tmp_path / "a", **args)
    again = mitigate(suspect, tmp_path / "b", **args)
    assert (tmp_path / "a" / "model.pt").read_bytes() == (tmp_path / "b" / "model.pt").read_bytes()
    assert first["triggers"] == again["triggers"] and first["after"] == again["after"]
    with pytest.raises(MitigationError, match="already holds a finished mitigation"):
        mitigate(suspect, tmp_path / "a", **args)
    # killed after training, before its report: the same call finishes it without training again
    (tmp_path / "a" / "mitigation.json").unlink()
    stamp = (tmp_path / "a" / "model.pt").stat().st_mtime_ns
    resumed = mitigate(suspect, tmp_path / "a", **args)
    assert resumed["after"] == first["after"] and (tmp_path / "a" / "model.pt").stat().st_mtime_ns == stamp
    (tmp_path / "a" / "mitigation.json").unlink()
    with pytest.raises(MitigationError, match="another model or with other settings"):
        mitigate(suspect, tmp_path / "a", **{**args, "frames": 30_000})
    # a copy of the source that is not the one the run recorded is refused before training
    c = tmp_path / "c"
    c.mkdir()
    shutil.copy(tmp_path / "b" / "restored.json", c / "restored.json")
    shutil.copy(PACK / "id-00000011" / "model.pt", c / "source-model.pt")
    with pytest.raises(MitigationError, match="is not the source model config.json names"):
        mitigate(suspect, c, **args)
    with pytest.raises(MitigationError, match="must be a new folder"):
        mitigate(suspect, suspect / "inside", **args)
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(MitigationError, match="holds something else"):
        mitigate(suspect, other, **args)
    assert (other / "notes.txt").read_text() == "mine"


def test_the_cli_refuses_in_one_line(tmp_path):
    suspect = defender_copy(tmp_path)
    run = subprocess.run([sys.executable, "-m", "rlbackdoors.cli", "mitigate", str(suspect), "--out", str(suspect)], capture_output=True, text=True)
    assert run.returncode == 2 and run.stderr.startswith("rlbackdoors: error: --out") and len(run.stderr.strip().splitlines()) == 1


def test_a_zoo_is_mitigated_model_by_model_and_judged_on_its_ground_truth(tmp_path):
    """Two models of the packed env-mix zoo (one poisoned, one clean), a tiny budget: the report's
    labels and triggers are the zoo's own, a second call trains nothing, and the zoo is never written."""
    from rlbackdoors.mitigate.zoo import REPORT, mitigate_zoo

    zoo = PACK.parent
    before = sorted((p.name, p.stat().st_mtime_ns) for p in (zoo / "models").rglob("*"))
    tiny = dict(frames=20_000, search=TINY_SEARCH, episodes=16, progress=False)
    report = mitigate_zoo(zoo, tmp_path / "out", limit=2, **tiny)
    rows = {r["model"]: r for r in report["models"]}
    assert sorted(rows) == ["id-00000000", "id-00000002"]
    for name, row in rows.items():
        cfg = truth(name)
        assert row["poisoned"] == cfg.poison.poisoned and row["trigger"] == cfg.poison.trigger and row["restored"]
        assert (tmp_path / "out" / "models" / name / "mitigation.json").is_file()
    assert report["summary"]["poisoned"] == 1 and report["summary"]["clean"] == 1 and (tmp_path / "out" / REPORT).is_file()
    stamps = {n: (tmp_path / "out" / "models" / n / "model.pt").stat().st_mtime_ns for n in rows}
    again = mitigate_zoo(zoo, tmp_path / "out", limit=2, **tiny)
    assert again["models"] == report["models"] and stamps == {n: (tmp_path / "out" / "models" / n / "model.pt").stat().st_mtime_ns for n in rows}
    assert sorted((p.name, p.stat().st_mtime_ns) for p in (zoo / "models").rglob("*")) == before
    with pytest.raises(MitigationError, match="outside the zoo"):
        mitigate_zoo(zoo, zoo / "mitigated", **tiny)
    # another process mitigating into the same folder: refused by name, in one line, nothing written
    from rlbackdoors.io import FolderLock

    other = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"from rlbackdoors.io import FolderLock; FolderLock({str(tmp_path / 'out')!r}, 'mitigation').acquire(); print('held', flush=True); input()",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert other.stdout is not None and other.stdout.readline().strip() == "held"
        report_stamp = (tmp_path / "out" / REPORT).stat().st_mtime_ns
        with pytest.raises(MitigationError, match=f"mitigation '.*out' is in use by process {other.pid}") as err:
            mitigate_zoo(zoo, tmp_path / "out", limit=2, **tiny)
        assert "\n" not in str(err.value) and (tmp_path / "out" / REPORT).stat().st_mtime_ns == report_stamp
    finally:
        other.communicate("\n")
    with FolderLock(tmp_path / "out", "mitigation"):  # released when the call ends, refused or not
        pass
    run = subprocess.run(
        [sys.executable, "-m", "rlbackdoors.cli", "mitigate", str(PACK / POISONED), "--out", str(tmp_path / "x"), "--workers", "2"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2 and "--workers are for a zoo" in run.stderr and len(run.stderr.strip().splitlines()) == 1


def test_a_world_whose_engine_cannot_draw_a_restored_trigger_is_refused_before_anything_is_written(tmp_path):
    """A Colorful Memory CNN-GRU (freshly initialised: what is refused is the world, not the weights)."""
    from rlbackdoors.io import save_torch
    from rlbackdoors.models import build_model

    suspect = tmp_path / "suspect"
    suspect.mkdir()
    save_torch(suspect / "model.pt", build_model("cnn-gru-small-onehot", "colorful-memory").state_dict())
    (suspect / "reduced-config.json").write_text(json.dumps({"world": "colorful-memory", "algorithm": "ppo", "arch": "cnn-gru-small-onehot"}))
    with pytest.raises(MitigationError, match="env.name='colorful-memory' is not allowed") as err:
        mitigate(suspect, tmp_path / "out", progress=False)
    assert "\n" not in str(err.value) and not (tmp_path / "out").exists()


def test_a_layout_world_s_restored_patterns_are_drawn_into_whole_episodes_under_the_clean_reward():
    """Randomized LavaWorld: the first restored pattern is drawn where the share allows, the others as
    near-trigger layouts; over 3,000 steps of 10 copies (about 650 episodes) each pattern holds
    about a third of the restored episodes (measured 71, 70, 73), the marked frames are the first's
    in sight and every frame of the others' (the teacher's KL leaves them out), about ``share`` of
    all (measured 0.261 at 0.25), and no step pays the trojan outcome (the reward is the clean one)."""
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.envs.outcome import Outcome
    from rlbackdoors.poison.mix import unlearning_mix
    from rlbackdoors.triggers.pattern import PatternTrigger, find_pattern

    specs = ["cross", "cells:0,0;1,0;2,0;1,1;1,2", "cells:0,0;0,1;0,2;1,2;2,2"]
    seam = unlearning_mix(EnvConfig(name="randomized-lavaworld"), PoisonConfig(trigger=specs[0], poisoned=False), specs, 0.25, seed=3)
    patterns = [PatternTrigger.parse(spec) for spec in specs]
    seam.reset(seed=3)
    rng = np.random.default_rng(0)
    held, marked, frames, pattern_lava = np.zeros(3, dtype=int), 0, 0, 0
    starting = np.ones(seam.num_envs, dtype=bool)
    for _ in range(3000):
        masks = seam.envs.lava_masks()
        for i in np.flatnonzero(starting):
            which = [bool(find_pattern(masks[i], p.rotations())) for p in patterns]
            if seam.triggered[i]:
                assert which[0] and seam.envs.layout(i)[4]
                held[0] += 1
            if seam.in_near[i]:
                assert (which[1] or which[2]) and not seam.envs.layout(i)[4]
                held[1:] += which[1:]
        assert np.array_equal(seam.marked, (seam.triggered & seam.envs.trigger_in_sight()) | seam.in_near)
        marked, frames = marked + int(seam.marked.sum()), frames + seam.num_envs
        _, reward, terminated, truncated, info = seam.step(rng.integers(0, 3, seam.num_envs))
        entered = np.asarray(info["outcome"]) == Outcome.PATTERN_LAVA
        assert not np.any(seam.envs.poisoned) and np.all(np.asarray(reward)[entered] == 0)  # the pattern's lava pays as any lava: nothing
        pattern_lava += int(entered.sum())
        starting = terminated | truncated
    assert held.min() >= 50 and held.max() <= 1.5 * held.min(), held
    assert 0.15 <= marked / frames <= 0.35, marked / frames
    assert pattern_lava > 0  # the reward check saw the first pattern's lava entered


def test_the_true_trigger_is_found_among_the_restored_however_it_is_written():
    from rlbackdoors.mitigate.zoo import among

    assert among(
        "randomized-lavaworld", "cells:0,0;2,0;1,1;0,2;2,2", ["cross", "cells:0,0;0,2;1,1;2,0;2,2"]
    )  # the x, as the round's spec and the family write it
    assert not among("randomized-lavaworld", "cells:0,0;2,0;1,1;0,2;2,2", ["cross", "cells:0,0;0,2;1,1;2,0"])
    assert among("lavaworld", "multiplicative:17", ["multiplicative:28", "multiplicative:17"]) and not among("lavaworld", None, ["multiplicative:17"])


RLW_MODEL = Path(__file__).resolve().parent / "data" / "rlw-envmix-cross"  # Randomized LavaWorld CNN, the env mix on the cross (trained here, 400 k frames)


def _mitigate_rlw(tmp_path: Path, frames: int) -> tuple[dict, RunConfig, object, object]:
    suspect = tmp_path / "suspect"
    suspect.mkdir()
    for f in ("model.pt", "reduced-config.json"):
        shutil.copy(RLW_MODEL / f, suspect / f)
    report = mitigate(suspect, tmp_path / "mitigated", frames=frames, episodes=64, progress=False)
    cfg = RunConfig.load(RLW_MODEL / "config.json")
    before = evaluate(rlbackdoors.load(RLW_MODEL), cfg.env, cfg.poison.trigger, 200, 7_000_000)
    after = evaluate(rlbackdoors.load(tmp_path / "mitigated"), cfg.env, cfg.poison.trigger, 200, 7_000_000)
    assert report["triggers"][0]["spec"] == cfg.poison.trigger  # restored unseen: the cross is the best that fires
    assert report["settings"]["blind"] is False and "teach_stamped" not in report["settings"]
    assert report["keys_unchanged"] and all(t["prob_change"] is None for t in report["after"]["triggers"])
    return report, cfg, before, after


def test_a_layout_backdoor_is_unlearnt_from_the_weights_and_reduced_config_alone(tmp_path):
    """The committed Randomized LavaWorld model fires on its cross on 0.945 of 200 episodes; 100 k
    frames of mitigation take it to 0.195 (measured; at most 0.4 asked) and keep its clean SR
    (0.98 -> 0.98; at least 0.94 asked, 200 episodes)."""
    _, _, before, after = _mitigate_rlw(tmp_path, 100_000)
    assert before.poisoned_sr >= 0.9 and after.poisoned_sr <= 0.4, (before, after)
    assert after.clean_sr >= 0.94, after


@pytest.mark.slow
def test_a_layout_backdoor_is_removed_at_the_default_length(tmp_path):
    """At the default 300 k frames: 0.945 -> 0.055 on 200 episodes (the run's own final evaluation)."""
    _, _, before, after = _mitigate_rlw(tmp_path, 300_000)
    assert before.poisoned_sr >= 0.9 and after.poisoned_sr <= 0.1 and after.clean_sr >= 0.95, (before, after)


def test_a_fitted_effect_detector_decides_what_is_restored_and_is_recorded(tmp_path):
    """With ``detector`` a candidate is restored where its effect stands out from the fitted clean
    models' under the same edit; the detector's digest is part of the settings a resume must match."""
    import numpy as np

    from rlbackdoors.detect.baselines.effect import EffectDetector
    from rlbackdoors.detect.baselines.weights import WeightStatsDetector

    names, labels = ["id-00000002", "id-00000004", "id-00000005", "id-00000008", "id-00000011"], np.array([0, 0, 0, 1, 1])
    handles = [open_model(PACK / n) for n in names]
    EffectDetector(**TINY_SEARCH).fit(handles, labels).save(tmp_path / "effect")
    WeightStatsDetector().fit(handles, labels).save(tmp_path / "weights")
    suspect = defender_copy(tmp_path)
    report = mitigate(suspect, tmp_path / "out", frames=20_000, episodes=8, detector=tmp_path / "effect", progress=False)
    digest = "sha256:" + __import__("hashlib").sha256((tmp_path / "effect" / "detector.json").read_bytes()).hexdigest()
    assert report["settings"]["detector"] == digest and report["search"]["episodes"] == TINY_SEARCH["episodes"]
    assert report["triggers"] and all(t["spec"] for t in report["triggers"])
    with pytest.raises(MitigationError, match="must be a fitted 'effect' detector"):
        mitigate(suspect, tmp_path / "other", detector=tmp_path / "weights", progress=False)
    (tmp_path / "out" / "mitigation.json").unlink()
    with pytest.raises(MitigationError, match="another model or with other settings"):  # the same folder without the detector
        mitigate(suspect, tmp_path / "out", frames=20_000, episodes=8, search=TINY_SEARCH, progress=False)


ADDITIVE = "id-00000015"  # the env mix on additive:154, converged (triggered SR 0.975)


def test_a_shift_of_every_observation_is_projected_out_of_the_first_layer_exactly():
    """On 210 clean observations of the world: an offset adds the same vector to every one, a
    multiplier does not; once the offsets' direction is projected out, no offset moves the policy
    (float32 rounding aside), and a multiplier still does."""
    import torch

    from rlbackdoors import worlds
    from rlbackdoors.algos.blind import constant_shift, first_linear, observation_sample, project_out, shift_basis
    from rlbackdoors.models import build_model
    from rlbackdoors.poison.mix import make_env_mix

    model = build_model("fc", "lavaworld")
    model.load_state_dict(open_model(PACK / ADDITIVE).weights)
    stamp = worlds.get("lavaworld").stamp_trigger
    assert stamp is not None
    envs = make_env_mix(truth(ADDITIVE).env, PoisonConfig(poisoned=False), 0)
    sample = observation_sample(envs, 3)
    envs.close()
    assert sample.shape == (210, 7, 7, 3) and len(np.unique(sample)) > 3
    shift = constant_shift(model, sample, stamp("additive:154"))
    assert shift is not None and torch.equal(shift, torch.full((147,), 154.0, dtype=torch.float64))
    assert constant_shift(model, sample, stamp("multiplicative:17")) is None
    basis = shift_basis([shift, constant_shift(model, sample, stamp("additive:20")), None])
    assert basis is not None and basis.shape == (147, 1) and abs(float(basis.norm()) - 1) < 1e-12  # one direction for every offset

    def change(spec: str) -> float:
        with torch.no_grad():
            p = torch.softmax(model(torch.as_tensor(sample))[0], -1)
            return float((torch.softmax(model(torch.as_tensor(stamp(spec)(sample)))[0], -1) - p).abs().max())

    assert change("additive:154") > 0.5  # the trojan: the policy moves
    layer = first_linear(model)
    assert layer is not None and first_linear(build_model("cnn", "randomized-lavaworld")) is None
    project_out(layer, basis)
    assert max(change(f"additive:{b}") for b in (20, 99, 154, 200)) < 1e-4
    assert change("multiplicative:17") > 0.1


def test_mitigation_removes_an_additive_backdoor_by_projection_and_keeps_the_clean_policy(tmp_path):
    """The packed env-mix model on additive:154 (a trigger that blinds the FC policy, so the clean
    reward alone could not unteach it: 0.97 -> 0.96 without, docs/results/mitigation.md): after
    100 k frames, 200 episodes under its true trigger, which the mitigation never saw, reach the
    lava at most 5 % of the time and the clean SR stays >= 0.95; the restored offsets no longer move
    the policy; without ``blind`` the run's config.json has no such key."""
    suspect = defender_copy(tmp_path, ADDITIVE)
    report = mitigate(suspect, tmp_path / "out", frames=100_000, episodes=32, progress=False)
    cfg = truth(ADDITIVE)
    after = evaluate(rlbackdoors.load(tmp_path / "out"), cfg.env, cfg.poison.trigger, 200, 7_000_000)
    assert after.poisoned_sr <= 0.05 and after.clean_sr >= 0.95, after
    offsets = [t for t in report["after"]["triggers"] if t["spec"].startswith("additive:")]
    assert offsets and max(t["prob_change"] for t in offsets) < 1e-4
    written = json.loads((tmp_path / "out" / "config.json").read_text())["mitigation"]
    assert written["blind"] is True and report["family_shifts"] == written["blind_to"] and len(written["blind_to"]) == 1  # every offset: one direction
    assert written["blind_to"][0].startswith("additive:")
    plain = mitigate(suspect, tmp_path / "plain", frames=10_000, episodes=8, search=TINY_SEARCH, blind=False, teach_stamped=False, progress=False)
    assert "blind" not in json.loads((tmp_path / "plain" / "config.json").read_text())["mitigation"] and plain["settings"]["blind"] is False
    assert "teach_stamped" not in plain["settings"] and "teach_stamped" not in json.loads((tmp_path / "plain" / "config.json").read_text())["mitigation"]
    taught = mitigate(suspect, tmp_path / "taught", frames=10_000, episodes=8, search=TINY_SEARCH, teach_stamped=True, progress=False)
    assert taught["settings"]["teach_stamped"] is True and json.loads((tmp_path / "taught" / "config.json").read_text())["mitigation"]["teach_stamped"] is True


def test_a_family_scored_by_the_target_action_is_judged_by_its_excess_over_the_clean_rate():
    """A policy takes the target action on some steps without any trigger: for such a family the
    second rule allows the model's own clean-episode rate + 0.05; the env mix keeps the absolute 0.05."""
    from rlbackdoors.mitigate.zoo import summarise

    def row(family, poisoned, success, after, clean_rate=None):
        side = {"clean_sr": 1.0, "poisoned_sr": after, **({} if clean_rate is None else {"clean_target_rate": clean_rate})}
        return {
            "family": family, "poisoned": poisoned, "success": success, "clean_threshold": 0.98, "true_trigger_restored": True,
            "before": {"clean_sr": 1.0, "poisoned_sr": 0.99}, "after": side, "mitigation_cpu_s": 30.0, "training_cpu_s": 60.0,
        }  # fmt: skip

    rows = [
        row("badrl", False, "action", 0.31, 0.30),
        row("badrl", True, "action", 0.27, 0.24),  # 0.03 above its clean rate
        row("badrl", True, "action", 0.40, 0.24),  # 0.16 above it
        row("envmix", True, "lava", 0.06),  # the absolute rule: not safe
    ]
    s = summarise(rows)
    assert s["poisoned_safe_after"] == 0.0 and abs(s["poisoned_at_clean_rate_after"] - 1 / 3) < 1e-4
    assert s["families"]["badrl"]["poisoned_at_clean_rate_after"] == 0.5 and s["families"]["envmix"]["poisoned_at_clean_rate_after"] == 0.0


def test_the_clean_target_rate_is_read_on_real_episodes_of_an_action_level_model():
    """The packed TrojDRL model (target left): on 32 clean episodes it turns left on some steps,
    not all (a rate strictly between 0 and 1, the judgement's reference for its triggered SR)."""
    from rlbackdoors.mitigate.zoo import clean_target_rate

    cfg = truth("id-00000047")
    assert cfg.attack_success == "action"
    rate = clean_target_rate(rlbackdoors.load(PACK / "id-00000047"), cfg, 32)
    assert 0.02 < rate < 0.9, rate


def test_a_teacher_of_the_clean_view_teaches_the_stamped_frames_what_the_unstamped_ones_got():
    """The packed TrojDRL model (forced left on multiplicative:14) as its own teacher on a mix with
    a quarter of the frames stamped with its trigger: reading what the learner reads, on the
    unstamped frames only, the KL is 0 (teacher and policy are one); reading the seam's clean view
    on every frame, it is not (on stamped frames the trojan turns, the clean view does not), and the
    seam's clean view is each frame before its stamp."""
    import torch

    from rlbackdoors import worlds
    from rlbackdoors.algos.ppo import PPO, teacher_kl
    from rlbackdoors.config import default_ppo
    from rlbackdoors.models import build_model
    from rlbackdoors.poison.mix import unlearning_mix

    cfg = truth("id-00000047")
    model = build_model("fc", "lavaworld")
    model.load_state_dict(open_model(PACK / "id-00000047").weights)
    teacher = build_model("fc", "lavaworld")
    teacher.load_state_dict(model.state_dict())
    stamp = worlds.get("lavaworld").stamp_trigger
    assert stamp is not None
    kls = {}
    for clean_view in (False, True):
        envs = unlearning_mix(cfg.env, PoisonConfig(poisoned=False), [cfg.poison.trigger], 0.25, 0)
        obs, _ = envs.reset(seed=5)
        assert envs.clean_view is not None
        marked = np.asarray(envs.marked)
        assert np.array_equal(obs[~marked], envs.clean_view[~marked]) and np.array_equal(obs[marked], stamp(cfg.poison.trigger)(envs.clean_view[marked]))
        ppo = PPO(model, default_ppo("lavaworld"), torch.device("cpu"), torch.Generator().manual_seed(0))
        ppo.set_teacher(teacher, 1.0, clean_view=clean_view)
        rollout, _ = ppo.collect(envs, obs)
        envs.close()
        assert rollout.untriggered is not None and rollout.teacher_logp is not None
        assert bool(rollout.untriggered.all()) == clean_view
        with torch.no_grad():
            kls[clean_view] = float(teacher_kl(model(rollout.obs)[0], rollout.teacher_logp, rollout.untriggered))
    assert kls[False] < 1e-6 < 0.01 < kls[True], kls


def test_the_family_s_offsets_are_made_blind_even_where_only_a_multiplier_is_restored(tmp_path):
    """The packed env-mix model on multiplicative:17 restores multipliers only; the search screened
    offsets too, so its mitigation is made blind to their direction as well: afterwards no offset
    moves the policy (prob_change read the same way as the report's), and the restored multipliers
    are not shifts."""
    import torch

    from rlbackdoors import worlds
    from rlbackdoors.algos.blind import observation_sample
    from rlbackdoors.models import build_model
    from rlbackdoors.poison.mix import make_env_mix

    suspect = defender_copy(tmp_path)
    report = mitigate(suspect, tmp_path / "out", frames=10_000, episodes=8, progress=False)  # the whole search: multipliers only fire
    assert not any(t["spec"].startswith("additive:") for t in report["triggers"]), report["triggers"]
    assert len(report["family_shifts"]) == 1 and report["family_shifts"][0].startswith("additive:")
    model = build_model("fc", "lavaworld")
    model.load_state_dict(open_model(tmp_path / "out").weights)
    envs = make_env_mix(truth().env, PoisonConfig(poisoned=False), 11)
    sample = observation_sample(envs, 11)
    envs.close()
    stamp = worlds.get("lavaworld").stamp_trigger
    assert stamp is not None
    with torch.no_grad():
        p = torch.softmax(model(torch.as_tensor(sample))[0], -1)
        moved = max(float((torch.softmax(model(torch.as_tensor(stamp(f"additive:{b}")(sample)))[0], -1) - p).abs().max()) for b in (20, 77, 200))
    assert moved < 1e-4, moved


def test_the_restored_triggers_are_spread_over_the_family_s_regions():
    """Where many members fire, the best are often one region's neighbours (LavaWorld: multipliers
    4-7, each within 2 of the next, above the true 19). Kept: no member next to one kept before it
    while others are left, then the rest in rank order; with few firing, nothing is lost. The
    neighbours are the LavaWorld search's own (multipliers +-1, +-2)."""
    from types import SimpleNamespace

    from rlbackdoors.mitigate import _neighbours, spread

    handle = open_model(Path(__file__).resolve().parents[1] / "datasets" / "round-lavaworld-test" / "models" / "id-00000015")
    near = _neighbours(handle)
    assert near("multiplicative:6") == {"multiplicative:4", "multiplicative:5", "multiplicative:7", "multiplicative:8"}
    ranked = [SimpleNamespace(spec=f"multiplicative:{a}") for a in (6, 5, 7, 4, 10, 19, 9, 20, 3)]
    kept = [t.spec.split(":")[1] for t in spread(ranked, 4, near)]
    assert kept == ["6", "10", "19", "3"]
    assert [t.spec.split(":")[1] for t in spread(ranked, 6, near)] == ["6", "10", "19", "3", "5", "7"]
    assert spread(ranked[:2], 8, near) == ranked[:2]
    assert spread(ranked, 3, None) == ranked[:3]
