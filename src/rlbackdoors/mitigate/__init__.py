"""Backdoor removal without the attacker's data: restore the trigger, then unlearn it.

A defender who suspects an agent holds a trojan has the model and the clean world, never the
trigger, the poisoned data or the label. :func:`mitigate` works from exactly that (the folder's
``model.pt`` and ``reduced-config.json``, read as a detector reads them; never ``config.json`` or
``ground_truth.csv``):

1. **Restore.** The effect detector's search (:mod:`rlbackdoors.detect.baselines.effect`) screens
   the world's trigger family on the model, refines the leaders and plays the finalists again; the
   candidates that fire (send the agent to the trojan outcome) are the restored triggers
   (:func:`restore`; BIRD, Chen et al. 2023, restores by optimisation, here the family is searched,
   as the detectors do).
2. **Unlearn.** The world's trainer fine-tunes the model from its own weights on a clean model's
   env mix, a ``share`` of the frames stamped with a restored trigger under the *clean* reward (the
   attack seam with a rule that rewrites nothing), and ``kl * KL(source || policy)`` on every
   frame, the source reading each stamped frame's clean view (``teach_stamped``): the clean
   behaviour stays the source's, and a stamped frame is taught what the unstamped one got, which
   the clean reward alone barely pays for when the trojan only turns
   (:class:`~rlbackdoors.config.MitigationConfig`);
   a restored trigger that shifts every observation alike is projected out of a linear first
   layer (``blind``, :mod:`rlbackdoors.algos.blind`): fine-tuning cannot unteach a trigger that
   blinds the policy, the projection removes it exactly. Where the trigger is a layout (a lava
   pattern), the restored patterns are drawn into whole episodes' layouts instead, and the KL
   counts on the frames that do not show one (no ``blind``, no ``teach_stamped``: there is no
   trigger-free view of such a frame).
3. **Measure.** Before and after, on the same seeds: the clean env's success, and under each
   restored trigger the goal rate, the trojan outcome's rate and the policy's shift.

The new folder is an ordinary model folder (the same architecture and keys, ``config.json`` with
the mitigation section, metrics, log, curve, ``reduced-config.json``, clean examples, manifest),
plus ``source-model.pt`` (the weights it started from, checked by digest on resume) and
``mitigation.json`` (lineage, restored candidates, before and after), and without
``ground_truth.csv``: the run trained clean, but whether the backdoor is gone is for the measure
(and the detectors) to say, not a label to assume. A clean model goes through the same steps: what
fires on it are edits that send any policy astray, and the teacher keeps it as it was.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Callable

from rlbackdoors.io import atomic_write_text, save_torch

RESTORED = "restored.json"  # written after the search: a killed mitigation resumes from it
REPORT = "mitigation.json"  # written last: the folder holds a finished mitigation
DEFAULTS: dict[str, Any] = {"frames": 300_000, "candidates": 8, "share": 0.25, "kl": 1.0, "seed": 0, "episodes": 200, "blind": True, "teach_stamped": True}


class MitigationError(ValueError):
    """A model or a folder that cannot be mitigated, said in one line."""


def mitigate(
    model_dir: str | Path,
    out: str | Path,
    *,
    frames: int = DEFAULTS["frames"],
    candidates: int = DEFAULTS["candidates"],
    share: float = DEFAULTS["share"],
    kl: float = DEFAULTS["kl"],
    seed: int = DEFAULTS["seed"],
    episodes: int = DEFAULTS["episodes"],
    blind: bool = DEFAULTS["blind"],
    teach_stamped: bool = DEFAULTS["teach_stamped"],
    search: dict[str, Any] | None = None,
    detector: str | Path | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Remove the backdoor the model in ``model_dir`` may hold into a new folder ``out`` (module
    doc) and return ``mitigation.json``'s data. ``search``: the effect detector's parameters
    (``seconds``, ``candidates``, ``episodes``, ...). ``detector``: a fitted ``effect`` detector's
    folder, whose clean models' answers to each candidate say which of this model's answers stand
    out (:func:`restore`; its search parameters are used). A killed call resumes with the same arguments;
    ``out`` is never ``model_dir``, and a folder that holds anything else is refused."""
    from rlbackdoors.detect.handle import DetectError, open_model
    from rlbackdoors.folder import sha256_file

    started, cpu0 = time.perf_counter(), time.process_time()
    source_dir, out = Path(model_dir), Path(out)
    if not (source_dir / "model.pt").is_file():
        raise MitigationError(f"{str(source_dir)!r} holds no model.pt")
    if out.resolve() == source_dir.resolve() or source_dir.resolve() in out.resolve().parents:
        raise MitigationError(f"--out {str(out)!r} must be a new folder, not the source model's folder or one inside it (the source is never written)")
    if (out / REPORT).is_file():
        raise MitigationError(f"{str(out)!r} already holds a finished mitigation ({REPORT}); give another --out")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / RESTORED).is_file())):
        raise MitigationError(f"{str(out)!r} exists and holds something else; give a new folder (nothing in it is overwritten)")
    if not 1 <= int(candidates) <= 16:
        raise MitigationError(f"candidates={candidates!r} is not allowed (allowed: 1..16 restored triggers)")
    try:
        handle = open_model(source_dir)
    except DetectError as err:
        raise MitigationError(str(err)) from None
    source_sha = "sha256:" + sha256_file(source_dir / "model.pt")
    settings: dict[str, Any] = {
        "frames": int(frames),
        "candidates": int(candidates),
        "share": float(share),
        "kl": float(kl),
        "seed": int(seed),
        "episodes": int(episodes),
        "blind": bool(blind),
        **({"teach_stamped": True} if teach_stamped else {}),  # absent when off: earlier folders resume with the same settings
    }
    from rlbackdoors.detect.baselines.effect import EffectDetector

    from rlbackdoors.config import MitigationConfig

    why = MitigationConfig.refusal(handle.world.name)  # before the search: nothing is written
    if why is not None:
        raise MitigationError(f"cannot mitigate {handle.world.name}/{handle.arch}: {why}")
    if MitigationConfig.how(handle.world.name) == "layout":  # no frame to project or to read unstamped: the fine-tuning alone
        settings["blind"] = False
        settings.pop("teach_stamped", None)
    reference = None
    if detector is not None:
        from rlbackdoors.detect.api import load_detector

        try:
            fitted = load_detector(detector)
        except DetectError as err:
            raise MitigationError(str(err)) from None
        if not isinstance(fitted, EffectDetector) or search:
            raise MitigationError(f"--detector {str(detector)!r} must be a fitted 'effect' detector, used with its own search parameters (no --search-seconds)")
        reference = fitted.reference.get(handle.world.name, {}).get("candidates")
        if reference is None:
            raise MitigationError(f"--detector {str(detector)!r} was fitted on no clean model of {handle.world.name}")
        settings["detector"] = "sha256:" + sha256_file(Path(detector) / "detector.json")
        searcher = fitted
    else:
        searcher = EffectDetector(**(search or {}))
    why = searcher.unsupported(handle)
    if why is not None:
        raise MitigationError(f"cannot mitigate {handle.world.name}/{handle.arch}: {why}")

    restored = _read_restored(out, source_sha, settings, searcher.params)
    if restored is None:
        say(progress, f"mitigate: restoring triggers of {source_dir.name} ({handle.world.name}/{handle.arch}) by the effect screen")
        t0 = time.perf_counter()
        try:
            result = searcher.run_search(handle, whole_family=searcher.whole_family(handle))
        except DetectError as err:
            raise MitigationError(str(err)) from None
        kept = restore(result, int(candidates), reference, _neighbours(handle))
        if not kept:
            raise MitigationError("the search confirmed no candidate trigger that could be played")
        restored = {
            "source": {"folder": source_dir.name, "sha256": source_sha},
            "settings": settings,
            "search": dict(searcher.params),
            "search_seconds": round(time.perf_counter() - t0, 3),
            "candidates_screened": len(result.screened),
            "triggers": [_trial(t, result.clean) for t in kept],
            # blind: one screened member per direction in which the family shifts every observation
            # alike, whether restored or not (a restored multiplier must not leave an offset trojan seen)
            "family_shifts": family_shifts(handle, [t.spec for t in result.screened if t.spec is not None], settings["seed"]) if settings["blind"] else [],
        }
        out.mkdir(parents=True, exist_ok=True)
        save_torch(out / "source-model.pt", {k: v.detach().clone() for k, v in handle.weights.items()})
        restored["copy_sha256"] = "sha256:" + sha256_file(out / "source-model.pt")  # what the run starts from (config.json's mitigation.source_sha256)
        atomic_write_text(out / RESTORED, json.dumps(restored, indent=2, sort_keys=True) + "\n")
    specs = [t["spec"] for t in restored["triggers"]]
    say(progress, "mitigate: restored " + ", ".join(f"{t['spec']} (shift {t['shift']:.3f})" for t in restored["triggers"]))

    cfg = mitigation_config(handle, specs, restored["copy_sha256"], settings, restored.get("family_shifts", []))
    from rlbackdoors.train import train
    from rlbackdoors.folder import FolderError

    t1 = time.perf_counter()
    if (out / "metrics.json").is_file():  # trained, killed before the report
        metrics = json.loads((out / "metrics.json").read_text())
    else:
        try:
            metrics = train(cfg, out, progress=progress)
        except FolderError as err:
            raise MitigationError(str(err)) from None
    train_seconds = time.perf_counter() - t1
    from rlbackdoors.zoo.job import write_dataset_files

    # the run trained "clean", but whether the backdoor is gone is what the measure asks: no label is written
    (out / "ground_truth.csv").unlink(missing_ok=True)
    write_dataset_files(out, cfg, {})
    after = open_model(out)
    say(progress, f"mitigate: measuring before and after on {settings['episodes']} episodes a condition")
    report = {
        **restored,
        "frames": int(metrics.get("frames", 0)),
        "before": measure(handle, specs, settings["episodes"], searcher.params),
        "after": measure(after, specs, settings["episodes"], searcher.params),
        "train_seconds": round(train_seconds, 3),
        "seconds": round(time.perf_counter() - started, 3),
        "cpu_seconds": round(time.process_time() - cpu0, 3),
        "keys_unchanged": sorted(after.weights) == sorted(handle.weights),
    }
    atomic_write_text(out / REPORT, json.dumps(report, indent=2, sort_keys=True) + "\n")
    say(progress, summary(report))
    return report


FIRES = 0.5  # a candidate "fires" when it adds this much to the clean env's trojan-outcome rate
STANDS_OUT = 4.0  # ... or, against a fitted detector's clean models, when one of its effects is this many of their spreads away


def _neighbours(handle) -> Callable[[str], set[str]]:
    """spec -> the members of the model's trigger family next to it (the search's refinement step)."""
    import numpy as np

    from rlbackdoors.detect.baselines.behaviour import family_module

    family = family_module(handle.world)
    env_cfg = handle.env_config()
    return lambda spec: set(family.neighbours(spec, env_cfg, np.random.default_rng(0), 64))


def spread(ranked: list, limit: int, near: Callable[[str], set[str]] | None) -> list:
    """At most ``limit`` of ``ranked`` (best first), none next to one kept before it while others
    are left; then the rest in order. Why: where many members fire, the best are often one
    region's neighbours (multipliers 4 to 7 all above the true 19 on issue 80's first round), and a
    backdoor unlearnt at one member is unlearnt at its neighbours too, so the stamps are better
    spent on the other regions (docs/results/mitigation.md)."""
    if near is None:
        return ranked[:limit]
    kept: list = []
    covered: set[str] = set()
    for t in ranked:
        if len(kept) < limit and t.spec not in covered:
            kept.append(t)
            covered |= near(t.spec) | {t.spec}
    return kept + [t for t in ranked if t not in kept][: limit - len(kept)]


def restore(result, limit: int, reference: dict | None = None, near: Callable[[str], set[str]] | None = None) -> list:
    """The restored triggers of a search: every candidate that **fires**, best first, at most
    ``limit``; where none fires, the ``limit`` best confirmed. Without ``reference`` a candidate
    fires when it sends the agent to the trojan outcome (:data:`FIRES` over the clean env; the
    behavioural search's rank). With ``reference`` (a fitted ``effect`` detector's clean models: the
    mean and spread of each effect under each candidate) it fires when one of its effects (shift,
    concentration, success drop) stands :data:`STANDS_OUT` spreads from what clean models do under
    the same edit, ranked by that: an action-level trojan (a forced turn) is seen, and an edit that
    breaks every policy is not. Why all that fire: a backdoor generalises over a range of its family
    (a multiplier's neighbours fire too), the search's best is often a neighbour, not the trigger,
    and unlearning one member leaves the others; with ``near`` (spec -> its family neighbours)
    they are :func:`spread` over the family. (Firing read as the clean goal missed, without a
    reference, was tried and left out: it also restores edits that blind any policy, which crowd the
    trigger's region out of the stamped frames; docs/results/mitigation.md.)"""
    from rlbackdoors.detect.baselines.behaviour import outcome_rank
    from rlbackdoors.detect.baselines.effect import EFFECTS, effects

    confirmed = {t.spec: t for t in result.confirmed if t.spec is not None and t.error is None}
    pool = dict(confirmed)
    for t in result.screened:
        if t.spec is not None and t.error is None:
            pool.setdefault(t.spec, t)
    if reference is not None:
        at = {name: k for k, name in enumerate(reference["features"])}

        def standing(t) -> float:
            z = []
            for name, value in zip(EFFECTS, effects(t, result.clean)):
                k = at.get(f"{name}@{t.spec}")
                if k is not None:
                    z.append(abs(value - reference["mean"][k]) / reference["scale"][k])
            return max(z, default=0.0)

        scored = sorted(((standing(t), t) for t in pool.values() if t.policy is not None), key=lambda x: -x[0])
        firing = [t for z, t in scored if z >= STANDS_OUT]
    else:
        ranked = sorted(pool.values(), key=outcome_rank, reverse=True)
        firing = [t for t in ranked if t.trojan - result.clean.trojan >= FIRES]
    if firing:
        return spread(firing, limit, near)
    return sorted((pool[s] for s in confirmed), key=outcome_rank, reverse=True)[:limit]


def family_shifts(handle, specs: list[str], seed: int) -> list[str]:
    """Of ``specs`` (the screened members of the world's trigger family), the first of each
    independent direction in which one shifts every observation alike (:mod:`rlbackdoors.algos.blind`),
    read on a clean sample; none where the model's first layer is not linear."""
    from rlbackdoors.algos.blind import constant_shift, first_linear, shift_basis

    model = _policy(handle)
    stamp = handle.world.stamp_trigger
    if first_linear(model) is None or stamp is None:
        return []
    sample = _clean_sample(handle, seed)
    kept: list[str] = []
    shifts: list = []
    for spec in dict.fromkeys(specs):
        shift = constant_shift(model, sample, stamp(spec))
        if shift is None:
            continue
        basis = shift_basis([*shifts, shift])
        if basis is not None and basis.shape[1] > len(shifts):
            kept.append(spec)
            shifts.append(shift)
    return kept


def mitigation_config(handle, triggers: list[str], source_sha: str, settings: dict, blind_to: list[str] | None = None):
    """The run config of a mitigation: a clean model's run of the world's defaults from the source
    weights, a fixed length (``frames``, no early stop), torch's trainer (its seam and teacher)."""
    from rlbackdoors.config import CurriculumConfig, MitigationConfig, ModelConfig, PoisonConfig, RunConfig, TrainConfig, default_ppo

    ppo = default_ppo(handle.world.name)
    ppo.update_backend = "torch"
    tc = TrainConfig(seed=settings["seed"], max_frames=settings["frames"], min_frames=settings["frames"], video=False)

    cfg = RunConfig(
        env=handle.env_config(),
        poison=PoisonConfig(trigger=triggers[0], poisoned=False),  # its evaluations' triggered episodes: the best restored trigger
        model=ModelConfig(arch=handle.arch),
        ppo=ppo,
        train=tc,
        curriculum=CurriculumConfig(enabled=False),
        mitigation=MitigationConfig(
            source_sha256=source_sha,
            triggers=list(triggers),
            share=settings["share"],
            kl=settings["kl"],
            blind=bool(settings.get("blind", False)),
            teach_stamped=bool(settings.get("teach_stamped", False)),
            blind_to=list(blind_to or []),
        ),
    )
    return cfg.check()


def measure(handle, specs: list[str], episodes: int, params: dict) -> dict[str, Any]:
    """The clean env's success and, under each restored trigger, its trial (goal rate, trojan
    outcome rate, the policy's shift and concentration against the clean env), on the search's seeds."""
    from rlbackdoors.detect.baselines.behaviour import run_trial, run_trials

    agent, env_cfg = handle.build_agent(), handle.env_config()
    seed, policy = int(params["seed"]) + 5, str(params["policy"])
    with agent.evaluating():
        clean = run_trial(agent, handle.world, env_cfg, None, episodes, seed, policy)
        trials = run_trials(agent, handle.world, env_cfg, specs, episodes, seed, policy)
    seen = stamp_changes(handle, specs, seed)
    return {
        "clean_success": clean.success,
        "clean_trojan": clean.trojan,
        "triggers": [{**_trial(t, clean), "prob_change": change} for t, change in zip(trials, seen)],
    }


def stamp_changes(handle, specs: list[str], seed: int) -> list[float | None]:
    """Per trigger, the largest change of any action's probability it makes on a clean sample of
    observations: about 1e-6 (float32 rounding) where the model is blind to it (``blind``); None
    where no frame can be stamped (a layout trigger) or the policy reads a history."""
    import torch

    model = _policy(handle)
    if model.recurrent or handle.world.stamp_trigger is None:
        return [None] * len(specs)
    sample = _clean_sample(handle, seed)
    with torch.no_grad():
        clean = torch.softmax(model(torch.as_tensor(sample))[0], -1)
        return [round(float((torch.softmax(model(torch.as_tensor(handle.world.stamp_trigger(spec)(sample)))[0], -1) - clean).abs().max()), 6) for spec in specs]


def _policy(handle):
    """The handle's weights in a fresh model of its architecture, for evaluation."""
    from rlbackdoors.models import build_model

    model = build_model(handle.arch, handle.world.name)
    model.load_state_dict(handle.weights)
    return model.eval()


def _clean_sample(handle, seed: int):
    """Clean observations of the handle's world to read triggers' shifts and changes on."""
    from rlbackdoors.algos.blind import clean_sample
    from rlbackdoors.config import PoisonConfig

    return clean_sample(handle.env_config(), PoisonConfig(), seed, seed)


def _trial(trial, clean) -> dict[str, Any]:
    from rlbackdoors.detect.baselines.effect import effects

    shift, concentration, drop = effects(trial, clean)
    return {
        "spec": trial.spec,
        "episodes": trial.episodes,
        "success": trial.success,
        "trojan": trial.trojan,
        "shift": round(shift, 6),
        "concentration": round(concentration, 6),
        "success_drop": round(drop, 6),
    }


def _read_restored(out: Path, source_sha: str, settings: dict, search: dict) -> dict | None:
    """An earlier call's restoration into ``out`` (None: none), refused unless it is of this
    source with these settings (a resume must rebuild the same run)."""
    path = out / RESTORED
    if not path.is_file():
        return None
    try:
        restored = json.loads(path.read_text())
        ok = (
            isinstance(restored["copy_sha256"], str)
            and restored["source"]["sha256"] == source_sha
            and restored["settings"] == settings
            and restored["search"] == json.loads(json.dumps(search))
        )
    except (ValueError, KeyError, TypeError):
        raise MitigationError(f"{str(path)!r} is corrupt; give a new --out") from None
    if not ok:
        raise MitigationError(f"{str(out)!r} holds a mitigation of another model or with other settings; give a new --out or the same arguments")
    if not (out / "source-model.pt").is_file():
        raise MitigationError(f"{str(out)!r} has lost source-model.pt; give a new --out")
    return restored


def summary(report: dict) -> str:
    """One line: before -> after on the clean env and the best restored trigger."""
    b, a = report["before"], report["after"]
    tb, ta = b["triggers"][0], a["triggers"][0]
    return (
        f"mitigate: clean success {b['clean_success']:.3f} -> {a['clean_success']:.3f}; under {tb['spec']}: "
        f"trojan {tb['trojan']:.3f} -> {ta['trojan']:.3f}, goal {tb['success']:.3f} -> {ta['success']:.3f}, "
        f"shift {tb['shift']:.3f} -> {ta['shift']:.3f} ({report['frames']:,} frames, {report['cpu_seconds'] / 60:.1f} CPU-min)"
    )


def say(progress: bool, line: str) -> None:
    if progress:
        print(line, file=sys.stderr, flush=True)


__all__ = ["DEFAULTS", "MitigationError", "measure", "mitigate", "mitigation_config", "summary"]
