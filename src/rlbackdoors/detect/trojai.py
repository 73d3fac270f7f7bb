"""The TrojAI container interface: ``infer`` and ``configure`` with TrojAI's argument names.

Matched to ``entrypoint.py`` of usnistgov/trojai-example's reinforcement-learning round branches
(the Sep 2024 round's branch; the Jul 2023, Aug 2023 and Oct 2024 RL branches take the same
arguments; docs/detectors.md names them):

* ``infer --model_filepath --result_filepath --scratch_dirpath --examples_dirpath
  --round_training_dataset_dirpath --metaparameters_filepath --schema_filepath
  --learned_parameters_dirpath``: writes one probability into ``result_filepath``. The model's
  settings are read from the round files beside the model file, wherever its round put them
  (``reduced-config.json``; the Aug 2023 round's ``config.json``; ...); ``examples_dirpath`` is
  optional (the Sep 2024 branch made it so). A model or metaparameters the detector was not
  fitted for are refused (:mod:`rlbackdoors.detect.scope`).
  ``round_training_dataset_dirpath`` is accepted and not read: the learned parameters hold
  what was learned from the training set.
* ``configure --scratch_dirpath --configure_models_dirpath --metaparameters_filepath
  --schema_filepath --learned_parameters_dirpath [--automatic_configuration]``: fits the
  detector named by the metaparameters' ``detector`` key (its other keys are the detector's
  parameters) on the models and writes the learned parameters (plain data, no pickle) and a copy
  of the metaparameters into ``learned_parameters_dirpath``.

Metaparameters are validated against the schema first (``jsonschema`` when installed, else the
subset TrojAI's schemas use: type, minimum, maximum, enum, required, additionalProperties).
``detect metaparameters --detector NAME --out DIR`` writes a matching pair of files.
"""

from __future__ import annotations

import json
from pathlib import Path

from rlbackdoors.detect.api import Detector, get_detector, load_detector
from rlbackdoors.detect.handle import DetectError, open_files
from rlbackdoors.detect.scope import check_model, with_params
from rlbackdoors.io import atomic_write_text, first_line

METAPARAMETERS = "metaparameters.json"
SCHEMA = "metaparameters_schema.json"
DETECTOR_KEY = "detector"


def read_json(path: str | Path, what: str):
    path = Path(path)
    if not path.is_file():
        raise DetectError(f"{what} {str(path)!r} does not exist")
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise DetectError(f"{what} {str(path)!r} is not JSON ({first_line(err)})") from None


def validate(metaparameters_filepath: str | Path, schema_filepath: str | Path) -> dict:
    """The metaparameters, checked against the schema (one error line naming the field)."""
    config = read_json(metaparameters_filepath, "metaparameters file")
    schema = read_json(schema_filepath, "schema file")
    if not isinstance(config, dict) or not isinstance(schema, dict):
        raise DetectError("metaparameters and schema must each hold a JSON object")
    try:
        import jsonschema
    except ImportError:
        _validate_subset(config, schema)
    else:
        try:
            jsonschema.validate(instance=config, schema=schema)
        except jsonschema.ValidationError as err:
            where = ".".join(str(p) for p in err.absolute_path) or "metaparameters"
            raise DetectError(f"metaparameters {str(metaparameters_filepath)!r}: {where}: {err.message}") from None
        except jsonschema.SchemaError as err:
            raise DetectError(f"schema {str(schema_filepath)!r} is not a valid JSON schema ({err.message})") from None
    return config


_TYPES: dict[str, type | tuple[type, ...]] = {"integer": int, "number": (int, float), "string": str, "boolean": bool, "object": dict, "array": list}


def _validate_subset(config: dict, schema: dict) -> None:
    properties = schema.get("properties", {})
    for key in schema.get("required", []):
        if key not in config:
            raise DetectError(f"metaparameters: {key} is required by the schema")
    for key, value in config.items():
        rule = properties.get(key)
        if rule is None:
            if schema.get("additionalProperties", True) is False:
                raise DetectError(f"metaparameters: {key} is not allowed by the schema")
            continue
        kind = rule.get("type")
        if kind in _TYPES and (not isinstance(value, _TYPES[kind]) or (kind in ("integer", "number") and isinstance(value, bool))):
            raise DetectError(f"metaparameters: {key}={value!r} must be of type {kind}")
        if "enum" in rule and value not in rule["enum"]:
            raise DetectError(f"metaparameters: {key}={value!r} must be one of {rule['enum']}")
        if "minimum" in rule and value < rule["minimum"]:
            raise DetectError(f"metaparameters: {key}={value!r} is below the minimum {rule['minimum']}")
        if "maximum" in rule and value > rule["maximum"]:
            raise DetectError(f"metaparameters: {key}={value!r} is above the maximum {rule['maximum']}")


def _property(name: str, key: str, default, rule) -> dict:
    """The schema of one parameter, from its rule (:class:`rlbackdoors.detect.api.Param`)."""
    types = {bool: "boolean", int: "integer", float: "number", str: "string", dict: "object", list: "array"}
    prop: dict = {"description": (rule.help if rule and rule.help else f"parameter {key} of detector {name}")}
    kind = types.get(type(default))
    if kind:
        prop["type"] = kind
    if rule is not None:
        if rule.minimum is not None:
            prop["minimum"] = rule.minimum
        if rule.maximum is not None:
            prop["maximum"] = rule.maximum
        if rule.choices:
            prop["enum"] = list(rule.choices)
    return prop


def schema_for(name: str, params: dict | None = None) -> tuple[dict, dict]:
    """(metaparameters, schema) for detector ``name``: its default parameters (``params`` on top,
    validated), and a JSON schema whose types, ranges and choices are its rules'."""
    cls = get_detector(name)
    values = dict(cls(**(params or {})).params)  # the rules' one-line errors for a bad value
    properties: dict = {DETECTOR_KEY: {"description": "which detector (rlbackdoors detect list)", "enum": [name]}}
    for key, default in cls.defaults.items():
        properties[key] = _property(name, key, default, cls.rules.get(key))
    schema = {
        "$schema": "http://json-schema.org/draft-07/schema#",
        "title": f"rlbackdoors detector {name}",
        "technique": name,
        "technique_description": cls.description,
        "technique_type": ["Weight Analysis"] if name == "weights" else ["Other"],
        "required": [DETECTOR_KEY],
        "additionalProperties": False,
        "type": "object",
        "properties": properties,
    }
    return {DETECTOR_KEY: name, **values}, schema


def write_metaparameters(detector: Detector, folder: str | Path) -> tuple[Path, Path]:
    """``metaparameters.json`` (the parameters ``detector`` holds) and its schema into ``folder``:
    what ``infer`` must be given for a detector fitted with them."""
    config, schema = schema_for(detector.name, dict(detector.params))
    folder = Path(folder)
    return (
        atomic_write_text(folder / METAPARAMETERS, json.dumps(config, indent=2) + "\n"),
        atomic_write_text(folder / SCHEMA, json.dumps(schema, indent=2) + "\n"),
    )


def infer(
    model_filepath: str,
    result_filepath: str,
    scratch_dirpath: str,
    examples_dirpath: str | None,
    round_training_dataset_dirpath: str | None,
    metaparameters_filepath: str,
    schema_filepath: str,
    learned_parameters_dirpath: str,
    allow_mismatch: bool = False,
) -> tuple[float, str | None, str | None]:
    """Write the probability that ``model_filepath`` is poisoned; (probability, why it is 0.5 or
    None, the mismatch flag or None).

    The model's settings are read from the round files beside it (``reduced-config.json``,
    ``config.json``, ``model.info.json``, ...: :mod:`rlbackdoors.trojai_round`). Metaparameters
    other than those fitted with, or a model outside what the detector was fitted on (world,
    architecture, env settings: :mod:`rlbackdoors.detect.scope`), are refused with one line and
    no result file, unless ``allow_mismatch``: then the result is written and the flag returned
    (and kept in ``scratch_dirpath/result.json``). A model folder that contradicts itself (its
    settings name another architecture than its weights fit) is a model the harness cannot read:
    0.5 and the reason, as TrojAI scores an unreadable model; with ``allow_mismatch`` it is scored
    from its weights and flagged."""
    config = validate(metaparameters_filepath, schema_filepath)
    detector = load_detector(learned_parameters_dirpath)
    name = config.get(DETECTOR_KEY, detector.name)
    if name != detector.name:
        raise DetectError(f"metaparameters name detector {name!r} but the learned parameters hold {detector.name!r}")
    detector, flags = with_params(detector, {k: v for k, v in config.items() if k != DETECTOR_KEY}, allow_mismatch)
    scratch = Path(scratch_dirpath)
    scratch.mkdir(parents=True, exist_ok=True)
    error = None
    try:
        handle = open_files(model_filepath, Path(model_filepath).parent, examples_dirpath, name="model", scratch=scratch, allow_contradiction=allow_mismatch)
    except Exception as err:  # the harness scores a model it cannot read 0.5 (a folder that contradicts itself too)
        probability, error = 0.5, f"{type(err).__name__}: {first_line(err)}"
    else:
        why = detector.unsupported(handle)
        if why is not None and not allow_mismatch:
            raise DetectError(f"{model_filepath}: {why}")
        mismatch = check_model(detector, handle, allow_mismatch, str(model_filepath))
        flags = "; ".join(f for f in (flags, why, mismatch) if f) or None
        prediction = detector.predict([handle])[0]
        probability, error = prediction.probability, prediction.error
    atomic_write_text(result_filepath, f"{probability!r}\n")
    note = {"model": str(model_filepath), "probability": probability, "error": error, "mismatch": flags}
    atomic_write_text(scratch / "result.json", json.dumps(note, indent=2) + "\n")
    return probability, error, flags


def configure(
    scratch_dirpath: str,
    configure_models_dirpath: str,
    metaparameters_filepath: str,
    schema_filepath: str,
    learned_parameters_dirpath: str,
    automatic_configuration: bool = False,
) -> dict:
    """Fit the detector the metaparameters name on the models; write the learned parameters."""
    from rlbackdoors.detect.score import fit_into

    config = validate(metaparameters_filepath, schema_filepath)
    name = config.get(DETECTOR_KEY)
    if not isinstance(name, str):
        raise DetectError(f"metaparameters {str(metaparameters_filepath)!r} must name the detector ({DETECTOR_KEY!r}: one of rlbackdoors detect list)")
    Path(scratch_dirpath).mkdir(parents=True, exist_ok=True)
    detector = get_detector(name)(**{k: v for k, v in config.items() if k != DETECTOR_KEY})
    out = Path(learned_parameters_dirpath)
    # C is chosen by cross-validation either way; a killed configure resumes
    info = fit_into(detector, configure_models_dirpath, out, extra={"automatic_configuration": bool(automatic_configuration)})
    return info  # fit_into wrote the metaparameters fitted with, and their schema, beside it


__all__ = ["configure", "infer", "schema_for", "validate", "write_metaparameters"]
