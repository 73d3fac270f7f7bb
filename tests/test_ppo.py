import pytest
import torch

from rlbackdoors.algos.ppo import PPO, gae, sample_actions
from rlbackdoors.config import EnvConfig, PoisonConfig, PPOConfig
from rlbackdoors.evaluate import evaluate
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_env_mix


def test_sample_actions_follows_the_distribution():
    logits = torch.log(torch.tensor([[0.2, 0.5, 0.3]])).repeat(60_000, 1)
    g = torch.Generator().manual_seed(0)
    counts = torch.bincount(sample_actions(logits, g), minlength=3).float() / 60_000
    assert torch.allclose(counts, torch.tensor([0.2, 0.5, 0.3]), atol=0.01)  # 60k draws: sd ~0.002


def test_gae_matches_hand_computation():
    rewards = torch.tensor([[1.0], [0.0], [2.0]])
    dones = torch.tensor([[False], [True], [False]])
    values = torch.tensor([[0.5], [1.0], [0.25]])
    adv = gae(rewards, dones, values, torch.tensor([4.0]), gamma=0.5, lam=0.5)
    a2 = 2.0 + 0.5 * 4.0 - 0.25  # 3.75
    a1 = 0.0 - 1.0  # episode ends after step 1: no bootstrap, no trace
    a0 = (1.0 + 0.5 * 1.0 - 0.5) + 0.25 * a1
    assert torch.allclose(adv[:, 0], torch.tensor([a0, a1, a2]))


def test_gae_of_a_group_is_each_learners_bytes():
    """A group's K learners in one (T, K, B) pass get exactly the advantages each gets alone."""
    g = torch.Generator().manual_seed(3)
    rewards, values = torch.rand((16, 3, 5), generator=g), torch.rand((16, 3, 5), generator=g)
    dones, next_value = torch.rand((16, 3, 5), generator=g) < 0.2, torch.rand((3, 5), generator=g)
    together = gae(rewards, dones, values, next_value, 0.99, 0.95)
    for k in range(3):
        assert torch.equal(together[:, k], gae(rewards[:, k], dones[:, k], values[:, k], next_value[k], 0.99, 0.95))


def test_rollout_shapes_and_update_reduces_loss():
    torch.manual_seed(0)
    envs = make_env_mix(EnvConfig(), PoisonConfig())
    ppo = PPO(build_model("fc"), PPOConfig(rollout=16, epochs=1), torch.device("cpu"), torch.Generator().manual_seed(0))
    obs, _ = envs.reset(seed=0)
    rollout, _ = ppo.collect(envs, obs)
    assert rollout.obs.shape == (160, 7, 7, 3) and rollout.num_frames == 160
    assert torch.allclose(rollout.returns, rollout.values + rollout.advantages)

    def value_error():
        with torch.no_grad():
            return ((ppo.model(rollout.obs)[1] - rollout.returns) ** 2).mean().item()

    before = value_error()
    for _ in range(5):
        ppo.update(rollout)
    assert value_error() < before  # fitting the same rollout repeatedly must fit its returns better


@pytest.mark.parametrize("arch", ["fc", "cnn"])
def test_ppo_learns_a_small_crossing(arch):
    """5x5 LavaWorld (one river, one gap), clean only: PPO must go from near-random to mostly solving it.

    100 evaluation episodes, fixed seeds; the threshold 0.8 sits far above a random walk (< 0.2).
    """
    torch.manual_seed(0)
    env = EnvConfig(size=5, max_steps=40)
    poison = PoisonConfig(poisoned=False, num_clean_envs=16, num_poisoned_envs=0)
    model = build_model(arch)
    before = evaluate(model, env, None, episodes=100, seed=123).clean_sr
    ppo = PPO(model, PPOConfig(rollout=64), torch.device("cpu"), torch.Generator().manual_seed(0))
    envs = make_env_mix(env, poison)
    obs, _ = envs.reset(seed=0)
    for _ in range(40):  # 41k frames
        rollout, obs = ppo.collect(envs, obs)
        ppo.update(rollout)
    after = evaluate(model, env, None, episodes=100, seed=123).clean_sr
    assert before < 0.3
    assert after >= 0.8


def test_ppo_runs_on_gymnasiums_own_vector_env_and_refuses_next_step_autoreset():
    """Any Gymnasium VectorEnv with SAME_STEP autoreset and a Discrete action space will do:
    here gymnasium's SyncVectorEnv over the registered LavaWorld id. NEXT_STEP autoreset (the
    default) would feed PPO a bogus transition after each episode end: refused by name."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode

    import rlbackdoors  # noqa: F401  (registers the ids)

    envs = gym.make_vec("rlbackdoors/LavaWorld-v0", num_envs=4, vectorization_mode="sync", vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})
    ppo = PPO(build_model("fc"), PPOConfig(rollout=64, batch_size=64), "cpu", torch.Generator().manual_seed(0))
    obs, _ = envs.reset(seed=0)
    rollout, obs = ppo.collect(envs, obs)
    losses = ppo.update(rollout)
    assert rollout.num_frames == 256 and all(map(lambda v: v == v, losses.values()))  # finite losses
    assert rollout.dones.any() and set(rollout.outcomes[rollout.dones].tolist()) <= {1, 2, 3}  # outcomes passed through
    envs.close()
    default = gym.make_vec("rlbackdoors/LavaWorld-v0", num_envs=2, vectorization_mode="sync")
    with pytest.raises(ValueError, match="SAME_STEP autoreset"):
        ppo.collect(default, default.reset(seed=0)[0])
    default.close()
