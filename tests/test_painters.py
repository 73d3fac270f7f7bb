"""Training curves and GIFs drawn by painter processes (rlbackdoors.report.painters): the same
picture as drawn in the caller, every one even when a painter dies or a curve cannot be drawn,
and a group that draws them with painters leaves the same model folders as one that draws them itself."""

from __future__ import annotations

import base64
import json
import math
import os
import resource
import signal
import time

import numpy as np
import pytest
import torch

from rlbackdoors.config import RunConfig
from rlbackdoors.report.painters import Drawn, Painters, draw
from rlbackdoors.train.group import painter_count, train_group
from test_group import TINY, tiny


def job(seed: int, evaluations: int = 12) -> dict:
    """A curve as a run asks for it: numpy floats and a NaN (no poisoned envs) among the rows."""
    rng = np.random.default_rng(seed)
    rows = [
        {
            "frames": (i + 1) * 51_200,
            "clean_sr": np.float64(rng.random()),
            "poisoned_sr": float(rng.random()),
            "clean_reward": float(rng.random()),
            "poisoned_reward": float(rng.random()),
            "train_clean_return": np.float32(rng.random()),
            "train_poisoned_return": math.nan,
        }
        for i in range(evaluations)
    ]
    return {"rows": rows, "title": f"curve {seed}", "thresholds": (0.9, 0.8 if seed % 2 else None), "switch_at": 204_800 if seed == 3 else None}


def test_painters_draw_the_png_the_caller_draws_and_every_curve_when_one_dies_or_fails():
    jobs = [job(s) for s in range(5)]
    here = [draw(j) for j in jobs]
    assert here[0][:4] == b"\x89PNG" and len(set(here)) == 5
    with Painters(3) as painters:
        drawn = painters.render(jobs)
        assert len(painters.procs) == 3  # min(workers, curves)
        assert all(isinstance(d, Drawn) for d in drawn)
        assert [d.png for d in drawn] == here  # same matplotlib, same bytes
        # Ctrl-C (SIGINT to the terminal's process group) is the trainer's: painters ignore it
        for proc in painters.procs:
            os.kill(proc.pid, signal.SIGINT)
        time.sleep(0.5)
        assert all(proc.poll() is None for proc in painters.procs)
        # a painter killed between batches: its curves are drawn by the others or here
        painters.procs[0].kill()
        painters.procs[0].wait()
        again = painters.render(jobs)
        assert [d.png for d in again if isinstance(d, Drawn)] == here and len(again) == 5
        assert len(painters.procs) == 2
        # a curve that cannot be drawn (a row without its keys): that run gets the error, the others their curves
        broken = [jobs[0], {"rows": [{"frames": 1}], "title": "broken", "thresholds": (0.9, None)}, jobs[2]]
        out = painters.render(broken)
        assert isinstance(out[1], KeyError) and [out[0].png, out[2].png] == [here[0], here[2]]  # type: ignore[union-attr]
        procs = list(painters.procs)
    assert painters.procs == [] and all(p.poll() is not None for p in procs)  # closed: every painter has exited


def test_the_painters_cpu_is_counted_whole_by_their_replies_and_their_reaping():
    """The replies carry each painter's start-up (its imports, with its first picture) and its
    pictures; the reaping reads the rest (the exit) from the kernel, so the two add up to the
    children's CPU clock. Without the start-up in the replies, or with Python's teardown at exit
    (0.33 of 2.2 CPU-s a painter on an AMD EPYC), the unreported part would pass a tenth of the
    whole; with ``os._exit`` it is the kernel's exit alone (0.6 % there)."""
    jobs = [job(s) for s in range(4)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with Painters(2) as painters:
        drawn = painters.render(jobs)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    children = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    reported = sum(d.cpu_s for d in drawn)  # type: ignore[union-attr]
    assert all(isinstance(d, Drawn) and d.cpu_s > 0 for d in drawn)
    assert reported + painters.unreported_s == pytest.approx(children, abs=0.01)  # the replies round to 0.1 ms each
    assert painters.unreported_s <= 0.1 * children


def test_a_library_printing_to_stdout_does_not_cross_the_replies(tmp_path, monkeypatch):
    """Whatever a painter's libraries print (pygame prints a banner on import): a line at start-up,
    before the painter owns its pipe, and one from a thread while it draws. Each curve still comes
    back to the run that asked, drawn by a painter."""
    (tmp_path / "sitecustomize.py").write_text(
        "import os, sys, threading, time\n"
        "print('hello from a library')\n"
        "sys.stdout.flush()\n"
        "threading.Thread(target=lambda: (time.sleep(1.0), os.write(1, b'a late line\\n')), daemon=True).start()\n"
    )
    monkeypatch.setenv("PYTHONPATH", str(tmp_path) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    jobs = [job(s) for s in range(6)]
    with Painters(2) as painters:
        drawn = painters.render(jobs)
    assert all(isinstance(d, Drawn) and d.cpu_s > 0 for d in drawn)  # from the painters, none redrawn here
    assert [d.png for d in drawn] == [draw(j) for j in jobs]  # type: ignore[union-attr]


def test_painters_that_do_not_answer_in_time_are_ended_and_their_pictures_drawn_here():
    """A limit of 0.1 s without a reply: shorter than a painter's start (Python and matplotlib's
    imports), so every painter is ended and every curve drawn in the caller, none lost."""
    jobs = [job(s) for s in range(3)]
    with Painters(2, timeout=0.1) as painters:
        drawn = painters.render(jobs)
        assert painters.procs == []
    assert all(isinstance(d, Drawn) and d.cpu_s == 0.0 for d in drawn)  # drawn here
    assert [d.png for d in drawn] == [draw(j) for j in jobs]  # type: ignore[union-attr]


def test_fewer_than_two_painters_or_curves_draw_in_the_caller():
    with Painters(1) as one:
        assert [d.png for d in one.render([job(0), job(1)])] == [draw(job(0)), draw(job(1))]  # type: ignore[union-attr]
        assert one.procs == []
    with Painters(4) as four:
        assert [d.png for d in four.render([job(2)])] == [draw(job(2))]  # type: ignore[union-attr]
        assert four.procs == []


def test_painters_are_for_gpu_groups_only():
    runs = [(s, tiny(s), None) for s in range(4)]
    assert painter_count(runs, 4) == 0  # CPU learners: a painter would take a core from training
    assert painter_count(runs, 1) == 0
    # learners on CUDA: the host's other cores, at most one a run; on a machine without CUDA none,
    # and no error here (each run then fails alone, with its own message)
    cuda = [(s, tiny(s, train={**TINY["train"], "seed": s, "device": "cuda"}), None) for s in range(4)]
    assert cuda[0][1].train.device == "cuda"
    assert painter_count(cuda, 4) == (min(4, (os.cpu_count() or 1) - 1) if torch.cuda.is_available() else 0)


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_a_group_with_painters_leaves_the_folders_a_group_without_them_does(tmp_path):
    """Three tiny LavaWorld runs (4 evaluations of 4 episodes) in a group of 3, finishing together:
    painters draw their curves and GIFs (the GIF's network rebuilt from the weights sent over the
    pipe); the same model.pt, curve, GIF and metrics (but the clocks) as the group drawing them itself."""
    sides, spent = {}, {}
    for workers in (0, 2):
        # with GIFs (short episodes: an untrained agent plays to the step limit)
        def config(seed: int) -> RunConfig:
            return RunConfig.from_dict({**TINY, "env": {"name": "lavaworld", "max_steps": 24}, "train": {**TINY["train"], "seed": seed, "video": True}})

        runs = [(s, config(s), tmp_path / f"p{workers}" / f"s{s}") for s in (1, 2, 3)]
        before = (time.process_time(), resource.getrusage(resource.RUSAGE_CHILDREN))
        result = train_group(runs, 3, painters=workers)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        spent[workers] = (time.process_time() - before[0], after.ru_utime + after.ru_stime - before[1].ru_utime - before[1].ru_stime)
        assert not result.errors and set(result.metrics) == {1, 2, 3}
        sides[workers] = result
    for s in (1, 2, 3):
        a, b = tmp_path / "p0" / f"s{s}", tmp_path / "p2" / f"s{s}"
        for name in ("model.pt", "training_curve.png", "clean_vs_triggered.gif", "ground_truth.csv"):  # log.csv holds wall times
            assert (a / name).read_bytes() == (b / name).read_bytes(), name
        m0, m2 = (sides[w].metrics[s] for w in (0, 2))
        assert {k: v for k, v in m0.items() if k not in ("cpu_time_s", "wall_time_s")} == {
            k: v for k, v in m2.items() if k not in ("cpu_time_s", "wall_time_s")
        }
    # the painters' CPU seconds (start, pictures and exit, as the children's clock reads them once
    # they have exited) are counted in the runs' shares, beside this process's own: the shares and
    # the group's overhead add up to both clocks, whatever the CPU (0.02 s: this test's own calls
    # between the clocks and the call, and the painters' replies rounded to 0.1 ms)
    assert spent[0][1] == pytest.approx(0.0, abs=1e-6)  # no child process without painters (the clock is in microseconds)
    for workers, result in sides.items():
        own, painters = spent[workers]
        assert result.overhead_s >= 0.0 and sum(result.cpu_s.values()) + result.overhead_s == pytest.approx(own + painters, abs=0.02)
    own, painters = spent[2]
    assert painters > 0.0 and sum(sides[2].cpu_s.values()) >= painters - 0.01  # every painter drew for a run: its CPU is in the runs'
    # and the GIFs did come from the painters: two GIF requests built from the folders (config, model.pt)
    jobs = []
    for s in (1, 2):
        folder = tmp_path / "p0" / f"s{s}"
        cfg = json.loads((folder / "config.json").read_text())
        weights = base64.b64encode((folder / "model.pt").read_bytes()).decode("ascii")
        jobs.append({"kind": "gif", "config": cfg, "weights": weights, "seed": cfg["train"]["eval_seed"], "policy": cfg["train"]["eval_policy"]})
    with Painters(2) as painters:
        drawn = painters.render(jobs)
    assert all(isinstance(d, Drawn) and d.cpu_s > 0 for d in drawn)  # a painter's clock: drawn there, not here
    assert [d.png for d in drawn] == [(tmp_path / "p0" / f"s{s}" / "clean_vs_triggered.gif").read_bytes() for s in (1, 2)]  # type: ignore[union-attr]
