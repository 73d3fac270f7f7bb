import os

import pytest
import torch

# Small nets on 2 cores: one intra-op thread is both fastest and deterministic.
torch.set_num_threads(1)
os.environ.setdefault("MPLBACKEND", "Agg")

# JAX as every rlbackdoors process starts it (one compute thread: algos.xla.start), before a test
# module imports it: XLA splits a large minibatch's gradient sums across its threads, so a compiled
# run in this process gives the CLI's bytes (a kill -9 test's other side) only with the CLI's threads.
from rlbackdoors.algos import xla  # noqa: E402

xla.start()


@pytest.fixture
def tiny_run_dict():
    """A config that trains in seconds: small rollouts, few frames, few eval episodes, and no
    clean_vs_triggered.gif (rendering ~480 frames costs ~2.5 s a run on a 2-core EPYC, more than
    the training; the tests that check the GIF turn it back on)."""
    return {
        "ppo": {"rollout": 32},
        "train": {
            "seed": 1,
            "max_frames": 3200,
            "eval_interval": 1600,
            "eval_episodes": 8,
            "final_eval_episodes": 8,
            "video": False,
        },
    }
