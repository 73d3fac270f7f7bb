"""OPAC²'s optional observation standardisation: statistics, use in act/update, checkpoints."""

import io

import numpy as np
import pytest
import torch

from rlbackdoors.io import torch_bytes
from rlbackdoors.algos.opac2 import OPAC2, MultitaskReplay, OPAC2Config, RunningNorm
from rlbackdoors.validate import ConfigError

OBS, ACT = 5, 2


def test_running_norm_matches_numpy_over_uneven_batches():
    rng = np.random.default_rng(0)
    data = rng.normal(loc=[0, 9.8, -3, 0, 100], scale=[1, 4, 0.01, 0.1, 30], size=(1000, OBS))
    norm = RunningNorm(OBS, clip=100.0)
    x = np.ones((2, OBS), np.float32)
    np.testing.assert_array_equal(norm(x), x)  # identity before any data
    for chunk in np.split(data, [1, 7, 300, 301, 999]):
        norm.update(chunk)
    assert norm.count == 1000
    np.testing.assert_allclose(norm.mean, data.mean(0), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(norm.std, np.sqrt(data.var(0) + 1e-8), rtol=1e-10)
    z = norm(data)
    assert z.dtype == np.float32
    np.testing.assert_allclose(z.mean(0), 0, atol=1e-5)
    np.testing.assert_allclose(z.std(0), 1, atol=1e-4)
    clipped = RunningNorm(OBS, clip=2.0)
    clipped.update(data)
    assert np.abs(clipped(data)).max() == pytest.approx(2.0)


def test_agent_standardises_in_act_and_update_and_checkpoints_the_statistics():
    cfg = OPAC2Config(depth=1, width=16, batch_size=32, obs_norm=True)
    agent = OPAC2(OBS, ACT, cfg, torch.Generator().manual_seed(0))
    rng = np.random.default_rng(1)
    obs = rng.normal(5.0, 3.0, size=(200, OBS))
    agent.observe(obs)
    # act() sees standardised input: feeding pre-standardised input to a plain agent with the same nets agrees.
    plain = OPAC2(OBS, ACT, OPAC2Config(depth=1, width=16, batch_size=32), torch.Generator().manual_seed(0))
    np.testing.assert_allclose(agent.act(obs[:4], deterministic=True), plain.act(agent.obs_norm(obs[:4]), deterministic=True), atol=1e-6)
    assert not np.allclose(agent.act(obs[:4], deterministic=True), plain.act(obs[:4], deterministic=True))

    replay = MultitaskReplay.create({"clean": 1.0}, 500, OBS, ACT)
    replay["clean"].add_batch(obs, rng.uniform(-1, 1, (200, ACT)), rng.normal(size=200), obs[::-1], np.zeros(200))
    batch = agent.batch_tensors(replay.sample(64, np.random.default_rng(2)))
    assert abs(float(batch.obs.mean())) < 0.5 and abs(float(batch.next_obs.std()) - 1) < 0.3
    agent.update(replay, np.random.default_rng(3))

    state = torch.load(io.BytesIO(torch_bytes(agent.state_dict())), weights_only=True)  # as a checkpoint holds it
    other = OPAC2(OBS, ACT, cfg, torch.Generator().manual_seed(9))
    other.load_state_dict(state)
    np.testing.assert_array_equal(other.obs_norm.mean, agent.obs_norm.mean)
    np.testing.assert_array_equal(other.act(obs[:3], deterministic=True), agent.act(obs[:3], deterministic=True))
    plain.observe(obs)  # a no-op without obs_norm
    assert plain.obs_norm is None and plain.state_dict()["obs_norm"] is None


def test_obs_norm_fields_are_checked():
    with pytest.raises(ConfigError, match="opac2.obs_norm must be true or false"):
        OPAC2Config(obs_norm=1).check()
    with pytest.raises(ConfigError, match="opac2.obs_clip"):
        OPAC2Config(obs_clip=0.0).check()
