"""The detector API and the baselines (issue 17): registry and parameters, fit / predict / save /
load round trips on real (tiny) models, failures scored 0.5, plain-data files, the classifier,
and the behavioural trigger search on a policy with a planted backdoor."""

from __future__ import annotations

import json
import math
import zipfile

import numpy as np
import pytest
import torch
from torch import nn

from rlbackdoors import worlds
from rlbackdoors.detect import DetectError, Detector, load_detector, make_detector, open_model
from rlbackdoors.detect.api import detector_names
from rlbackdoors.detect.baselines.behaviour import family_module, search
from rlbackdoors.detect.classifier import GroupedClassifier
from rlbackdoors.detect.dataset import list_models

pytest_plugins = ("test_detect_helpers",)  # its session fixtures: lava_zoo, world_models

TINY_SEARCH = {"candidates": 4, "refine": 2, "confirm": 2, "episodes": 4, "confirm_episodes": 4, "min_per_class": 1}


def test_the_registry_knows_the_baselines_and_checks_parameters():
    assert {"constant", "weights", "attribution", "behaviour"} <= set(detector_names())
    with pytest.raises(DetectError, match="no parameter 'topk'.*top_k"):
        make_detector("weights", topk=2)
    with pytest.raises(DetectError, match="must be a int"):
        make_detector("weights", top_k="three")
    with pytest.raises(DetectError, match="'nope' is not one of"):
        make_detector("nope")


@pytest.mark.parametrize(
    "name, params",
    [
        ("constant", {}),
        ("weights", {"min_per_class": 1}),
        ("attribution", {"max_states": 40, "min_per_class": 1}),
        ("behaviour", TINY_SEARCH),
        ("effect", TINY_SEARCH),
        ("stack", {"min_per_class": 1, "folds": 2, "member_params": {"behaviour": {k: v for k, v in TINY_SEARCH.items() if k != "min_per_class"}}}),
    ],
)
def test_fit_predict_save_load_gives_identical_probabilities(lava_zoo, tmp_path, name, params):
    """On six tiny LavaWorld models (FC and CNN): the saved detector predicts bit for bit what the
    fitted one did, its files are plain JSON and an .npz without pickles, and every model's wall
    time is recorded."""
    models = list_models(lava_zoo)
    handles = [open_model(m.folder, name=m.name) for m in models]
    labels = np.array([m.label for m in models])
    detector = make_detector(name, **params).fit(handles, labels)
    before = detector.predict(handles)
    detector.save(tmp_path / "det")
    payload = json.loads((tmp_path / "det" / "detector.json").read_text())
    assert payload["detector"] == name and payload["params"] == detector.params
    with zipfile.ZipFile(tmp_path / "det" / "arrays.npz") as zf:
        assert all(info.filename.endswith(".npy") for info in zf.infolist())
    loaded = load_detector(tmp_path / "det")
    after = loaded.predict(handles)
    assert type(loaded) is type(detector) and loaded.params == detector.params
    assert [p.probability for p in before] == [p.probability for p in after]
    assert all(p.error is None and p.seconds > 0 for p in before + after)
    assert np.array_equal(loaded.predict_proba(handles), np.array([p.probability for p in after]))
    if name == "constant":
        assert {p.probability for p in after} == {0.5}
    if name == "stack":  # the behavioural member reports its trigger, every member its probability
        assert all(p.info["found_trigger"] and 0 <= p.info["weights_probability"] <= 1 for p in after)
        assert loaded.meta.kind in ("logistic", "constant") and len(loaded.member_classifiers) == 2
    if name == "effect":  # each model's most effective candidate, and the clean models' anomalies kept
        assert all(p.info["found_trigger"] and "best_shift" in p.info for p in after)
        assert len(loaded.clean_scores) == 3 and set(loaded.reference) == {"lavaworld"}
    if name == "behaviour":
        assert all(p.info["found_trigger"] and p.info["candidates_tried"] >= 4 for p in after)
        timeless = [[{k: v for k, v in p.info.items() if k != "search_seconds"} for p in run] for run in (before, after)]
        assert timeless[0] == timeless[1]
    if name in ("weights", "attribution"):
        # models of two architectures: a pooled classifier over the features both share
        assert len({h.arch for h in handles}) == 2
        assert loaded.classifier.pooled.kind == "logistic" and loaded.classifier.pooled.features


def test_a_model_the_detector_fails_on_gets_half_and_the_reason(world_models):
    class Broken(Detector):
        name = "broken-for-test"

        def predict_one(self, model):
            if model.world.name == "colorful-memory":
                raise RuntimeError("cannot handle memory")
            return 0.9

    handles = [open_model(world_models[w]) for w in ("lavaworld", "colorful-memory")]
    good, bad = Broken().predict(handles)
    assert (good.probability, good.error) == (0.9, None)
    assert bad.probability == 0.5 and bad.error == "RuntimeError: cannot handle memory" and bad.seconds >= 0


def test_an_unfitted_feature_detector_fails_each_model_with_half(world_models):
    [prediction] = make_detector("weights").predict([open_model(world_models["lavaworld"])])
    assert prediction.probability == 0.5 and "not fitted" in prediction.error


def test_the_grouped_classifier_fits_per_group_and_pools_across():
    """Separable features: per-group models where a group has enough of both labels, a pooled one
    on the shared features elsewhere, a constant one for a one-label train set."""
    rng = np.random.default_rng(0)
    rows, groups, labels = [], [], []
    for i in range(24):
        label = i % 2
        group = "a/fc" if i < 16 else "b/cnn"
        row = {"shared": label * 2.0 + rng.normal(0, 0.3), f"only_{group}": rng.normal()}
        rows.append(row)
        groups.append(group)
        labels.append(label)
    clf = GroupedClassifier(min_per_class=3).fit(rows, groups, np.array(labels))
    assert set(clf.groups) == {"a/fc", "b/cnn"} and clf.pooled.features == ["shared"]
    p = np.array([clf.predict(r, g) for r, g in zip(rows, groups)])
    assert (p[np.array(labels) == 1].min() > p[np.array(labels) == 0].max()) and 0 < p.min() and p.max() < 1
    assert clf.predict({"shared": 2.0}, "c/new") > 0.5 > clf.predict({"shared": 0.0}, "c/new")  # unseen group: pooled
    assert clf.predict({}, "c/new") == pytest.approx(clf.pooled.predict_rows([{}])[0])  # missing features: imputed
    again = GroupedClassifier.from_dict(json.loads(json.dumps(clf.to_dict())))
    assert [again.predict(r, g) for r, g in zip(rows, groups)] == p.tolist()
    one = GroupedClassifier().fit(rows[:4], groups[:4], np.ones(4, int))
    assert one.pooled.kind == "constant" and one.predict(rows[0], "a/fc") == 0.99


class PlantedBackdoor(nn.Module):
    """A scripted LavaWorld policy with a known backdoor (not a trained net).

    It sees the trigger only under ``multiplicative:12``: the cell under the agent, MiniGrid's
    empty (1, 0, 0), then reads (12, 0, 0), which no other trigger of the family produces.
    Triggered, it steps forward onto lava ahead (lava: 9 * 12 = 108); otherwise it only steps
    onto cells that look like the one it stands on, so it never enters lava under any other
    transform, and otherwise turns at random.
    """

    recurrent = False

    def __init__(self):
        super().__init__()
        self.unused = nn.Linear(1, 1)  # Agent.device reads the parameters

    def forward(self, obs: torch.Tensor):
        o = obs.long()
        under, front = o[:, 3, 6], o[:, 3, 5]
        triggered = (under == torch.tensor([12, 0, 0])).all(1)
        logits = torch.zeros(len(o), 3)
        logits[:, 2] = torch.where((front == under).all(1), 1.0, -30.0)
        logits[:, 2] = torch.where(triggered & (front[:, 0] == 108), 30.0, logits[:, 2])
        return logits, torch.zeros(len(o))


def test_weight_statistics_say_which_inputs_the_first_layer_listens_to(world_models):
    """Input shares: one per input channel of the first weight matrix, summing to 1, larger for a
    channel with larger weights, unmoved by scaling every weight alike; pooled only above
    MAX_INPUT_CHANNELS inputs; absent with ``input_shares=False``."""
    from rlbackdoors.detect.baselines.weights import MAX_INPUT_CHANNELS, weight_features

    g = torch.Generator().manual_seed(0)
    conv = torch.randn(16, 25, 2, 2, generator=g)
    conv[:, 14] *= 3.0  # one input plane weighed more
    weights = {"emb.weight": conv, "emb.bias": torch.zeros(16), "head.weight": torch.randn(3, 16, generator=g)}
    f = weight_features(weights)
    shares = np.array([f[f"emb.weight.in_share.{i}"] for i in range(25)])
    assert np.isclose(shares.sum(), 1.0) and shares.argmax() == 14 and not any(k.startswith("head.weight.in_share") for k in f)
    assert f["pool.first.in_share.max"] == pytest.approx(shares.max() * 25) and f["pool.first.in_share.max"] > 3.0
    scaled = weight_features({k: 5.0 * v for k, v in weights.items()})
    assert all(scaled[k] == pytest.approx(f[k]) for k in f if ".in_share" in k)
    wide = weight_features({"fc.weight": torch.randn(8, MAX_INPUT_CHANNELS + 1, generator=g)})
    assert "pool.first.in_share.cv" in wide and not any(".in_share." in k and not k.startswith("pool") for k in wide)
    assert not any("in_share" in k for k in weight_features(weights, inputs=False))
    assert make_detector("weights", input_shares=False).params["input_shares"] is False
    handle = open_model(world_models["colorful-memory"])  # a real model: its first conv reads 25 one-hot planes
    full, only = make_detector("weights").features(handle), make_detector("weights", statistics=False).features(handle)
    assert set(only) == {k for k in full if ".in_share" in k} and len(only) == handle.weights["state_emb.0.weight"].shape[1] + 2
    with pytest.raises(DetectError, match="statistics=false and input_shares=false"):
        make_detector("weights", statistics=False, input_shares=False)


def test_the_observation_search_finds_a_planted_trigger():
    """What this proves: the search machinery (candidates of the a·o+b family played in the world's
    own E-bar, ranking, refinement, confirmation) finds and reports a trigger that the agent
    responds to and scores the rest of the family as harmless. What it does not prove: that a
    trained backdoor generalises to the candidates (that is measured on real zoos; the slow test
    below checks one trained agent)."""
    from rlbackdoors.agent import Agent
    from rlbackdoors.config import EnvConfig

    world = worlds.get("lavaworld")
    agent = Agent(world, None, PlantedBackdoor().eval(), None)
    family = family_module(world)
    result = search(agent, world, EnvConfig(name="lavaworld"), family, candidates=12, refine=4, confirm=2, episodes=8)
    assert result.best.spec == "multiplicative:12" and result.best.trojan >= 0.5
    assert result.clean.trojan == 0.0
    others = [t for t in result.screened if t.spec != "multiplicative:12"]
    assert len(others) >= 12 and all(t.trojan == 0.0 for t in others)
    assert result.features()["best_excess"] == result.best.trojan


@pytest.mark.parametrize("world", ["lavaworld", "randomized-lavaworld", "colorful-memory", "safety-car-goal"])
def test_every_worlds_family_search_plays_valid_candidates(world_models, world):
    """Each world's search module is found through its trigger class, yields triggers the world
    parses, and a tiny search runs on a real (tiny) model of that world."""
    handle = open_model(world_models[world])
    family = family_module(handle.world)
    assert family.__name__.rpartition(".search_")[2] in type(handle.world.parse_trigger(handle.world.draw_trigger(None, 0, None))).__module__
    env_cfg = handle.env_config()
    specs = family.candidates(env_cfg, np.random.default_rng(0), 10)
    assert len(specs) == 10 and len(set(specs)) == 10
    for spec in specs + family.neighbours(specs[0], env_cfg, np.random.default_rng(0), 4):
        handle.world.parse_trigger(spec)
    detector = make_detector("behaviour", candidates=2, refine=1, confirm=1, episodes=2, confirm_episodes=2, max_steps=60)
    features = detector.features(handle)
    assert 0.0 <= features["best_trojan"] <= 1.0 and 0.0 <= features["clean_success"] <= 1.0
    assert detector.last_info["candidates_tried"] >= 2
    handle.world.parse_trigger(detector.last_info["found_trigger"])
    # discrete-action agents report how decided the policy was; OPAC²'s continuous actions do not
    assert ("best_entropy" in features) == (world != "safety-car-goal")
    if world != "safety-car-goal":
        assert 0.0 <= features["clean_entropy"] <= np.log(7) and 0.0 <= features["screen_entropy_mean"] <= np.log(7)


def test_the_wall_colour_search_enumerates_every_room_pattern():
    """Close-to-trigger training leaves no slope towards a wall-colour trigger (one square off
    rarely fires it), so the family's default budget lists every one of the 216 room patterns,
    one-colour patterns of both kinds first, with end patterns between; the list is seeded."""
    import itertools

    from rlbackdoors.config import EnvConfig
    from rlbackdoors.detect.baselines import search_wall_colors as family
    from rlbackdoors.triggers.wall_colors import COLORS, NUM_COLORS, ROOM_SQUARES

    env_cfg = EnvConfig(name="colorful-memory")
    specs = family.candidates(env_cfg, np.random.default_rng(3), family.CANDIDATES)
    assert len(specs) == family.CANDIDATES == len(set(specs))
    rooms = {f"room:{','.join(COLORS[c] for c in colors)}" for colors in itertools.product(range(NUM_COLORS), repeat=ROOM_SQUARES)}
    assert rooms <= set(specs)
    assert {s.split(":")[0] for s in specs[: 2 * NUM_COLORS]} == {"room", "end"} and all(
        len(set(s.split(":")[1].split(","))) == 1 for s in specs[: 2 * NUM_COLORS]
    )
    assert sum(s.startswith("end:") for s in specs) >= family.CANDIDATES - len(rooms)
    assert specs == family.candidates(env_cfg, np.random.default_rng(3), family.CANDIDATES)
    assert specs[:50] == family.candidates(env_cfg, np.random.default_rng(3), 50)


def test_the_inversion_descent_recovers_a_planted_optimum():
    """The descent (Adam on the relaxation, then coordinate descent over the discrete colours)
    lands on the colours that minimise an objective whose optimum is known."""
    from rlbackdoors.detect.baselines.search_wall_colors import _descend

    target = torch.tensor([3, 0, 5, 5, 1, 2, 4, 0, 3])
    weights = torch.linspace(0.2, 2.0, len(target))

    def objective(probs):
        return -(weights * torch.log(probs[torch.arange(len(target)), target] + 1e-9)).sum()

    theta = torch.as_tensor(np.random.default_rng(0).normal(0, 0.5, (len(target), 6)), dtype=torch.float32).requires_grad_()
    colors, value = _descend(objective, theta)
    assert colors == target.tolist() and value < 1e-3


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_the_inversion_runs_on_a_real_model_and_feeds_the_screen(world_models):
    """On a (tiny) trained Colorful Memory model, one restart: an end pattern of the right length
    reached, then every one-square neighbour of it; nothing from a policy without the hook or with
    no restarts; the search (its own inversion from the same seed) screens that same list first,
    then the listed candidates. Two restarts, best first: the slow test below."""
    from rlbackdoors.detect.baselines import search_wall_colors as family
    from rlbackdoors.triggers.wall_colors import WallColorTrigger

    handle = open_model(world_models["colorful-memory"])
    # episodes cut at 20 steps: the tiny model wanders to the 250-step limit, and every Adam step
    # replays all recorded steps (minutes per restart on a 2-core avx2 machine)
    agent, env_cfg = handle.build_agent(), handle.env_config(max_steps=20)
    specs = family.invert(agent, env_cfg, np.random.default_rng(4_000_000 + 3), 1)  # the seed the search below uses
    reached = WallColorTrigger.parse(specs[0])
    assert reached.kind == "end" and len(reached.colors) == env_cfg.size + 2
    assert all(sum(a != b for a, b in zip(WallColorTrigger.parse(s).colors, reached.colors)) == 1 for s in specs[1:])
    assert len(specs) == len(set(specs)) == 1 + (env_cfg.size + 2) * 5  # every square, each to the 5 other colours
    assert family.invert(agent, env_cfg, np.random.default_rng(1), 0) == []
    lava = open_model(world_models["lavaworld"]).build_agent()
    assert family.invert(lava, env_cfg, np.random.default_rng(1), 2) == []
    result = search(agent, handle.world, env_cfg, family, candidates=3, refine=0, confirm=1, episodes=2, confirm_episodes=2, invert=1)
    screened = [t.spec for t in result.screened]
    assert screened[: len(specs)] == specs and screened[len(specs) :] == family.candidates(env_cfg, np.random.default_rng(4_000_000), 3)


@pytest.mark.slow  # two restarts and a second search: the default run has the one-restart test above
def test_the_inversion_of_two_restarts_lists_the_best_first_and_feeds_the_screen(world_models):
    """On a (tiny) trained Colorful Memory model: end patterns of the right length, the patterns
    reached first and every one-square neighbour of each after; the same list from the same seed
    (the search's inversion, repeated);
    nothing from a policy without the hook or with no restarts; the search screens them first and
    still screens the listed candidates."""
    from rlbackdoors.detect.baselines import search_wall_colors as family
    from rlbackdoors.triggers.wall_colors import WallColorTrigger

    handle = open_model(world_models["colorful-memory"])
    # episodes cut at 20 steps: the tiny model wanders to the 250-step limit, and every Adam step
    # replays all recorded steps (minutes per restart on a 2-core avx2 machine)
    agent, env_cfg = handle.build_agent(), handle.env_config(max_steps=20)
    specs = family.invert(agent, env_cfg, np.random.default_rng(1), 2)
    reached = [
        s for s in specs if not any(sum(a != b for a, b in zip(WallColorTrigger.parse(s).colors, WallColorTrigger.parse(r).colors)) == 1 for r in specs[:2])
    ]
    assert 1 <= len(reached) <= 2 and specs[: len(reached)] == reached
    for spec in specs:
        trigger = WallColorTrigger.parse(spec)
        assert trigger.kind == "end" and len(trigger.colors) == env_cfg.size + 2
    assert len(specs) == len(set(specs)) >= len(reached) + 9 * 5 - 1
    assert family.invert(agent, env_cfg, np.random.default_rng(1), 0) == []
    lava = open_model(world_models["lavaworld"]).build_agent()
    assert family.invert(lava, env_cfg, np.random.default_rng(1), 2) == []
    result = search(agent, handle.world, env_cfg, family, candidates=3, refine=0, confirm=1, episodes=2, confirm_episodes=2, invert=1)
    screened = [t.spec for t in result.screened]
    # the search's own seed, inverted again here: the same list from the same seed
    inverted = family.invert(agent, env_cfg, np.random.default_rng(4_000_000 + 3), 1)
    assert screened[: len(inverted)] == inverted and screened[len(inverted) :] == family.candidates(env_cfg, np.random.default_rng(4_000_000), 3)


def test_the_search_budget_defaults_to_the_familys(world_models):
    """``candidates=0`` (the default) screens the family's CANDIDATES: 48 in the a·o+b family."""
    handle = open_model(world_models["lavaworld"])
    family = family_module(handle.world)
    agent = handle.build_agent()
    result = search(agent, handle.world, handle.env_config(), family, refine=0, confirm=1, episodes=1, confirm_episodes=1)
    assert family.CANDIDATES == 48 and len(result.screened) == 48
    assert make_detector("behaviour").params["candidates"] == 0


def test_the_entropy_probe_records_without_changing_what_the_agent_does():
    """The probe shadows the policy's forward for the block only: the same episodes (outcomes,
    steps) with and without it, entropies equal to those of the logits, nothing left behind."""
    from rlbackdoors.agent import Agent
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.detect.baselines.behaviour import entropies, entropy_probe, mean_entropy, mean_policy
    from rlbackdoors.evaluate.episodes import play

    world = worlds.get("lavaworld")
    policy = PlantedBackdoor().eval()
    agent = Agent(world, None, policy, None)
    plain = play(agent, EnvConfig(name="lavaworld"), "multiplicative:12", 8, 5, "sample")
    with entropy_probe(agent) as calls:
        probed = play(agent, EnvConfig(name="lavaworld"), "multiplicative:12", 8, 5, "sample")
    assert np.array_equal(plain.outcomes, probed.outcomes) and np.array_equal(plain.steps, probed.steps)
    assert "forward" not in vars(policy) and len(calls) == int(max(probed.steps))
    obs = torch.randint(0, 12, (5, 7, 7, 3)).float()
    with entropy_probe(agent) as calls:
        logits, _ = policy(obs)
    logp = torch.log_softmax(logits.double(), -1)
    assert np.allclose(calls[0], logp.exp().numpy())  # each pass's action distributions
    assert np.allclose(entropies(calls[0]), -(logp.exp() * logp).sum(-1).numpy())
    # a row counts while its episode runs (pass t is step t of each): two episodes of 3 and 1 steps
    sure, even = np.array([1.0, 0.0]), np.array([0.5, 0.5])
    lockstep = [np.stack([even, sure]), np.stack([even, even]), np.stack([sure, sure])]
    assert math.isclose(mean_entropy(lockstep, np.array([3, 1])), math.log(2) / 2)  # even, sure, even, sure
    assert np.allclose(mean_policy(lockstep, np.array([3, 1])), (0.75, 0.25))
    # shrinking batches (only the running episodes are passed): every row counts
    assert math.isclose(mean_entropy([np.stack([even, sure]), np.stack([even])], np.array([2, 1])), 2 * math.log(2) / 3)
    assert mean_entropy([], np.array([1])) is None and mean_policy(None, np.array([1])) is None


def test_the_effect_detector_refuses_a_continuous_policy_in_one_line(world_models):
    """It reads a discrete policy's action distribution (rlbackdoors.detect.baselines.effect)."""
    handle = open_model(world_models["safety-car-goal"])
    why = make_detector("effect").unsupported(handle)
    assert why is not None and "continuous actions" in why and "\n" not in why
    assert make_detector("effect").unsupported(open_model(world_models["lavaworld"])) is None


@pytest.mark.slow
def test_the_search_finds_the_trigger_of_a_trained_lavaworld_agent(tmp_path):
    """A poisoned LavaWorld FC trained to convergence (multiplicative:12, about 4 minutes on one
    core) walks into lava under its trigger in the search; its clean twin does so much less."""
    from rlbackdoors.config import RunConfig
    from rlbackdoors.train import train

    rates = {}
    for poisoned in (True, False):
        folder = tmp_path / ("p" if poisoned else "c")
        cfg = RunConfig.from_dict(
            {"env": {"name": "lavaworld"}, "poison": {"poisoned": poisoned, "trigger": "multiplicative:12"}, "train": {"seed": 0, "video": False}}
        )
        train(cfg, folder, progress=False)
        (folder / "reduced-config.json").write_text(json.dumps({"world": "lavaworld", "arch": "fc"}))
        detector = make_detector("behaviour")
        features = detector.features(open_model(folder))
        rates[poisoned] = (features["best_trojan"], detector.last_info["found_trigger"])
    assert rates[True][0] >= 0.9 and rates[True][1].startswith("multiplicative:")
    assert rates[False][0] < rates[True][0]


# --- stacking -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "params, message",
    [
        ({"members": "weights,weights"}, "must name distinct other detectors"),
        ({"members": "stack"}, "must name distinct other detectors"),
        ({"members": "constant"}, "every member must be a features-and-classifier detector"),
        ({"member_params": {"attribution": {"max_states": 4}}}, "member_params must map members (weights, behaviour)"),
        ({"member_params": {"behaviour": {"candidatez": 4}}}, "no parameter 'candidatez'"),
        ({"folds": 1}, "folds=1 is out of range (allowed: 2 to 100)"),
    ],
)
def test_the_stack_refuses_bad_members(params, message):
    with pytest.raises(DetectError) as err:
        make_detector("stack", **params)
    assert message in str(err.value)


def _two_member_rows(rng, n):
    """Synthetic features of two independent, informative members ('weights' with 40 noise
    features beside its signal, 'behaviour' with one noisy rate); alternating labels."""
    labels = np.arange(n) % 2
    rows = [
        {
            **{f"weights:noise{i}": rng.normal() for i in range(40)},
            "weights:signal": 1.5 * y + rng.normal(0, 0.5),
            "behaviour:rate": 0.6 * y + rng.normal(0, 0.3),
        }
        for y in labels
    ]
    return rows, labels


def test_the_stack_beats_each_member_when_their_evidence_is_independent():
    """24 train and 400 held-out synthetic models (seed 0; each member alone ranks them at AUC
    0.80 and 0.94): averaging the members' logits ranks better than either, and a logistic
    regression on the average of the out-of-fold logits gives a held-out log loss below both
    members'. (The default, Platt's smoothed targets with a bound chosen by CV, pays 0.02 of log
    loss here, where no member is ever sure and wrong: the next test is what it is for.)"""
    from sklearn.metrics import log_loss, roc_auc_score

    rng = np.random.default_rng(0)
    train, y_train = _two_member_rows(rng, 24)
    test, y_test = _two_member_rows(rng, 400)
    group = "lavaworld/fc|lavaworld"
    plain = {"meta": "logistic", "logit_bound": "none"}
    stack = make_detector("stack", **plain).fit_rows(train, [group] * len(train), y_train)
    assert stack.meta.kind == "logistic" and stack.meta.features == ["mean_logit"] and stack.meta.coef[0] > 0
    scored = [stack.predict_row(row, group) for row in test]
    p = np.array([s for s, _ in scored])
    for name in ("weights", "behaviour"):
        member = np.array([m[name] for _, m in scored])
        assert roc_auc_score(y_test, p) > roc_auc_score(y_test, member), name
        assert log_loss(y_test, p) < log_loss(y_test, member), name
    again = make_detector("stack", **plain).fit_rows(train, [group] * len(train), y_train)  # deterministic
    assert again.get_state() == stack.get_state()


def _sure_and_wrong_rows(rng, n):
    """A 'weights' member that separates the labels widely (a classifier on it is sure) but reads
    one model in ten as the other label, beside an honest, noisy 'behaviour'; alternating labels."""
    labels = np.arange(n) % 2
    rows = []
    for y in labels:
        read = 1 - y if rng.random() < 0.1 else y
        rows.append(
            {
                **{f"weights:noise{i}": rng.normal() for i in range(10)},
                "weights:signal": 3.0 * read + rng.normal(0, 0.3),
                "behaviour:rate": 0.6 * y + rng.normal(0, 0.3),
            }
        )
    return rows, labels


def test_the_bounded_platt_stack_is_not_outvoted_by_a_member_sure_and_wrong():
    """Seeds 0-3, 24 train and 400 held-out synthetic models each: the default stack (each member's
    logit bounded, the bound chosen by the train split's cross-validated log loss; Platt's
    smoothed targets) has a lower held-out log loss than the plain average under a logistic
    regression on every seed, by 0.10 on average (measured 0.009-0.23); a stack saved without a
    bound reads back unbounded."""
    from sklearn.metrics import log_loss

    group = "lavaworld/fc|lavaworld"
    gains = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        train, y_train = _sure_and_wrong_rows(rng, 24)
        test, y_test = _sure_and_wrong_rows(rng, 400)
        losses = []
        for params in ({"meta": "logistic", "logit_bound": "none"}, {}):
            stack = make_detector("stack", **params).fit_rows(train, [group] * len(train), y_train)
            losses.append(log_loss(y_test, [stack.predict_row(row, group)[0] for row in test]))
        assert losses[1] < losses[0], seed
        gains.append(losses[0] - losses[1])
    assert np.mean(gains) > 0.05
    state, arrays = stack.get_state()
    old = make_detector("stack")
    old.set_state({k: v for k, v in state.items() if k != "logit_bound"}, arrays)
    assert math.isinf(old.bound) and (stack.bound < math.inf) == ("logit_bound" in state)


def _effect_rows(rng, n):
    """Synthetic features of an own-scoring member ('effect': three candidates' effects and the
    summary features) beside a classifier member ('weights'); alternating labels, where a poisoned
    model's shift under one candidate stands out."""
    from rlbackdoors.detect.baselines.effect import EFFECTS, FEATURES

    labels = np.arange(n) % 2
    rows = []
    for y in labels:
        row = {f"effect:{e}@additive:{b}": abs(rng.normal(0.2, 0.05)) for e in EFFECTS for b in (20, 30, 40)}
        row["effect:shift@additive:30"] += 0.4 * y
        row.update({f"effect:{f}": abs(rng.normal(0.2, 0.05)) for f in FEATURES})
        row["weights:signal"] = 1.0 * y + rng.normal(0, 0.8)
        rows.append(row)
    return rows, labels


def test_the_stack_takes_an_own_scoring_member_as_itself(tmp_path):
    """``effect`` scores its features as an anomaly against clean models, not by a classifier: in
    the stack its out-of-fold logits come from copies fitted on the other folds, and the member
    fitted on all 24 synthetic train models is the one a lone ``effect`` fit gives (the same
    probabilities on 40 held-out ones), saved and read back with the stack."""
    rng = np.random.default_rng(1)
    train, y_train = _effect_rows(rng, 24)
    test, _ = _effect_rows(rng, 40)
    group = "lavaworld/fc|lavaworld/fc"
    stack = make_detector("stack", members="effect,weights").fit_rows(train, [group] * len(train), y_train)
    assert stack.scores_itself(0) and not stack.scores_itself(1)
    assert stack.meta.kind == "logistic" and stack.meta.coef[0] > 0
    alone = make_detector("effect").fit_rows([stack._split(r, 0) for r in train], ["lavaworld/fc"] * len(train), y_train)
    for row in test:
        assert stack.predict_row(row, group)[1]["effect"] == pytest.approx(alone.classify(stack._split(row, 0), "lavaworld/fc"), abs=1e-12)
    stack.fitted = True
    again = load_detector(stack.save(tmp_path / "stack"))
    assert [again.classify(r, group) for r in test] == [stack.classify(r, group) for r in test]
    with zipfile.ZipFile(tmp_path / "stack" / "arrays.npz") as npz:
        assert "effect:clean_scores.npy" in npz.namelist()


def test_the_formation_grid_holds_every_pair_of_lidar_bins_once():
    """The agent sees the cubes in a 16-bin pseudo-lidar, one group for both cubes, so the grid
    at distance 0.5 is every unordered pair of bin headings 1.5 to 8 bins apart, each once
    (phi1, eta and its swap phi1 + eta, 2 pi - eta are one formation)."""
    from rlbackdoors.detect.baselines import search_formation as family
    from rlbackdoors.triggers.formation import ETA_RANGE, FormationTrigger

    specs = family.candidates(None, np.random.default_rng(0), family.CANDIDATES)
    assert len(specs) == family.CANDIDATES == 216
    halves = set()
    for spec in specs:
        t = FormationTrigger.parse(spec)
        assert t.distance == 0.5
        a, b = (round(x / (family.BIN / 2)) % 32 for x in (t.phi1, t.phi1 + t.eta))
        assert abs(t.phi1 / (family.BIN / 2) - round(t.phi1 / (family.BIN / 2))) < 1e-9
        halves.add(frozenset((a, b)))
    assert len(halves) == 216  # no formation twice, not even swapped
    for k in range(16):  # every pair of whole bins at least 2 apart (45 degrees) is there
        for sep in range(2, 9):
            assert frozenset((2 * k % 32, (2 * k + 2 * sep) % 32)) in halves
    # neighbours turn phi1 or eta by half a bin, eta kept in the family's range (here its 30 degrees)
    first = FormationTrigger.parse(specs[0])
    assert (first.phi1, first.eta) == (0.0, 1.5 * family.BIN)
    half = family.BIN / 2
    expected = {family._spec(0.5, p, e) for p, e in ((half, first.eta), (-half, first.eta), (0.0, first.eta + half), (0.0, ETA_RANGE[0]))}
    assert set(family.neighbours(specs[0], None, np.random.default_rng(0), 4)) == expected
