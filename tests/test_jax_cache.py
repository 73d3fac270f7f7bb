"""JAX's compilation cache (algos/xla.compile_cache_dir): private, per machine, refused where
another user may write it, off on request; a program read from it trains the same bytes as one
compiled anew (two fresh processes on one cache)."""

from __future__ import annotations

import os
import stat
import subprocess
import sys

import pytest


from rlbackdoors.algos.xla import CACHE_ENV, compile_cache_dir  # noqa: E402


def test_the_cache_is_private_and_per_machine(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "c"))
    path = compile_cache_dir()
    assert path is not None and path.parent == tmp_path / "c" and path.name.startswith("jax-") and len(path.name) == 16
    assert stat.S_IMODE(path.stat().st_mode) == 0o700
    assert compile_cache_dir() == path  # the same machine: the same folder
    os.chmod(path, 0o770)  # another user of the group may write it: not trusted
    with pytest.warns(UserWarning, match="is not .*'s alone"):
        assert compile_cache_dir() is None
    monkeypatch.setenv(CACHE_ENV, "off")
    assert compile_cache_dir() is None


RUN = """
import hashlib, sys
sys.path.insert(0, "tests")
from test_compiled_attacks import iterate, seam_learner
learner = seam_learner({"attack": "trojdrl", "attack_params": {"budget": 0.03}})
iterate([learner])
print(hashlib.sha256(b"".join(learner.state.params[k].tobytes() for k in sorted(learner.state.params))).hexdigest())
"""


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_a_program_from_the_cache_trains_the_same_bytes(tmp_path):
    env = {**os.environ, CACHE_ENV: str(tmp_path)}
    cold, warm = (subprocess.run([sys.executable, "-c", RUN], env=env, capture_output=True, text=True, check=True).stdout.split()[-1] for _ in range(2))
    entries = [p.name for p in next(tmp_path.glob("jax-*")).iterdir()]
    assert any(name.startswith("jit_iteration-") for name in entries)  # the iteration was written, then read
    assert cold == warm and len(cold) == 64
