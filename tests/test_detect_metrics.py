"""Scoring arithmetic (issue 17) against hand computations: TrojAI's clipped cross-entropy, AUC,
Brier, bootstrap CIs, breakdowns and the plots."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rlbackdoors.detect import metrics


def test_the_constant_half_detector_scores_ln2_auc_half_and_brier_quarter():
    for n in (2, 7, 40, 101):  # sizes where a plain mean of ln 2 would round off
        y = np.arange(n) % 2
        p = np.full(n, 0.5)
        assert metrics.cross_entropy(p, y) == math.log(2)
        assert metrics.auc(p, y) == 0.5
        assert metrics.brier(p, y) == 0.25


def test_cross_entropy_is_trojais_clipped_formula():
    p = np.array([0.9, 0.2, 0.6, 0.0, 1.0])
    y = np.array([1, 0, 0, 1, 0])
    eps = 1e-12
    by_hand = [-math.log(0.9), -math.log(0.8), -math.log(0.4), -math.log(eps), -math.log(1 - (1 - eps))]
    assert metrics.cross_entropy_per_model(p, y) == pytest.approx(by_hand, rel=1e-12)
    assert metrics.cross_entropy(p, y) == pytest.approx(sum(by_hand) / 5, rel=1e-12)
    # a sure, wrong answer costs about -ln(1e-12) = 27.63 (1 - 1e-12 rounds in float64, as in
    # TrojAI's harness), not infinity; a sure right one costs ~1e-12, not 0
    assert metrics.cross_entropy([1.0], [0]) == -math.log(1.0 - (1.0 - 1e-12)) == pytest.approx(27.631, abs=1e-3)
    assert metrics.cross_entropy([0.0], [1]) == -math.log(1e-12)
    assert 0 < metrics.cross_entropy([1.0, 0.0], [1, 0]) < 1e-11


def test_auc_of_a_known_ranking_and_a_perfect_detector():
    # positives at 0.35 and 0.8, negatives at 0.1 and 0.4: 3 of 4 pairs ordered right
    assert metrics.auc([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == 0.75
    assert metrics.auc([0.5, 0.5, 0.2], [0, 1, 0]) == 0.75  # a tie counts half
    assert metrics.auc([0.1, 0.2, 0.7, 0.9], [0, 0, 1, 1]) == 1.0
    assert math.isnan(metrics.auc([0.1, 0.2], [1, 1]))
    assert metrics.brier([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == pytest.approx((0.01 + 0.16 + 0.4225 + 0.04) / 4)


def test_bootstrap_cis_are_reproducible_contain_the_estimate_and_skip_one_label_resamples():
    rng = np.random.default_rng(5)
    y = np.arange(30) % 2
    p = np.clip(0.5 + 0.3 * (y - 0.5) + rng.normal(0, 0.25, 30), 0, 1)
    summary = metrics.summarize(p, y, resamples=2000, seed=0)
    for name in metrics.METRICS:
        low, high = summary[name]["ci"]
        assert low <= summary[name]["value"] <= high and low < high
    assert summary["ce"]["resamples"] == 2000
    again = metrics.bootstrap_ci("auc", p, y, 2000, seed=0)
    other = metrics.bootstrap_ci("auc", p, y, 2000, seed=1)
    assert again[:2] == tuple(summary["auc"]["ci"]) and again != other
    # 3 models, one poisoned: (2/3)^3 + (1/3)^3 of resamples hold one label and have no AUC
    low, high, used = metrics.bootstrap_ci("auc", [0.2, 0.3, 0.9], [0, 0, 1], 2000, seed=0)
    assert 1000 < used < 2000 and low == high == 1.0
    perfect = metrics.summarize([0.1, 0.2, 0.8, 0.9], [0, 0, 1, 1])
    assert perfect["auc"]["value"] == 1.0 and perfect["auc"]["ci"] == [1.0, 1.0]


def test_breakdown_scores_each_level_on_its_own_models():
    p = np.array([0.1, 0.9, 0.5, 0.5, 0.2, 0.7])
    y = np.array([0, 1, 0, 1, 0, 1])
    worlds = ["a", "a", "b", "b", "a", "a"]
    out = metrics.breakdown(p, y, {"world": worlds}, resamples=200)
    assert out["world"]["a"]["n"] == 4 and out["world"]["a"]["auc"]["value"] == 1.0
    assert out["world"]["b"]["ce"]["value"] == math.log(2) and out["world"]["b"]["auc"]["value"] == 0.5


def test_the_reliability_curve_bins_predictions_and_weighs_each_bin_s_gap_by_its_models():
    # bins of 0.5: [0.1, 0.2, 0.4] with one poisoned (mean 0.233, share 0.333); [0.6, 0.9] both poisoned (0.75, 1.0)
    out = metrics.reliability([0.1, 0.2, 0.4, 0.6, 0.9], [0, 0, 1, 1, 1], bins=2)
    assert [b["models"] for b in out["bins"]] == [3, 2] and [b["bin"] for b in out["bins"]] == [[0.0, 0.5], [0.5, 1.0]]
    assert out["bins"][0]["mean_probability"] == pytest.approx(0.7 / 3) and out["bins"][1]["share_poisoned"] == 1.0
    assert out["ece"] == pytest.approx((3 * abs(0.7 / 3 - 1 / 3) + 2 * 0.25) / 5)
    assert metrics.reliability([1.0, 0.0], [1, 0], bins=10)["ece"] == 0.0  # a prediction of exactly 1 falls in the last bin
    assert [b["bin"][0] for b in metrics.reliability([1.0, 0.0], [1, 0], bins=10)["bins"]] == [0.0, 0.9]


def test_plots_are_pngs(tmp_path):
    p, y = [0.1, 0.6, 0.4, 0.9, 0.3, 0.8], [0, 0, 1, 1, 0, 1]
    roc = metrics.plot_roc(p, y, ["a", "a", "a", "b", "b", "b"], tmp_path / "roc.png")
    cal = metrics.plot_calibration(p, y, tmp_path / "cal.png")
    for path in (roc, cal):
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000


def test_an_auc_grid_colours_each_cell_by_its_auc_and_leaves_missing_ones_grey(tmp_path):
    """Read back as pixels: a cell of AUC 0.0 paints a block of the colour map's red end, one of 1.0
    its blue end, a missing cell grey (the colour bar holds only a sliver of each end)."""
    import matplotlib
    import matplotlib.image

    ends = {"red": np.array(matplotlib.colormaps["RdBu"](0.0)[:3]), "blue": np.array(matplotlib.colormaps["RdBu"](1.0)[:3]), "grey": np.full(3, 0.9)}

    def pixels(cells: dict) -> dict[str, int]:
        path = metrics.plot_auc_grid(["fit a", "fit b"], ["x", "y"], cells, tmp_path / "grid.png", title="t")
        image = matplotlib.image.imread(path)[..., :3]
        return {name: int(np.all(np.abs(image - rgb) < 0.02, axis=2).sum()) for name, rgb in ends.items()}

    full = {("fit a", "x"): {"value": 1.0, "ci": [1.0, 1.0], "models": 20}, ("fit a", "y"): {"value": 0.0, "ci": None}, ("fit b", "x"): {"value": 0.5}}
    shown = pixels(full)
    without_red = pixels({**full, ("fit a", "y"): {"value": None}})
    assert shown["red"] > 10 * max(without_red["red"], 1) and shown["blue"] > 1000
    assert without_red["grey"] > shown["grey"] + 1000  # the cell left out is grey, as the one never given


def test_a_one_label_roc_is_a_png_without_warnings(tmp_path):
    """Scoring a control of clean models only: no curve, no legend warning, still a PNG."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        roc = metrics.plot_roc([0.2, 0.9, 0.4], [0, 0, 0], None, tmp_path / "roc.png")
    assert roc.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_summarize_rows_is_summarize_of_the_rows():
    """The pooling helper of the benchmark scripts: the same values and CIs as summarize."""
    rows = [{"probability": p, "label": y} for p, y in zip([0.1, 0.6, 0.4, 0.9, 0.3, 0.8], [0, 0, 1, 1, 0, 1])]
    full, short = metrics.summarize([r["probability"] for r in rows], [r["label"] for r in rows]), metrics.summarize_rows(rows)
    assert short["n"] == 6 and short["poisoned"] == 3
    assert all(short[k] == {"value": full[k]["value"], "ci": full[k]["ci"]} for k in ("auc", "ce", "brier"))
    assert metrics.summarize_rows([]) == {"n": 0}
