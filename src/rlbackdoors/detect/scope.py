"""What a fitted detector was fitted for, and the refusal of anything outside it.

A fitted classifier means something only for models like those it was fitted on, with the
features it was fitted on. Scored outside that, it still returns a probability, and the number
is wrong without a word: a detector fitted on one world gave another world's model 1.000, and
``statistics: false`` against a detector fitted with ``true`` moved a model from 0.000013 to 0.49
(issue 31). So :func:`record` keeps, at fit time, every (world, group) the fit saw, each world's
env settings (grid size, lava count, cubes, episode cut, ...), the parameters and the package
version; :func:`model_mismatch` and :func:`params_mismatch` name what a model or a set of
metaparameters has that the fit did not see. ``detect score`` and ``detect infer`` refuse on
either (one ``rlbackdoors: error:`` line) unless ``--allow-mismatch``, and then flag every such
result instead of scoring it quietly. A model folder that contradicts itself (its settings name
another architecture than its weights fit: :class:`rlbackdoors.detect.handle.Contradiction`) is
treated the same way on every path.
"""

from __future__ import annotations

from rlbackdoors import __version__
from rlbackdoors.detect.api import Detector
from rlbackdoors.detect.handle import DetectError, ModelHandle

SKIPPED_SETTINGS = ("engine",)  # how an env is computed, not which env it is
ALLOW_HINT = "pass --allow-mismatch to score it anyway (flagged in the result)"


def model_scope(detector: Detector, handle: ModelHandle) -> dict:
    """The facts of one model that a fit must have seen: world, the detector's group for it
    (world and architecture, or world only where its features mean the same for every
    architecture) and the world's env settings (defaults filled in)."""
    cfg = handle.env_config()
    fields = [k for k in ("max_steps", *handle.world.env_fields) if k not in SKIPPED_SETTINGS]
    return {"world": handle.world.name, "group": detector.scope_group(handle), "env": {k: getattr(cfg, k) for k in fields}}


def record(detector: Detector, scopes: list[dict]) -> dict:
    """``fitted_on`` of a detector fitted on models of ``scopes`` (module doc)."""
    env: dict[str, list[dict]] = {}
    for scope in scopes:
        seen = env.setdefault(scope["world"], [])
        if scope["env"] not in seen:
            seen.append(scope["env"])
    return {
        "worlds": sorted(env),
        "groups": sorted({s["group"] for s in scopes}),
        "env": {w: sorted(v, key=lambda e: sorted((k, str(x)) for k, x in e.items())) for w, v in sorted(env.items())},
        "params": dict(detector.params),
        "rlbackdoors": __version__,
    }


def _settings(env: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in sorted(env.items()))


def model_mismatch(detector: Detector, scope: dict) -> str | None:
    """Why the fitted ``detector`` was not fitted for a model of ``scope``; None when it was."""
    fitted = detector.fitted_on
    if fitted is None:
        return f"detector {detector.name!r} was fitted by an older rlbackdoors that did not record what it was fitted on; fit it again"
    world = scope["world"]
    if world not in fitted.get("worlds", []):
        return f"it is a {world} model; detector {detector.name!r} was fitted on {', '.join(fitted.get('worlds', [])) or 'no'} models only"
    if scope["group"] not in fitted.get("groups", []):
        groups = ", ".join(g for g in fitted.get("groups", []) if g.split("/")[0] == world)
        return f"it is a {scope['group']} model; detector {detector.name!r} was fitted on {groups} only"
    seen = fitted.get("env", {}).get(world, [])
    if scope["env"] not in seen:
        return f"it is a {world} model with {_settings(scope['env'])}; detector {detector.name!r} was fitted on {' | '.join(_settings(e) for e in seen)} only"
    return None


def params_mismatch(detector: Detector, given: dict) -> str | None:
    """Why ``given`` parameters (metaparameters, ``--param``) are not those ``detector`` was fitted
    with, in anything but fit-only parameters (:class:`rlbackdoors.detect.api.Param`); None if they are."""
    rules = type(detector).rules
    changed = [k for k, v in given.items() if k in detector.params and detector.params[k] != v and not (k in rules and rules[k].fit_only)]
    if not changed:
        return None
    said = ", ".join(f"{k}={given[k]!r} (fitted with {detector.params[k]!r})" for k in sorted(changed))
    return f"parameters other than those detector {detector.name!r} was fitted with, which change its features: {said}"


def with_params(detector: Detector, given: dict, allow: bool) -> tuple[Detector, str | None]:
    """``detector`` with ``given`` parameters (checked against its rules), and the mismatch flag;
    a DetectError when they differ from the fitted ones and ``allow`` is off."""
    unknown = sorted(set(given) - set(detector.params))
    if unknown:
        raise DetectError(f"detector {detector.name!r} has no parameter {unknown[0]!r} (its parameters: {', '.join(sorted(detector.params))})")
    type(detector)(**{**detector.params, **given})  # the rules' one-line errors, before anything else
    why = params_mismatch(detector, given)
    if why is None:
        return detector, None
    if not allow:
        raise DetectError(f"{why}; {ALLOW_HINT}")
    fresh = type(detector)(**{**detector.params, **given})
    state, arrays = detector.get_state()
    fresh.set_state(state, arrays)
    fresh.fitted, fresh.fitted_on = detector.fitted, detector.fitted_on
    return fresh, why


def check_contradiction(handle: ModelHandle, allow: bool, shown: str) -> str | None:
    """The flag of a model folder that contradicts itself (a handle opened with
    ``allow_contradiction``; None: it does not); a DetectError naming ``shown`` unless ``allow``.
    What an unfitted detector (``detect search``) checks; :func:`check_model` checks it too."""
    if handle.contradiction is not None and not allow:
        raise DetectError(f"{shown}: {handle.contradiction}; {ALLOW_HINT}")
    return handle.contradiction


def check_model(detector: Detector, handle: ModelHandle, allow: bool, name: str | None = None) -> str | None:
    """The mismatch flag of one model (None: in scope); a DetectError when it is out of scope,
    or its folder contradicts itself, and ``allow`` is off."""
    shown = f"model {name or handle.name!r}"
    why = "; ".join(w for w in (check_contradiction(handle, allow, shown), model_mismatch(detector, model_scope(detector, handle))) if w) or None
    if why is not None and not allow:
        raise DetectError(f"{shown}: {why}; {ALLOW_HINT}")
    return why


__all__ = ["check_contradiction", "check_model", "model_mismatch", "model_scope", "params_mismatch", "record", "with_params"]
