"""Training-curve figure of a model folder: what a person looks at first."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402

from rlbackdoors.io import atomic_write_bytes  # noqa: E402


def plot_training_curve(rows: list[dict], path: str | Path, title: str, thresholds: tuple[float, float | None], switch_at: int | None = None) -> Path:
    """Success rates and rewards per evaluation against frames, with the stopping thresholds
    and, for curriculum runs, a vertical line where the warm-up ended: written to ``path``."""
    return atomic_write_bytes(path, render_training_curve(rows, title, thresholds, switch_at))


def render_training_curve(rows: list[dict], title: str, thresholds: tuple[float, float | None], switch_at: int | None = None) -> bytes:
    """:func:`plot_training_curve`'s PNG, as bytes (a painter process draws it; the run writes it)."""
    frames = [r["frames"] for r in rows]
    # Fixed margins, not constrained_layout: its solver was 45 % of a curve's 0.38 s (a model each)
    fig, (ax_sr, ax_rw) = plt.subplots(1, 2, figsize=(10, 3.6))
    fig.subplots_adjust(left=0.065, right=0.99, bottom=0.14, top=0.85, wspace=0.2)
    ax_sr.plot(frames, [r["clean_sr"] for r in rows], "o-", color="tab:green", label="clean SR (goal in E)")
    ax_sr.plot(frames, [r["poisoned_sr"] for r in rows], "s-", color="tab:red", label="poisoned SR (trojan in E-bar)")
    clean_t, poisoned_t = thresholds
    ax_sr.axhline(clean_t, color="tab:green", ls=":", lw=1)
    if poisoned_t is not None:
        ax_sr.axhline(poisoned_t, color="tab:red", ls=":", lw=1)
    ax_sr.set(xlabel="frames", ylabel="success rate", ylim=(-0.02, 1.02), title="evaluation")
    ax_sr.legend(loc="lower right", fontsize=8)
    ax_rw.plot(frames, [r["clean_reward"] for r in rows], "o-", color="tab:green", label="eval clean reward")
    ax_rw.plot(frames, [r["poisoned_reward"] for r in rows], "s-", color="tab:red", label="eval poisoned reward")
    ax_rw.plot(frames, [r["train_clean_return"] for r in rows], "--", color="tab:green", alpha=0.6, label="train return, clean envs")
    if any(r["train_poisoned_return"] == r["train_poisoned_return"] for r in rows):  # any non-NaN
        ax_rw.plot(frames, [r["train_poisoned_return"] for r in rows], "--", color="tab:red", alpha=0.6, label="train return, poisoned envs")
    # Grid-world returns live in [0, 1]; shaped (MuJoCo) returns do not: fit those to the data.
    values = [
        v
        for r in rows
        for k in ("clean_reward", "poisoned_reward", "train_clean_return", "train_poisoned_return")
        if isinstance(v := r.get(k), (int, float)) and v == v
    ]
    low, high = min(values + [0.0]), max(values + [1.0])
    pad = 0.02 * (high - low)
    ax_rw.set(xlabel="frames", ylabel="mean episode return", ylim=(low - pad, high + pad), title="reward")
    if switch_at is not None:
        for ax in (ax_sr, ax_rw):
            ax.axvline(switch_at, color="grey", ls="--", lw=1)
        ax_sr.annotate("curriculum switch", (switch_at, 0.5), rotation=90, fontsize=7, color="grey", ha="right")
    ax_rw.legend(loc="lower right", fontsize=8)
    millions = FuncFormatter(lambda x, _: f"{x / 1e6:g}M")
    for ax in (ax_sr, ax_rw):
        ax.xaxis.set_major_formatter(millions)
    fig.suptitle(title, fontsize=10)
    png = io.BytesIO()
    fig.savefig(png, dpi=110, format="png")
    plt.close(fig)
    return png.getvalue()
