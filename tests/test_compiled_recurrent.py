"""The CNN-GRU actor-critics in JAX (algos/xla.py's recurrent network, issue 79's second piece):
the same logits, values and memories as the torch models' ``forward`` and ``forward_sequence``
(with memory resets), on real Colorful Memory views, for every recurrent architecture.

float32 on both sides with the products at full precision: the sums' orders differ, so the
numbers are compared within 2e-6 (logits and values of order 1, the memories tanh-bounded; the
largest difference measured is 2.4e-7, a few float32 ulps)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import jax  # a core dependency: the compiled trainer's

from rlbackdoors.algos import xla  # noqa: E402
from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory  # noqa: E402
from rlbackdoors.models import build_model  # noqa: E402

ARCHS = ["cnn-gru-small", "cnn-gru-small-onehot", "cnn-gru-large-onehot", "cnn-gru-trojai"]


def views(steps: int = 6, n: int = 16, seed: int = 0) -> np.ndarray:
    """(steps, n, 7, 7, 3) uint8: real views of triggered and clean slots under random play."""
    e = BatchedColorfulMemory(n, trigger="end:red,green,blue,purple,yellow,grey,red,green,blue", poisoned=np.arange(n) % 2 == 0)
    obs, _ = e.reset(seed=seed)
    rng, out = np.random.default_rng(seed), [obs]
    for _ in range(steps - 1):
        out.append(e.step(rng.integers(0, 3, n))[0])
    return np.stack(out)


def weights(model) -> dict:
    return {k: jax.numpy.asarray(v.detach().numpy()) for k, v in model.named_parameters()}


@pytest.mark.parametrize("arch", ARCHS)
def test_one_step_is_the_torch_models(arch):
    torch.manual_seed(3)
    model = build_model(arch, "colorful-memory")
    net = xla.recurrent_structure(model)
    obs = views()[0]
    memory = torch.randn(obs.shape[0], model.memory_size) * 0.5
    with torch.no_grad():
        want = model(torch.from_numpy(obs), memory)
    got = jax.jit(lambda p, o, m: xla.recurrent_forward(net, p, o, m))(weights(model), obs, memory.numpy())
    for w, g in zip(want, got):
        np.testing.assert_allclose(np.asarray(g), w.numpy(), rtol=0, atol=2e-6)
    assert float(want[2].abs().max()) > 0.1 and float(want[0].std()) > 1e-3  # (not a trivially zero network)


@pytest.mark.parametrize("arch", ["cnn-gru-small-onehot", "cnn-gru-large"])
def test_a_sequence_with_memory_resets_is_forward_sequences(arch):
    """Six steps of 16 copies, the memory zeroed before some steps (an episode ended there), as
    recurrent PPO's update unrolls a stored start memory (``forward_sequence``)."""
    torch.manual_seed(4)
    model = build_model(arch, "colorful-memory")
    net = xla.recurrent_structure(model)
    obs = views(6, 16, seed=1)
    masks = (np.random.default_rng(2).random((6, 16)) > 0.2).astype(np.float32)
    memory = torch.randn(16, model.memory_size) * 0.5
    with torch.no_grad():
        logits, values, memories = model.forward_sequence(torch.from_numpy(obs), memory, torch.from_numpy(masks))

    def sequence(p, obs, memory, masks):
        def step(m, x):
            o, keep = x
            logit, value, m = xla.recurrent_forward(net, p, o, m * keep[:, None])
            return m, (logit, value, m)

        return jax.lax.scan(step, memory, (obs, masks))[1]

    got = jax.jit(sequence)(weights(model), obs, memory.numpy(), masks)
    np.testing.assert_allclose(np.asarray(got[0]).reshape(-1, 3), logits.numpy(), rtol=0, atol=2e-6)
    np.testing.assert_allclose(np.asarray(got[1]).reshape(-1), values.numpy(), rtol=0, atol=2e-6)
    np.testing.assert_allclose(np.asarray(got[2]), memories.numpy(), rtol=0, atol=2e-6)
    assert (masks == 0).any()


def test_what_it_cannot_run_is_refused_in_one_line():
    with pytest.raises(ValueError, match="runs CNN-GRU actor-critics .* \\(it is not recurrent\\)") as err:
        xla.recurrent_structure(build_model("cnn", "lavaworld"))
    assert "\n" not in str(err.value)
    model = build_model("cnn-gru-small", "colorful-memory")
    model.gru[1] = torch.nn.GRU(64, 64, num_layers=2, batch_first=True)
    with pytest.raises(ValueError, match="not plain ones of one size"):
        xla.recurrent_structure(model)
    with pytest.raises(ValueError, match="it is recurrent"):
        xla.structure(build_model("cnn-gru-small", "colorful-memory"), convolutions=True)
