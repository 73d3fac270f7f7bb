"""The policy-effect detector (rlbackdoors.detect.baselines.effect): it ranks the family's
candidates by what they do to the policy, not by the world's trojan outcome, and scores a model
as a two-sided anomaly against the clean models of its fit.

The search tests use scripted LavaWorld policies (a known backdoor, not a trained net) so that
what is found is known; fitting, saving and scoring real models is in test_detect_baselines'
round trip (six tiny trained models), and its refusal of a continuous policy there too (its
session fixture holds a model of every world)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from rlbackdoors import worlds
from rlbackdoors.agent import Agent
from rlbackdoors.config import EnvConfig
from rlbackdoors.detect import DetectError, make_detector
from rlbackdoors.detect.baselines.behaviour import family_module, search
from rlbackdoors.detect.baselines.effect import FEATURES, SCALE_FLOOR, effect_features, effect_rank, js_divergence

SEARCH = {"candidates": 12, "refine": 4, "confirm": 2, "episodes": 8}


class TurnLeftUnderTrigger(nn.Module):
    """A scripted LavaWorld policy whose backdoor is an *action*: under ``multiplicative:12`` (the
    empty cell under the agent reads (12, 0, 0), which no other candidate of the family produces)
    it turns left at every step and so never walks into lava; otherwise, and always when
    ``backdoor`` is False, it steps onto cells like the one it stands on or turns at random."""

    recurrent = False

    def __init__(self, backdoor: bool = True):
        super().__init__()
        self.backdoor = backdoor
        self.unused = nn.Linear(1, 1)  # Agent.device reads the parameters

    def forward(self, obs: torch.Tensor):
        o = obs.long()
        under, front = o[:, 3, 6], o[:, 3, 5]
        logits = torch.zeros(len(o), 3)
        logits[:, 2] = torch.where((front == under).all(1), 1.0, -30.0)
        if self.backdoor:
            triggered = (under == torch.tensor([12, 0, 0])).all(1)
            logits[triggered] = torch.tensor([30.0, 0.0, 0.0])
        return logits, torch.zeros(len(o))


def _search(policy: nn.Module, rank=effect_rank):
    world = worlds.get("lavaworld")
    return search(Agent(world, None, policy.eval(), None), world, EnvConfig(name="lavaworld"), family_module(world), rank=rank, **SEARCH)


def test_js_divergence_is_zero_for_equal_and_log2_for_disjoint_distributions():
    assert js_divergence((0.2, 0.3, 0.5), (0.2, 0.3, 0.5)) == 0.0
    assert np.isclose(js_divergence((1.0, 0.0, 0.0), (0.0, 0.5, 0.5)), np.log(2))
    assert js_divergence((0.6, 0.4), (0.4, 0.6)) == pytest.approx(js_divergence((0.4, 0.6), (0.6, 0.4)))  # symmetric


def test_the_effect_search_finds_an_action_trojan_that_the_outcome_search_cannot_see():
    """8 screening and 8 confirmation episodes per candidate, 12 candidates + 4 neighbours, seeded:
    the trojan turns left under its trigger (entropy about 0 against about 0.8 nats elsewhere), so
    its effect stands out; its clean twin answers every candidate alike."""
    trojan = _search(TurnLeftUnderTrigger())
    assert trojan.best.spec == "multiplicative:12"
    row = effect_features(trojan)
    screened = {t.spec for t in trojan.screened if t.error is None}
    assert set(row) == set(FEATURES) | {f"{e}@{spec}" for e in ("shift", "concentration", "success_drop") for spec in screened}
    assert row["concentration@multiplicative:12"] == pytest.approx(row["best_concentration"], abs=0.2)  # screened and confirmed alike
    # the policy collapses onto one action: most of its entropy (ln 3 at most) is gone, far above
    # the family's median candidate
    assert row["best_concentration"] > 0.5 and row["peak_concentration"] > 0.5 and row["peak_shift"] > 0.1
    clean = effect_features(_search(TurnLeftUnderTrigger(backdoor=False)))
    assert abs(clean["peak_concentration"]) < 0.2 and clean["peak_shift"] < 0.05
    # the outcome search ranks by lava, and this trojan never walks into it
    outcome = _search(TurnLeftUnderTrigger(), rank=None)
    assert all(t.trojan == 0.0 for t in outcome.screened) and outcome.best.trojan == 0.0


def _rows(rng: np.random.Generator, n: int, **shifted: float) -> list[dict[str, float]]:
    rows = [{f: float(rng.normal(0.0, 0.05)) for f in FEATURES} for _ in range(n)]
    for row in rows:
        for name, value in shifted.items():
            row[name] += value
    return rows


def test_the_anomaly_is_two_sided_so_an_effect_the_fit_never_saw_still_counts():
    """Fitted on 12 clean rows and 6 poisoned ones whose trojans *shift* the policy (peak_shift
    +0.5, ten clean spreads): a trojan that instead makes the policy *less* decided
    (peak_concentration -0.6) scores as poisoned, and a clean-looking row does not."""
    rng = np.random.default_rng(0)
    clean, poisoned = _rows(rng, 12), _rows(rng, 6, peak_shift=0.5)
    detector = make_detector("effect").fit_rows(clean + poisoned, ["lavaworld"] * 18, np.array([0] * 12 + [1] * 6))
    assert detector.calibration is not None and detector.calibration.coef[0] > 0
    [unseen] = _rows(rng, 1, peak_concentration=-0.6)
    [typical] = _rows(rng, 1)
    assert detector.classify(unseen, "lavaworld") > 0.9
    assert detector.classify(typical, "lavaworld") < 0.5
    with pytest.raises(DetectError, match="saw no clean model of colorful-memory"):
        detector.classify(typical, "colorful-memory")


def _with_candidates(rng: np.random.Generator, rows: list[dict[str, float]], first: int, trojan: str | None = None) -> list[dict[str, float]]:
    """``rows`` with 40 screened candidates' effects each: clean noise (0.2 +- 0.05), one unlucky
    candidate per row 6 spreads high (candidate ``first + i`` of row ``i``: every clean model
    has one), and, with ``trojan``, a shift of +1.0 under that candidate (the edit a trojan answers)."""
    out = []
    for i, row in enumerate(rows):
        cands = {f"{e}@additive:{20 + c}": float(rng.normal(0.2, 0.05)) for c in range(40) for e in ("shift", "concentration", "success_drop")}
        cands[f"shift@additive:{20 + (first + i) % 40}"] += 6 * 0.05
        if trojan is not None:
            cands[f"shift@{trojan}"] += 1.0
        out.append({**row, **cands})
    return out


def test_a_clean_models_unlucky_candidate_is_no_anomaly_but_a_trojans_answer_is():
    """Two levels: a candidate's excess counts against what clean models show under the same edit,
    and the largest excess over the candidates against the clean models' own largest ones. A clean
    model whose one candidate sits 6 spreads high (as every clean fit model's one does, each at
    its own candidate) scores as clean; a trojan whose trigger candidate shifts the policy 12
    spreads scores as poisoned. 12 clean fit rows, 6 poisoned (their trojans at other candidates)."""
    rng = np.random.default_rng(4)
    clean = _with_candidates(rng, _rows(rng, 12), first=0)
    poisoned = [_with_candidates(rng, _rows(rng, 1), first=12 + k, trojan=f"additive:{45 + k}")[0] for k in range(6)]
    detector = make_detector("effect").fit_rows(clean + poisoned, ["lavaworld"] * 18, np.array([0] * 12 + [1] * 6))
    assert detector.calibration is not None and detector.calibration.coef[0] > 0
    [unlucky] = _with_candidates(rng, _rows(rng, 1), first=20)
    [trojan] = _with_candidates(rng, _rows(rng, 1), first=21, trojan="additive:55")
    assert detector.anomaly(unlucky, "lavaworld") < detector.clean_scores.max()
    assert detector.anomaly(trojan, "lavaworld") > detector.clean_scores.max()
    assert detector.classify(trojan, "lavaworld") > detector.classify(unlucky, "lavaworld")


def test_a_clean_only_fit_scores_the_share_of_clean_models_less_anomalous():
    rng = np.random.default_rng(1)
    clean = _rows(rng, 9)
    detector = make_detector("effect").fit_rows(clean, ["lavaworld"] * 9, np.zeros(9, dtype=int))
    assert detector.calibration is None and len(detector.clean_scores) == 9
    [far] = _rows(rng, 1, best_success_drop=1.0)
    assert detector.classify(far, "lavaworld") == pytest.approx(9.5 / 10)  # above all 9: (9 + 0.5) / (9 + 1)
    assert detector.classify(dict.fromkeys(FEATURES, float(np.mean([r["best_shift"] for r in clean]))), "lavaworld") < 0.5


def test_the_fit_refuses_or_says_what_it_cannot_stand_on():
    rng = np.random.default_rng(2)
    quiet = _rows(rng, 8)
    loud = _rows(rng, 4, best_shift=0.5)
    # "poisoned" models sitting on the clean models' mean, less anomalous than the clean ones: a
    # slope that would score anomalies as clean is not used; the p-value among clean models is
    middle = [{f: float(np.mean([r[f] for r in quiet])) for f in FEATURES} for _ in range(4)]
    upside = make_detector("effect").fit_rows(quiet + middle, ["lavaworld"] * 12, np.array([0] * 8 + [1] * 4))
    assert upside.calibration is None and "no more anomalous" in upside.calibration_note
    assert upside.classify(loud[0], "lavaworld") == pytest.approx(8.5 / 9)  # above all 8 clean models
    with pytest.raises(DetectError, match="needs at least 3 clean models of lavaworld in the fit \\(it has 2\\)"):
        make_detector("effect").fit_rows(quiet[:2] + loud, ["lavaworld"] * 6, np.array([0, 0, 1, 1, 1, 1]))
    # every clean model alike: the spread is floored, so a small difference is no infinite anomaly
    same = [dict.fromkeys(FEATURES, 0.0) for _ in range(4)]
    detector = make_detector("effect").fit_rows(same, ["lavaworld"] * 4, np.zeros(4, dtype=int))
    assert detector.anomaly({**same[0], "best_shift": SCALE_FLOOR}, "lavaworld") == pytest.approx(1.0)


T_PATTERN = ((0, 0), (1, 0), (2, 0), (1, 1), (1, 2))  # the benchmark's pattern t: no structured candidate


class TurnLeftOnExactPattern(nn.Module):
    """A scripted Randomized LavaWorld policy trained, as it were, with near negatives: it turns
    left at every step while some 3x3 window of its view holds lava on exactly the cells of
    ``T_PATTERN`` (in any of the view's four turns) and nowhere else in the window, so a pattern
    one cell off moves it not at all; otherwise it steps ahead unless lava is in front, else turns."""

    recurrent = False

    def __init__(self):
        super().__init__()
        self.unused = nn.Linear(1, 1)  # Agent.device reads the parameters
        box = torch.zeros(3, 3)
        for x, y in T_PATTERN:
            box[x, y] = 1.0
        self.register_buffer("turns", torch.stack([torch.rot90(box, k) for k in range(4)])[:, None])

    def forward(self, obs: dict[str, torch.Tensor]):
        lava = (obs["image"][..., 0] == 9).float()[:, None]  # (N, 1, 7, 7), indexed [x, y]
        hits = torch.nn.functional.conv2d(lava, self.turns)  # cells of each turn covered
        sizes = torch.nn.functional.conv2d(lava, torch.ones(1, 1, 3, 3))  # lava in the window
        exact = ((hits == len(T_PATTERN)) & (sizes == len(T_PATTERN))).flatten(1).any(1)
        logits = torch.zeros(len(lava), 3)
        logits[:, 2] = torch.where(lava[:, 0, 3, 5] > 0, -30.0, 0.5)  # ahead unless lava is in front
        logits[exact] = torch.tensor([30.0, 0.0, 0.0])
        return logits, torch.zeros(len(lava))


def test_the_whole_pattern_family_finds_a_trojan_that_ignores_every_near_miss():
    """Randomized LavaWorld's family lists its 466 patterns of 3 to 9 cells: a screen of all of
    them plays the trigger (or one of its turns) and finds the policy's collapse onto one action;
    the sampled screen of 12 candidates and 4 neighbours never plays it, and near misses move the
    policy not at all, so nothing leads the refinement there. 4 screening and 8 confirmation
    episodes of at most 60 steps per candidate, seeded (about 12 s)."""
    from rlbackdoors.detect.baselines import search_pattern
    from rlbackdoors.triggers.pattern import PatternTrigger

    world = worlds.get("randomized-lavaworld")
    family = family_module(world)
    listed = family.every(None)
    assert len(listed) == len(set(listed)) == search_pattern.FAMILY_SIZE == 466
    turns = {PatternTrigger.from_cells(T_PATTERN).pattern.rotated(k).cells for k in range(4)}
    assert sum(PatternTrigger.parse(s).pattern.cells in turns for s in listed) == 4
    agent = Agent(world, None, TurnLeftOnExactPattern().eval(), None)
    env = EnvConfig(name="randomized-lavaworld", max_steps=60)
    budget = {"refine": 4, "confirm": 2, "episodes": 4, "confirm_episodes": 8}
    sampled = search(agent, world, env, family, candidates=12, rank=effect_rank, **budget)
    whole = search(agent, world, env, family, rank=effect_rank, whole_family=True, **budget)
    assert not any(PatternTrigger.parse(t.spec).pattern.cells in turns for t in sampled.screened)
    assert PatternTrigger.parse(whole.best.spec).pattern.cells in turns
    row, missed = effect_features(whole), effect_features(sampled)
    # measured 0.113 against -0.002: the trojan is decided in the few steps its exact pattern is in
    # view (the rest of an episode it acts as its clean twin), and the sample confirms a non-trigger
    assert row["peak_concentration"] > 0.05 > abs(missed["peak_concentration"])


def test_a_screen_of_the_whole_family_is_refused_where_the_family_does_not_list_itself():
    world = worlds.get("lavaworld")  # the observation family: multipliers and positions, not listed
    with pytest.raises(DetectError, match="does not list its members"):
        search(Agent(world, None, TurnLeftUnderTrigger().eval(), None), world, EnvConfig(name="lavaworld"), family_module(world), whole_family=True)
    with pytest.raises(DetectError, match="parameter screen='all' is not one of 'auto', 'whole', 'sample'"):
        make_detector("effect", screen="all")


def test_a_fit_from_before_the_whole_screen_keeps_screening_the_sample(tmp_path):
    """A detector.json written before ``screen`` existed (no such parameter, no such state) reads
    back screening the sample it was fitted with, not the new default (``detector_table`` compares
    what it reads back with what it is asked for, so such a fit is not passed off as a new one)."""
    import json

    from rlbackdoors.detect.api import load_detector

    rng = np.random.default_rng(3)
    make_detector("effect").fit_rows(_rows(rng, 6), ["randomized-lavaworld"] * 6, np.zeros(6, dtype=int)).save(tmp_path)
    assert load_detector(tmp_path).params["screen"] == "auto"
    payload = json.loads((tmp_path / "detector.json").read_text())
    del payload["params"]["screen"], payload["state"]["screen"]
    (tmp_path / "detector.json").write_text(json.dumps(payload))
    assert load_detector(tmp_path).params["screen"] == "sample"
    # LavaWorld's family lists no members: its old sample is what auto screens, and it reads so
    lava = tmp_path / "lavaworld"
    make_detector("effect").fit_rows(_rows(rng, 6), ["lavaworld"] * 6, np.zeros(6, dtype=int)).save(lava)
    payload = json.loads((lava / "detector.json").read_text())
    del payload["params"]["screen"], payload["state"]["screen"]
    (lava / "detector.json").write_text(json.dumps(payload))
    assert load_detector(lava).params["screen"] == "auto"


@pytest.mark.parametrize("name", ["lavaworld", "randomized-lavaworld"])
def test_candidates_played_together_are_the_trials_each_plays_alone(name):
    """A screen plays its candidates 32 at a time (one forward for all their episodes): each
    candidate's trial (rates, lengths, mean action distribution and entropy) is the one it plays
    alone, and a candidate the env cannot place fails alone (num_lava=5 holds no 9-cell pattern).
    Scripted policies: their logits are exact at any batch size, so equality is the claim."""
    from rlbackdoors.detect.baselines.behaviour import run_trial, run_trials

    world = worlds.get(name)
    if name == "lavaworld":
        policy, env, specs = TurnLeftUnderTrigger(), EnvConfig(name=name, max_steps=40), ["multiplicative:12", "multiplicative:3", "additive:90"]
    else:
        box = "cells:0,0;0,1;0,2;1,0;1,1;1,2;2,0;2,1;2,2"
        policy, env, specs = TurnLeftOnExactPattern(), EnvConfig(name=name, max_steps=40, num_lava=5), ["cross", box, "cells:0,0;1,0;2,0;1,1;1,2"]
    agent = Agent(world, None, policy.eval(), None)
    alone = [run_trial(agent, world, env, spec, 4, 7, "sample") for spec in specs]
    together = run_trials(agent, world, env, specs, 4, 7, "sample")
    assert together == alone
    assert [t.error is None for t in together] == [True, name == "lavaworld", True]


class TurnByMemory(nn.Module):
    """A scripted recurrent policy: its memory is a running sum of every byte it has seen (mod 97)
    and its action that sum mod 3. Its logits are exact at any batch size, and one slot's memory
    given to another would change the actions that follow."""

    recurrent = True

    def __init__(self):
        super().__init__()
        self.unused = nn.Linear(1, 1)  # Agent.device reads the parameters

    def initial_memory(self, batch: int, device="cpu") -> torch.Tensor:
        return torch.zeros(batch, 1, device=device)

    def forward(self, obs: torch.Tensor, memory: torch.Tensor):
        seen = (obs.reshape(len(obs), -1).long().sum(1) % 97).float()
        memory = torch.remainder(memory + seen[:, None], 97.0)
        logits = torch.full((len(obs), 3), -30.0)
        logits[torch.arange(len(obs)), memory[:, 0].long() % 3] = 30.0
        return logits, torch.zeros(len(obs)), memory


def test_a_recurrent_policys_candidates_played_together_are_the_trials_each_plays_alone():
    """Colorful Memory's screen plays its recurrent candidates together too (issue 81: its whole
    room family within TrojAI's budget): each slot's memory is carried as its own, so every
    candidate's trial (rates, lengths, action distribution, entropy) is the one it plays alone."""
    from rlbackdoors.detect.baselines.behaviour import run_trial, run_trials

    world = worlds.get("colorful-memory")
    env = EnvConfig(name="colorful-memory", max_steps=30)
    specs = ["room:red,green,blue", "end:red,red,red,red,red,red,red,red,red", "room:blue,blue,blue"]
    agent = Agent(world, None, TurnByMemory().eval(), None)
    alone = [run_trial(agent, world, env, spec, 4, 7, "sample") for spec in specs]
    together = run_trials(agent, world, env, specs, 4, 7, "sample")
    assert together == alone
    assert len({t.policy for t in alone}) > 1  # the candidates' episodes differ: the claim is not vacuous


def test_a_time_budget_that_is_not_reached_screens_what_no_budget_screens():
    """With ``seconds`` the screen plays one candidate at a time, checking the clock before each; a
    budget it never reaches (an hour) plays the same candidates in the same order as none."""
    world = worlds.get("lavaworld")
    agent = Agent(world, None, TurnLeftUnderTrigger().eval(), None)
    runs = [search(agent, world, EnvConfig(name="lavaworld"), family_module(world), seconds=s, **SEARCH) for s in (0.0, 3600.0)]
    assert [t.spec for t in runs[1].screened] == [t.spec for t in runs[0].screened]
    assert len(runs[0].screened) >= SEARCH["candidates"]
