"""The TrojAI container interface: ``infer`` and ``configure`` with TrojAI's argument names.

Matched to ``entrypoint.py`` of usnistgov/trojai-example's reinforcement-learning round branches
(the Sep 2024 round's branch; the Jul 2023, Aug 2023 and Oct 2024 RL branches take the same
arguments; docs/detectors.md names them):

* ``infer --model_filepath --result_filepath --scratch_dirpath --examples_dirpath
  --round_training_dataset_dirpath --metaparameters_filepath --schema_filepath
  --learned_parameters_dirpath``: writes one probability into ``result_filepath``. The reduced
  config is read beside the model file (``reduced-config.json``, as TrojAI's example detector
  reads it); ``examples_dirpath`` is optional (the Sep 2024 branch made it so).
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
import shutil
from pathlib import Path

from rlbackdoors.detect.api import Detector, get_detector, load_detector
from rlbackdoors.detect.handle import REDUCED_CONFIG, DetectError, open_files
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


def schema_for(name: str) -> tuple[dict, dict]:
    """(metaparameters, schema) for detector ``name`` with its default parameters."""
    cls = get_detector(name)
    types = {bool: "boolean", int: "integer", float: "number", str: "string", dict: "object", list: "array"}
    properties: dict = {DETECTOR_KEY: {"description": "which detector (rlbackdoors detect list)", "enum": [name]}}
    for key, value in cls.defaults.items():
        kind = types.get(type(value))
        properties[key] = {"description": f"parameter {key} of detector {name}", **({"type": kind} if kind else {})}
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
    return {DETECTOR_KEY: name, **cls.defaults}, schema


def _with_metaparameters(detector: Detector, config: dict) -> Detector:
    name = config.get(DETECTOR_KEY, detector.name)
    if name != detector.name:
        raise DetectError(f"metaparameters name detector {name!r} but the learned parameters hold {detector.name!r}")
    params = {k: v for k, v in config.items() if k != DETECTOR_KEY}
    changed = {k: v for k, v in params.items() if detector.params.get(k) != v}
    if changed:
        fresh = type(detector)(**{**detector.params, **changed})
        state, arrays = detector.get_state()
        fresh.set_state(state, arrays)
        fresh.fitted = detector.fitted
        detector = fresh
    return detector


def infer(
    model_filepath: str,
    result_filepath: str,
    scratch_dirpath: str,
    examples_dirpath: str | None,
    round_training_dataset_dirpath: str | None,
    metaparameters_filepath: str,
    schema_filepath: str,
    learned_parameters_dirpath: str,
) -> tuple[float, str | None]:
    """Write the probability that ``model_filepath`` is poisoned; (probability, why it is 0.5 or None)."""
    config = validate(metaparameters_filepath, schema_filepath)
    detector = _with_metaparameters(load_detector(learned_parameters_dirpath), config)
    scratch = Path(scratch_dirpath)
    scratch.mkdir(parents=True, exist_ok=True)
    error = None
    try:
        handle = open_files(model_filepath, Path(model_filepath).parent / REDUCED_CONFIG, examples_dirpath, name="model", scratch=scratch)
    except Exception as err:  # the harness scores a model it cannot read 0.5
        probability, error = 0.5, f"{type(err).__name__}: {first_line(err)}"
    else:
        prediction = detector.predict([handle])[0]
        probability, error = prediction.probability, prediction.error
    atomic_write_text(result_filepath, f"{probability!r}\n")
    return probability, error


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
    if Path(metaparameters_filepath).resolve() != (out / METAPARAMETERS).resolve():
        shutil.copyfile(metaparameters_filepath, out / METAPARAMETERS)
    return info


__all__ = ["configure", "infer", "schema_for", "validate"]
