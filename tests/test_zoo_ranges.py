"""Settings drawn per model, as a TrojAI round draws them (issue 80): an attack's parameters and
evasive knobs from ``ranges`` (``[low, high]`` or ``{ one_of = [...] }``), the cell's own config
fields (e.g. the training length) for clean and poisoned models alike; recorded in config.json
and METADATA.csv, reproducible from the spec, refused in one line where a value could not train."""

from __future__ import annotations

import copy
import glob

import numpy as np
import pytest

from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.index import metadata_rows, scan, write_metadata
from rlbackdoors.zoo.plan import Zoo, plan
from rlbackdoors.zoo.spec import ZooError, load_spec, parse_draw, parse_spec

TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 64_000, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False}}
LENGTH = {"train.min_frames": {"one_of": [0, [20_000, 40_000], [20_000, 40_000]]}}


def spec() -> dict:
    return {
        "name": "round",
        "seed": 80,
        "overrides": copy.deepcopy(TINY),
        "cells": [
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": [{"name": "add", "template": "additive:{b}", "ranges": {"b": [66, 200]}}],
                "attacks": [
                    {
                        "attack": "trojdrl",
                        "ranges": {"budget": [0.005, 0.03], "force_action": {"one_of": [True, False]}, "target_action": {"one_of": [0, 1]}},
                    },
                    {
                        "attack": "trojdrl",
                        "name": "trojdrl-finetune",
                        "params": {"force_action": True},
                        "evasion": {"finetune": True},
                        "ranges": {"evasion.teacher": [0.05, 0.2]},
                    },
                ],
                "clean": 18,
                "poisoned": 18,
                "ranges": copy.deepcopy(LENGTH),
            }
        ],
    }


def test_a_draw_is_a_range_or_one_of_values_and_ranges():
    rng = np.random.default_rng(0)
    draw = parse_draw("x", {"one_of": [0, [10, 20], True, "a", [0.5, 0.75]]})
    values = [draw.sample(rng) for _ in range(400)]
    kinds = {
        "zero": [v for v in values if type(v) is int and v == 0],
        "int range": [v for v in values if type(v) is int and 10 <= v <= 20],
        "true": [v for v in values if v is True],
        "a": [v for v in values if v == "a"],
        "float range": [v for v in values if type(v) is float and 0.5 <= v <= 0.75],
    }
    assert sum(map(len, kinds.values())) == 400  # nothing outside the options
    assert all(40 <= len(v) <= 120 for v in kinds.values()), {k: len(v) for k, v in kinds.items()}  # 80 each expected
    assert draw.corners() == [0, 10, 20, True, "a", 0.5, 0.75]
    assert parse_draw("x", draw.to_data()) == draw
    plain = parse_draw("x", [1, 3])  # a bare range draws one number, as ranges always drew
    assert [plain.sample(np.random.default_rng(5)) for _ in range(1)] == [int(np.random.default_rng(5).integers(1, 4))]


def test_drawn_settings_are_per_model_in_range_recorded_and_reproducible(tmp_path):
    parsed = parse_spec(spec())
    zoo, written = plan(parsed, tmp_path / "a")
    assert written == 72
    configs = {g.key: [zoo.draw(g, a) for a in range(g.wanted)] for g in parsed.groups}
    tj = configs["lavaworld/fc/add/trojdrl/poisoned"]
    assert all(0.005 <= c.poison.attack_params["budget"] <= 0.03 for c in tj)
    assert {c.poison.attack_params["force_action"] for c in tj} == {True, False}
    assert {c.poison.attack_params["target_action"] for c in tj} == {0, 1}
    ft = configs["lavaworld/fc/add/trojdrl-finetune/poisoned"]
    assert all(c.poison.evasion["finetune"] and 0.05 <= c.poison.evasion["teacher"] <= 0.2 for c in ft)
    assert len({c.poison.evasion["teacher"] for c in ft}) == len(ft)
    # the training length: both labels draw it, a third stop at convergence (0), the rest train on
    for key, runs in configs.items():
        lengths = [c.train.min_frames for c in runs]
        assert all(x == 0 or 20_000 <= x <= 40_000 for x in lengths), key
        assert 1 <= lengths.count(0) <= 12, (key, lengths)  # Binomial(18, 1/3): outside [1, 12] p < 1e-3
    clean = configs["lavaworld/fc/add/trojdrl/clean"]
    assert all(not c.poison.poisoned and not c.poison.evasion for c in clean)
    rows = {r["model_name"]: r for r in metadata_rows(scan(zoo))}
    model = zoo.model(parsed.groups[1], 0)
    assert rows[model.name]["train.min_frames"] == tj[0].train.min_frames
    assert rows[model.name]["poison.attack_params.budget"] == tj[0].poison.attack_params["budget"]
    # the normal form reads back, and draws the same models
    again, _ = plan(parse_spec(parsed.to_dict()), tmp_path / "b")
    assert all(again.draw(g, a).to_json() == c.to_json() for g in parsed.groups for a, c in enumerate(configs[g.key]))


def test_a_cell_without_its_own_ranges_draws_as_before():
    raw = spec()
    del raw["cells"][0]["ranges"]
    without, with_ranges = parse_spec(raw), parse_spec(spec())
    assert "ranges" not in without.normalized["cells"][0]
    old, new = Zoo("/nonexistent", without, "auto"), Zoo("/nonexistent", with_ranges, "auto")
    for g in without.groups:  # the cell's ranges are drawn last: seed, trigger and attack draws unchanged
        a, b = old.draw(g, 0), new.draw(g, 0)
        assert a.train.min_frames == 0 and a.train.seed == b.train.seed and a.poison.trigger == b.poison.trigger
        assert a.poison.attack_params == b.poison.attack_params and a.poison.evasion == b.poison.evasion


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda c: c["ranges"].update({"poison.budget": [0.1, 0.2]}), r"cells\[0\].ranges.poison.budget is a poisoned model's setting"),
        (lambda c: c["ranges"].update({"train.seed": [1, 2]}), r"cells\[0\].ranges.train.seed is set by the zoo"),
        (lambda c: c["ranges"].update({"min_frames": [1, 2]}), r'cells\[0\].ranges.min_frames must name a config field as "section.field"'),
        (
            lambda c: c["ranges"].update({"train.min_frames": [0, 100_000]}),
            r"cells\[0\].ranges.train.min_frames=100000: .*train.min_frames must be in 0..train.max_frames",
        ),
        (lambda c: c["ranges"].update({"train.nope": [0, 1]}), r"cells\[0\].ranges.train.nope=0: train: unknown key 'nope'"),
        (lambda c: c["ranges"].update({"train.min_frames": {"one_of": []}}), r"cells\[0\].ranges.train.min_frames must be \[low, high\] or \{ one_of"),
        (lambda c: c["ranges"].update({"train.min_frames": {"one_of": [{"a": 1}]}}), r"one_of\[0\] must be a number, a boolean, a string or \[low, high\]"),
        (lambda c: c["attacks"][0]["ranges"].update({"force_action": {"one_of": [True, 3]}}), r"attacks\[0\].ranges.force_action=3 is not allowed"),
        (lambda c: c["attacks"][0]["ranges"].update({"evasion.teacher": [0.1, 0.2]}), r"attacks\[0\].ranges.evasion.teacher=0.1 needs .*finetune=true"),
        (
            lambda c: c["attacks"][1]["ranges"].update({"evasion.finetune": {"one_of": [True]}}),
            r"attacks\[1\].ranges.evasion.finetune: finetune is also fixed in evasion",
        ),
        (lambda c: c["attacks"][1]["ranges"].update({"evasion.nope": [0, 1]}), r"attacks\[1\].ranges.evasion.nope is not an evasive variant"),
    ],
)
def test_a_draw_that_could_not_train_is_refused_naming_the_field(change, message):
    raw = spec()
    change(raw["cells"][0])
    with pytest.raises(ConfigError, match=message):
        parse_spec(raw)


@pytest.mark.parametrize("path", sorted(glob.glob("examples/*.toml")))
def test_every_example_spec_reads_back_from_its_normal_form(path):
    parsed = load_spec(path)
    assert parse_spec(parsed.to_dict()).normalized == parsed.normalized


def test_models_drawn_with_other_program_flags_queue_apart(tmp_path):
    """A drawn force_action changes a compiled group's program (its flags are the program's key,
    the numbers data): zoo run deals a cell's forced and unforced models to jobs apart."""
    from rlbackdoors.zoo.index import scan
    from rlbackdoors.zoo.run import _affinity

    zoo, _ = plan(parse_spec(spec()), tmp_path / "z")
    states = [s for s in scan(zoo) if s.model.group.poisoned and s.model.group.cell.attack.name == "trojdrl"]
    order = sorted(states, key=lambda s: (_affinity(s.model, s.config), s.model.attempt))
    forced = [s.config["poison"]["attack_params"]["force_action"] for s in order]
    assert 0 < sum(forced) < len(forced) and forced == sorted(forced)  # one run of each
    assert len({_affinity(s.model) for s in states}) == 1  # the cell alone could not tell them apart


LONGER = {"train.min_frames": {"one_of": [0, [30_000, 60_000], [30_000, 60_000]]}}


def test_clean_models_draw_their_own_lengths_with_the_same_numbers_and_poisoned_ones_are_untouched():
    """``clean_ranges`` replaces a field of ``ranges`` for the clean models alone, drawn from the same
    random numbers: the option (0 or a range) each clean model picks is the one it picked before,
    so a model that stopped at convergence keeps its config; the poisoned models' draws are the same."""
    raw = spec()
    raw["cells"][0]["clean_ranges"] = copy.deepcopy(LONGER)
    before, after = Zoo("/nonexistent", parse_spec(spec()), "auto"), Zoo("/nonexistent", parse_spec(raw), "auto")
    assert parse_spec(raw).normalized["cells"][0]["clean_ranges"] == LONGER and "clean_ranges" not in parse_spec(spec()).normalized["cells"][0]
    same = changed = 0
    for g, h in zip(before.spec.groups, after.spec.groups, strict=True):
        for attempt in range(g.wanted):
            a, b = before.draw(g, attempt), after.draw(h, attempt)
            if g.poisoned:
                assert a.to_json() == b.to_json()
                continue
            assert (a.train.min_frames == 0) == (b.train.min_frames == 0) and a.train.seed == b.train.seed
            assert b.train.min_frames == 0 or 30_000 <= b.train.min_frames <= 60_000
            if a.train.min_frames == 0:
                assert a.to_json() == b.to_json()
                same += 1
            else:
                changed += 1
    assert same >= 1 and changed >= 1, (same, changed)
    bad = spec()
    bad["cells"][0]["clean_ranges"] = {"poison.budget": [0.1, 0.2]}
    with pytest.raises(ConfigError, match=r"cells\[0\].clean_ranges.poison.budget is a poisoned model's setting"):
        parse_spec(bad)


def test_a_replan_keeps_every_folder_the_new_spec_draws_the_same_and_moves_the_others_aside(tmp_path):
    import json

    from rlbackdoors.zoo.plan import replan
    from rlbackdoors.zoo.spec import ZooError

    zoo, _ = plan(parse_spec(spec()), tmp_path / "z")
    write_metadata(zoo)  # as a run leaves it: a row per folder
    for folder in zoo.models_dir.iterdir():  # stands for a trained model's files
        (folder / "metrics.json").write_text(json.dumps({"name": folder.name}))
    raw = spec()
    raw["cells"][0]["clean_ranges"] = copy.deepcopy(LONGER)
    new = parse_spec(raw)
    rezoo, moved, into = replan(new, tmp_path / "z")
    assert into == tmp_path / "z" / "replaced" / "0" and sorted(p.name for p in into.iterdir()) == sorted(moved)
    for g in new.groups:
        for attempt in range(g.wanted):
            folder = rezoo.folder(rezoo.model(g, attempt))
            assert json.loads((folder / "config.json").read_text()) == json.loads(rezoo.draw(g, attempt).to_json())
            kept = (folder / "metrics.json").is_file()
            assert kept == (folder.name not in moved), folder.name
            assert g.poisoned <= kept  # every poisoned folder stays
    assert 1 <= len(moved) <= 36 and all((into / n / "metrics.json").is_file() for n in moved)  # nothing is lost
    assert Zoo.open(tmp_path / "z").spec.normalized == new.normalized
    listed = {r["model_name"] for r in metadata_rows(scan(rezoo))}
    assert (tmp_path / "z" / "METADATA.csv").is_file() and listed == {p.name for p in rezoo.models_dir.iterdir()}
    assert replan(new, tmp_path / "z")[1] == []  # again: nothing to move
    other = spec()
    other["seed"] = 81
    with pytest.raises(ZooError, match="a replan keeps the master seed"):
        replan(parse_spec(other), tmp_path / "z")
    assert Zoo.open(tmp_path / "z").spec.normalized == new.normalized


def test_the_order_a_spec_writes_its_ranges_in_draws_nothing_otherwise(tmp_path):
    """TOML keeps a table's order as written, zoo.json sorts its keys: a run's top-ups (drawn from
    zoo.json) must draw what ``zoo plan`` (from the TOML) draws. Both range tables reversed here."""
    raw = spec()
    raw["cells"][0]["attacks"][0]["ranges"] = {"reward": [0.05, 0.2], "budget": [0.005, 0.03], "target_action": {"one_of": [0, 1]}}
    raw["cells"][0]["ranges"] = {"train.max_frames": [64_000, 96_000], **raw["cells"][0]["ranges"]}
    backwards = copy.deepcopy(raw)
    for table in (backwards["cells"][0]["attacks"][0], backwards["cells"][0]):
        table["ranges"] = dict(reversed(list(table["ranges"].items())))
    zoo, _ = plan(parse_spec(raw), tmp_path / "z")
    reread, other = Zoo.open(tmp_path / "z"), Zoo("/nonexistent", parse_spec(backwards), "auto")
    budgets = set()
    for g, h, k in zip(zoo.spec.groups, reread.spec.groups, other.spec.groups, strict=True):  # a draw reads its group's own cell
        assert h.cell.attack.name != "trojdrl" or [name for name, _ in h.cell.attack.ranges] == ["budget", "reward", "target_action"]
        for attempt in (0, g.wanted + 3):  # a first attempt and a top-up
            text = zoo.draw(g, attempt).to_json()
            assert reread.draw(h, attempt).to_json() == text == other.draw(k, attempt).to_json()
            budgets.add(zoo.draw(g, attempt).poison.attack_params.get("budget"))
    assert len(budgets) > 2  # the draws do differ from model to model


def test_a_folder_drawn_in_the_order_its_spec_was_written_still_counts_as_drawn(tmp_path):
    """Before 2026-12-08 ``zoo plan`` drew a first attempt's ranges in the TOML's order (a run's
    top-ups in zoo.json's sorted one): planning the same spec again accepts such a folder, and a
    replan that does not change its group keeps it (it moved 5 trained BadRL models aside once)."""
    import json

    from rlbackdoors.zoo.plan import replan

    raw = spec()
    raw["cells"][0]["attacks"][0]["ranges"] = {"reward": [0.05, 0.2], "budget": [0.005, 0.03], "target_action": {"one_of": [0, 1]}}
    zoo, _ = plan(parse_spec(raw), tmp_path / "z")
    trojdrl = next(g for g in zoo.spec.groups if g.poisoned and g.cell.attack.name == "trojdrl")
    legacy = zoo.folder(zoo.model(trojdrl, 0)) / "config.json"
    old = zoo.draw(trojdrl, 0, written=True).to_json()
    assert json.loads(old) != json.loads(legacy.read_text())  # the two orders do draw otherwise
    legacy.write_text(old)
    assert plan(parse_spec(raw), tmp_path / "z")[1] == 0 and legacy.read_text() == old
    changed = copy.deepcopy(raw)
    changed["cells"][0]["attacks"][1]["params"] = {"force_action": False}  # the fine-tuned cell changes
    rezoo, moved, _ = replan(parse_spec(changed), tmp_path / "z")
    finetuned = {rezoo.folder(rezoo.model(g, a)).name for g in rezoo.spec.groups if g.cell.attack.name == "trojdrl-finetune" for a in range(g.wanted)}
    assert set(moved) == finetuned and len(moved) == 36 and legacy.read_text() == old  # its clean models record the attack too
    data = json.loads(old)
    data["poison"]["attack_params"]["budget"] = 0.0123  # drawn in neither order
    legacy.write_text(json.dumps(data))
    with pytest.raises(ZooError, match="is not the config the zoo's spec draws for lavaworld/fc/add/trojdrl/poisoned attempt 0"):
        plan(parse_spec(changed), tmp_path / "z")


def test_a_replan_may_append_cells_but_not_insert_or_drop_one(tmp_path):
    """A family whose cell's attempts cannot reach its count gets a cell after the others: every
    folder keeps its id and config, the new cell's models take ids after the old id space, and a
    cell put before another or taken away is refused with nothing touched."""
    import json

    from rlbackdoors.zoo.plan import replan

    zoo, _ = plan(parse_spec(spec()), tmp_path / "z")
    before = {p.name: (p / "config.json").read_text() for p in zoo.models_dir.iterdir()}
    extra = {
        "world": "lavaworld",
        "archs": ["fc"],
        "triggers": [{"name": "add-u", "template": "additive:{b}", "ranges": {"b": [66, 200]}}],
        "attacks": [{"attack": "trojdrl", "params": {"force_action": False}, "ranges": {"budget": [0.005, 0.03]}}],
        "clean": 0,
        "poisoned": 3,
    }
    raw = spec()
    raw["cells"].append(copy.deepcopy(extra))
    with pytest.raises(ZooError, match="the new cells would renumber its models: give them block = 1"):
        replan(parse_spec(raw), tmp_path / "z")
    raw["cells"][-1]["block"] = extra["block"] = 1
    rezoo, moved, into = replan(parse_spec(raw), tmp_path / "z")
    assert moved == [] and into is None
    after = {p.name: p for p in rezoo.models_dir.iterdir()}
    assert all(after[name].joinpath("config.json").read_text() == text for name, text in before.items())
    new = [rezoo.folder(rezoo.model(rezoo.spec.groups[-1], a)) for a in range(3)]
    assert sorted(p.name for p in new) == sorted(set(after) - set(before)) and min(int(p.name[3:]) for p in new) >= zoo.spec.id_space
    assert {json.loads((p / "config.json").read_text())["poison"]["trigger"].startswith("additive:") for p in new} == {True}
    again, _ = plan(parse_spec(raw), tmp_path / "fresh")  # the spec alone gives the same ids
    assert {p.name: (p / "config.json").read_text() for p in again.models_dir.iterdir()} == {n: (p / "config.json").read_text() for n, p in after.items()}
    with pytest.raises(ConfigError, match=r"cells\[1\].block=0 comes after a cell of block 1"):
        parse_spec({**raw, "cells": [copy.deepcopy(extra), *spec()["cells"]]})
    for bad in ({**raw, "cells": raw["cells"][:1]}, {**raw, "cells": [{**raw["cells"][0], "max_attempts": 19}, raw["cells"][1]]}):
        with pytest.raises(ZooError, match="new cells may follow them"):
            replan(parse_spec(bad), tmp_path / "z")
    assert {p.name for p in rezoo.models_dir.iterdir()} == set(after)
