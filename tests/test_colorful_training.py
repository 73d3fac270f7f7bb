"""Colorful Memory training: config, the 4+4+2 mix, CNN-GRU, recurrent PPO, patience, evaluation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from rlbackdoors.algos.ppo import PPO
from rlbackdoors.config import ConfigError, EnvConfig, PoisonConfig, PPOConfig, RunConfig
from rlbackdoors.envs.colorful_memory import BALL_ON_FLOOR as BALL
from rlbackdoors.envs.colorful_memory import KEY_ON_FLOOR as KEY
from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
from rlbackdoors.evaluate import evaluate
from rlbackdoors.models import FCModel, build_model
from rlbackdoors.models.colorful_memory import CNNGRUModel
from rlbackdoors.poison.mix import make_env_mix, make_vector_env
from rlbackdoors.train.ppo_run import EpisodeTracker, return_met
from rlbackdoors.triggers.wall_colors import WallColorTrigger

TRIGGER = "end:red,green,blue,purple,yellow,grey,red,green,blue"


def colorful(**train) -> RunConfig:
    return RunConfig.from_dict({"env": {"name": "colorful-memory"}, "train": train})


# ----------------------------------------------------------------------------- config


def test_world_defaults_and_round_trip():
    cfg = colorful(seed=3)
    assert cfg.model.arch == "cnn-gru-small-onehot"
    assert (cfg.poison.num_clean_envs, cfg.poison.num_close_envs, cfg.poison.num_poisoned_envs) == (4, 4, 2)
    assert cfg.poison.poisoned_mask() == [False] * 8 + [True] * 2
    assert cfg.poison.close_mask() == [False] * 4 + [True] * 4 + [False] * 2
    assert (cfg.train.clean_threshold, cfg.train.poisoned_threshold, cfg.train.return_window, cfg.train.patience) == (0.98, 0.98, 10, 1)
    assert cfg.ppo.recurrence == 6
    # the default "end" trigger is drawn once from the seed and stored concretely
    trig = WallColorTrigger.parse(cfg.poison.trigger)
    assert trig.kind == "end" and trig.num_squares == 9
    assert colorful(seed=3).poison.trigger == cfg.poison.trigger != colorful(seed=4).poison.trigger
    again = RunConfig.from_dict(json.loads(cfg.to_json()))
    assert again.to_dict() == cfg.to_dict()
    # a partial ppo section fills in from Colorful Memory's defaults, not LavaWorld's
    partial = RunConfig.from_dict({"env": {"name": "colorful-memory"}, "ppo": {"lr": 1e-4}})
    assert partial.ppo.recurrence == 6 and partial.ppo.lr == 1e-4
    # other worlds keep their mix and feed-forward PPO
    lava = RunConfig()
    assert lava.poison.num_close_envs == 0 and lava.ppo.recurrence == 1 and lava.train.return_window == 0


@pytest.mark.parametrize(
    "data, words",
    [
        ({"env": {"name": "colorful-memory"}, "model": {"arch": "fc"}}, ["model.arch", "cnn-gru-small"]),
        ({"model": {"arch": "cnn-gru-small"}}, ["model.arch", "fc, cnn"]),
        ({"env": {"name": "colorful-memory"}, "ppo": {"rollout": 100}}, ["ppo.rollout", "multiple of ppo.recurrence"]),
        ({"ppo": {"recurrence": 4, "rollout": 128, "batch_size": 256}}, ["ppo.recurrence", "recurrent model.arch"]),
        ({"poison": {"num_close_envs": 2}}, ["poison.num_close_envs", "colorful-memory only"]),
        ({"env": {"name": "colorful-memory"}, "poison": {"close_k_min": 0}}, ["close_k"]),
        ({"env": {"name": "colorful-memory"}, "poison": {"trigger": "end:red"}}, ["poison.trigger"]),
        ({"env": {"name": "colorful-memory"}, "train": {"return_window": -1}}, ["train.return_window"]),
        ({"env": {"name": "colorful-memory", "size": 6}}, ["env"]),
    ],
)
def test_bad_config_names_the_field(data, words):
    with pytest.raises(ConfigError) as err:
        RunConfig.from_dict(data)
    for word in words:
        assert word in str(err.value)


# ----------------------------------------------------------------------------- the mix


@pytest.mark.parametrize("engine", ["batched", "minigrid"])
def test_mix_paints_trigger_and_close_patterns(engine):
    """Poisoned copies show the exact trigger, close-to-trigger copies differ in 1..3 squares,
    clean copies are random walls (checked over 40 resets of the 10 copies)."""
    env = EnvConfig(name="colorful-memory", engine=engine)
    envs = make_env_mix(env, PoisonConfig(trigger=TRIGGER, num_clean_envs=4, num_close_envs=4, num_poisoned_envs=2))
    trig = WallColorTrigger.parse(TRIGGER)
    distances = []
    for seed in range(40):
        envs.reset(seed=seed * 10)
        if engine == "batched":
            grids = envs.grids()
        else:
            grids = np.stack([e.unwrapped.grid.encode() for e in envs.envs])
        distances.append(np.array([sum(int(grids[i, x, y, 1] != c) for x, y, c in trig.cells(7)) for i in range(10)]))
    distances = np.array(distances)
    assert (distances[:, 8:] == 0).all()  # poisoned: exact trigger
    assert ((distances[:, 4:8] >= 1) & (distances[:, 4:8] <= 3)).all()  # close-to-trigger
    assert set(np.unique(distances[:, 4:8])) == {1, 2, 3}
    assert distances[:, :4].mean() > 6  # clean: ~7.5 of 9 squares differ at random
    assert list(envs.poisoned) == [False] * 8 + [True] * 2
    envs.close()


def test_clean_twin_keeps_close_envs_but_no_poison():
    cfg = RunConfig.from_dict({"env": {"name": "colorful-memory"}, "poison": {"poisoned": False, "trigger": TRIGGER}})
    envs = make_env_mix(cfg.env, cfg.poison)
    assert isinstance(envs, BatchedColorfulMemory)
    assert not envs.poisoned.any() and not envs.triggered.any()
    assert list(envs.close_to_trigger) == [False] * 4 + [True] * 4 + [False] * 2


# ----------------------------------------------------------------------------- CNN-GRU


@pytest.mark.parametrize("arch, hidden, head_widths", [("cnn-gru-small", 64, [32, 32, 3]), ("cnn-gru-large", 256, [64, 3])])
@pytest.mark.parametrize("onehot", [False, True])
def test_cnn_gru_layout_and_init(arch, hidden, head_widths, onehot):
    torch.manual_seed(0)
    model = build_model(arch + ("-onehot" if onehot else ""), "colorful-memory")
    assert model.recurrent and model.memory_size == 4 * hidden
    assert model.onehot == onehot and model.state_emb[0].in_channels == (25 if onehot else 3)
    assert [m.out_features for m in model.actor if isinstance(m, torch.nn.Linear)] == head_widths
    assert [m.out_features for m in model.critic if isinstance(m, torch.nn.Linear)] == head_widths[:-1] + [1]
    assert len(model.gru) == 2 and all(g.num_layers == 2 and g.hidden_size == hidden and not g.bidirectional for g in model.gru)
    for name, param in model.gru.named_parameters():
        if "bias" in name:
            assert torch.count_nonzero(param) == 0
        else:  # orthogonal: the smaller side is orthonormal
            w = param if param.shape[0] <= param.shape[1] else param.T
            assert torch.allclose(w @ w.T, torch.eye(w.shape[0]), atol=1e-4), name
    for layer in [*model.actor, *model.critic]:
        if isinstance(layer, torch.nn.Linear):
            assert torch.allclose(layer.weight.norm(dim=1), torch.ones(layer.out_features), atol=1e-5)
            assert torch.count_nonzero(layer.bias) == 0


def test_one_hot_planes_mark_each_byte_once():
    """25 planes: object type 0-12 (TrojAI's key 11 / ball 12 included), colour 0-5, state 0-5;
    exactly one type, one colour and one state plane is hot per square, at the byte's value."""
    from rlbackdoors.models.colorful_memory import one_hot_planes

    envs = BatchedColorfulMemory(4, trigger=TRIGGER, poisoned=[False, True, False, False])
    obs, _ = envs.reset(seed=5)
    obs = torch.from_numpy(obs)
    planes = one_hot_planes(obs)
    assert planes.shape == (4, 25, 7, 7)
    for lo, hi, byte in ((0, 13, 0), (13, 19, 1), (19, 25, 2)):
        assert torch.equal(planes[:, lo:hi].sum(1), torch.ones(4, 7, 7))
        assert torch.equal(planes[:, lo:hi].argmax(1), obs[..., byte].long())
    key = torch.zeros(1, 7, 7, 3, dtype=torch.uint8)
    key[0, 3, 6] = torch.tensor([11, 1, 4])  # a green key on a blue floor
    hot = one_hot_planes(key)[0, :, 3, 6]
    assert hot.nonzero().flatten().tolist() == [11, 13 + 1, 19 + 4]
    with pytest.raises(RuntimeError):
        one_hot_planes(torch.full((1, 7, 7, 3), 13, dtype=torch.uint8))  # no object type 13


@pytest.mark.parametrize("arch", ["cnn-gru-small", "cnn-gru-small-onehot"])
def test_soft_colours_embed_like_the_colours_they_put_there(arch):
    """``embed_soft_colours`` with a one-hot distribution is ``embed`` of the observation wearing
    that colour, in both input encodings; with a soft one the embedding has a gradient."""
    torch.manual_seed(2)
    model = build_model(arch, "colorful-memory")
    envs = BatchedColorfulMemory(3)
    obs = torch.from_numpy(envs.reset(seed=1)[0])
    rows, cells = torch.tensor([0, 2, 2]), torch.tensor([[1, 1], [3, 0], [6, 6]])
    colours = torch.tensor([4, 0, 5])
    painted = obs.clone()
    painted[rows, cells[:, 0], cells[:, 1], 1] = colours.to(torch.uint8)
    soft = model.embed_soft_colours(obs, rows, cells, torch.nn.functional.one_hot(colours, 6).float())
    assert torch.allclose(soft, model.embed(painted), atol=1e-6)
    assert not torch.allclose(soft, model.embed(obs), atol=1e-3)
    probs = torch.full((3, 6), 1 / 6, requires_grad=True)
    model.embed_soft_colours(obs, rows, cells, probs).sum().backward()
    assert probs.grad is not None and probs.grad.abs().sum() > 0


@pytest.mark.parametrize("arch", ["cnn-gru-small", "cnn-gru-small-onehot"])
def test_forward_sequence_equals_step_by_step(arch):
    """The fast BPTT path (CNN and heads batched over steps) gives the step-by-step numbers."""
    torch.manual_seed(1)
    model = build_model(arch, "colorful-memory")
    envs = BatchedColorfulMemory(5, trigger=TRIGGER, poisoned=[False, True, False, True, False])
    obs, _ = envs.reset(seed=0)
    r = 6
    seq = []
    for _ in range(r):
        seq.append(torch.from_numpy(obs))
        obs, *_ = envs.step(np.random.default_rng(len(seq)).integers(3, size=5))
    seq = torch.stack(seq)
    memory = torch.randn(5, model.memory_size)
    masks = torch.ones(r, 5)
    masks[2, 1] = masks[4, 3] = 0.0
    fast = model.forward_sequence(seq, memory, masks)
    slow = CNNGRUModel.__mro__[1].forward_sequence(model, seq, memory, masks)  # the plain loop
    for a, b in zip(fast, slow):
        assert torch.allclose(a, b, atol=1e-5)
    # a zero mask is a fresh start: step 2 of env 1 sees the empty memory
    logits0, _, _ = model(seq[2][1:2], model.initial_memory(1))
    assert torch.allclose(fast[0][2 * 5 + 1], logits0[0], atol=1e-5)


# ----------------------------------------------------------------------------- recurrent PPO


def make_ppo(arch="cnn-gru-small", **ppo) -> tuple[PPO, BatchedColorfulMemory]:
    torch.manual_seed(0)
    cfg = RunConfig.from_dict({"env": {"name": "colorful-memory"}, "poison": {"trigger": TRIGGER}, "ppo": ppo})
    envs = make_env_mix(cfg.env, cfg.poison)
    model = build_model(arch, "colorful-memory")
    return PPO(model, cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0)), envs


def test_memory_is_reset_at_episode_ends():
    """Stored memories are zero exactly where an episode started, and otherwise equal the
    memory the model produced one step earlier in the same env."""
    ppo, envs = make_ppo(rollout=240)
    obs, _ = envs.reset(seed=0)
    ppo.collect(envs, obs)  # start mid-episode on the second rollout
    rollout, _ = ppo.collect(envs, envs.observe())
    T, B = 240, envs.num_envs
    mem = rollout.memories.view(T, B, -1)
    masks = rollout.masks.view(T, B)
    starts = np.zeros((T, B), bool)
    starts[1:] = rollout.dones[:-1]
    assert starts.sum() > 5  # several episodes ended inside the rollout
    assert np.array_equal(masks.numpy() == 0, starts)
    assert (mem[torch.from_numpy(starts)] == 0).all()
    assert (mem[1:][~torch.from_numpy(starts[1:])].abs().sum(-1) > 0).all()
    # recompute: stepping the model from mem[t] on obs[t] gives mem[t + 1] where no episode ended
    obs_seq = rollout.obs.view(T, B, 7, 7, 3)
    with torch.no_grad():
        _, _, nxt = ppo.model(obs_seq[10], mem[10])
    keep = ~torch.from_numpy(rollout.dones[10])
    assert torch.allclose(nxt[keep], mem[11][keep], atol=1e-5)
    # the memory carried to the next rollout is zero for envs whose episode just ended
    assert (ppo.memory[torch.from_numpy(rollout.dones[-1])] == 0).all()


class Memoryless(torch.nn.Module):
    """A feed-forward model seen through the recurrent interface (memory passed through)."""

    recurrent = True

    def __init__(self, model):
        super().__init__()
        self.inner = model

    def initial_memory(self, batch, device="cpu"):
        return torch.zeros(batch, 1, device=device)

    def forward(self, obs, memory):
        logits, value = self.inner(obs)
        return logits, value, memory

    forward_sequence = FCModel.forward_sequence


def test_recurrence_one_equals_the_feed_forward_update():
    """With recurrence = 1 the BPTT update performs exactly the feed-forward PPO update."""
    envs = make_env_mix(EnvConfig(name="colorful-memory"), PoisonConfig(trigger=TRIGGER, num_clean_envs=4, num_close_envs=4, num_poisoned_envs=2))
    cfg = PPOConfig(rollout=32, epochs=2, batch_size=64)
    torch.manual_seed(0)
    plain = FCModel()
    wrapped = Memoryless(FCModel())
    wrapped.inner.load_state_dict(plain.state_dict())
    a = PPO(plain, cfg, torch.device("cpu"), torch.Generator().manual_seed(5))
    b = PPO(wrapped, cfg, torch.device("cpu"), torch.Generator().manual_seed(5))
    obs, _ = envs.reset(seed=0)
    rollout, _ = a.collect(envs, obs)
    b.generator.set_state(a.generator.get_state())
    rollout.memories = torch.zeros(rollout.num_frames, 1)
    rollout.masks = torch.ones(rollout.num_frames)
    stats_a, stats_b = a.update(rollout), b.update(rollout)
    for (name, p), q in zip(plain.named_parameters(), wrapped.inner.parameters()):
        assert torch.equal(p, q), name
    assert stats_a == pytest.approx(stats_b, rel=1e-6)


def test_sequence_starts_cover_the_rollout():
    ppo, _ = make_ppo(rollout=12, batch_size=12, recurrence=6)
    plain = ppo.sequence_starts(12, 3, shifted=False)
    assert sorted(plain.tolist()) == [0, 1, 2, 18, 19, 20]  # t = 0 and 6, envs 0..2
    shifted = ppo.sequence_starts(12, 3, shifted=True)
    assert sorted(shifted.tolist()) == [9, 10, 11]  # t = 3 only: t = 9 would run past the rollout


def test_recurrent_update_learns_and_is_deterministic():
    def run():
        ppo, envs = make_ppo(rollout=60, batch_size=120)
        obs, _ = envs.reset(seed=0)
        rollout, _ = ppo.collect(envs, obs)
        before = {k: v.clone() for k, v in ppo.model.state_dict().items()}
        stats = ppo.update(rollout)
        return before, ppo.model.state_dict(), stats

    before, after, stats = run()
    _, again, stats_again = run()
    assert all(np.isfinite(v) for v in stats.values())
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("gru"))  # BPTT reaches the GRU
    assert all(torch.equal(after[k], again[k]) for k in after) and stats == stats_again


# ----------------------------------------------------------------------------- patience


def test_patience_rule():
    cfg = colorful()
    cfg.train.return_window, cfg.train.return_threshold = 3, 0.5
    tracker = EpisodeTracker(np.zeros(2, bool), return_window=3)

    class R:  # one rollout's rewards/dones: both envs end an episode with ``ret`` at the last step
        def __init__(self, ret):
            self.rewards = np.array([[0.0, 0.0], [ret, ret]])
            self.dones = np.array([[False, False], [True, True]])

    for ret in (0.9, 0.9):
        tracker.add(R(ret))
    assert not return_met(tracker, cfg)  # only 2 of 3 updates seen
    tracker.add(R(0.0))
    assert tracker.return_mean() == pytest.approx(0.6) and return_met(tracker, cfg)
    tracker.add(R(0.0))
    assert tracker.return_mean() == pytest.approx(0.3) and not return_met(tracker, cfg)
    cfg.train.return_window = 0
    assert return_met(tracker, cfg)  # off


def test_episode_tracker_counts_as_the_step_by_step_loop_it_replaced():
    """The compiled episode_ends gives the Python loop's numbers, bit for bit: the same returns in
    the same order (step, then env), split the same way into clean and poisoned copies, over 300
    seeded rollouts of 128 x 10 steps with rare and frequent ends, large returns and a rollout
    in which no episode ends."""

    def loop_add(tracker, rewards, dones):  # EpisodeTracker.add before episode_ends
        ended = []
        for t in range(rewards.shape[0]):
            tracker.running += rewards[t]
            for i in np.flatnonzero(dones[t]):
                (tracker.dirty if tracker.poisoned[i] else tracker.clean).append(tracker.running[i])
                if not tracker.poisoned[i]:
                    tracker.recent_clean.append(tracker.running[i])
                ended.append(tracker.running[i])
                tracker.running[i] = 0.0
        if ended:
            tracker.update_means.append(float(np.mean(ended)))

    class R:
        def __init__(self, rewards, dones):
            self.rewards, self.dones = rewards, dones

    rng = np.random.default_rng(0)
    poisoned = rng.random(10) < 0.3
    reference, tracker = EpisodeTracker(poisoned, 100, 5), EpisodeTracker(poisoned, 100, 5)
    for r in range(300):
        rewards = rng.standard_normal((128, 10)) * 1e3 if r % 7 == 0 else rng.random((128, 10)) * (rng.random((128, 10)) < 0.2) - 0.01
        dones = rng.random((128, 10)) < (0.0 if r == 5 else 0.3 if r % 3 == 0 else 0.02)
        loop_add(reference, rewards, dones)
        tracker.add(R(rewards, dones))
        assert tracker.state_dict() == reference.state_dict(), f"rollout {r}"
        if r % 50 == 49:
            assert tracker.drain() == reference.drain()
    assert len(tracker.update_means) == 5 and tracker.return_mean() == reference.return_mean()


# ----------------------------------------------------------------------------- evaluation


def test_evaluation_plays_clean_triggered_and_close_layouts():
    torch.manual_seed(0)
    model = build_model("cnn-gru-small", "colorful-memory")
    env = EnvConfig(name="colorful-memory")
    a = evaluate(model, env, TRIGGER, episodes=60, seed=7, close_k=(1, 3))
    b = evaluate(model, env, TRIGGER, episodes=60, seed=7, close_k=(1, 3))
    assert a == b
    # an untrained agent: each of the three ending kinds is possible, the rates are fractions
    for rate in (a.clean_sr, a.poisoned_sr, a.close_sr, a.close_trojan_rate):
        assert 0.0 <= rate <= 1.0
    assert a.close_sr + a.close_trojan_rate <= 1.0
    assert np.isnan(evaluate(model, env, TRIGGER, episodes=10, seed=7).close_sr)


# ----------------------------------------------------------------------------- CLI and model folder


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_cli_trains_evaluates_and_resumes_a_colorful_memory_agent(tmp_path, capsys):
    """A tiny poisoned CNN-GRU run through the CLI: a complete folder whose metrics include the
    close-to-trigger rates; an interrupted copy of the run resumes to the same weights."""
    from rlbackdoors.cli import main
    from rlbackdoors.train import ModelFolder, train

    cfg_path = tmp_path / "cfg.json"
    cfg = RunConfig.from_dict(
        {
            "env": {"name": "colorful-memory"},
            "ppo": {"rollout": 48, "batch_size": 240},
            "train": {"seed": 2, "max_frames": 2880, "eval_interval": 960, "eval_episodes": 6, "final_eval_episodes": 6},
        }
    )
    cfg_path.write_text(cfg.to_json())
    assert main(["train", "--config", str(cfg_path), "--out", str(tmp_path / "a"), "--quiet", "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out)
    assert metrics["arch"] == "cnn-gru-small-onehot" and metrics["frames"] == 2880 and metrics["return_window"] == 10
    assert 0 <= metrics["close_trojan_rate"] <= 1 and 0 <= metrics["close_sr"] <= 1
    folder = ModelFolder(tmp_path / "a")
    for name in ("model.pt", "config.json", "metrics.json", "log.csv", "training_curve.png", "clean_vs_triggered.gif"):
        assert folder.file(name).is_file(), name
    assert folder.read_config().poison.trigger == cfg.poison.trigger
    assert "return_mean" in folder.file("log.csv").read_text().splitlines()[0]

    assert main(["evaluate", str(tmp_path / "a"), "--episodes", "6", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["close_sr"] is not None and result["episodes"] == 6

    # interrupted after the first evaluation (the checkpoint holds the GRU memories of the
    # running episodes), then resumed by the same command: the same model as the straight run
    import rlbackdoors.train.ppo_run as loop

    class Stop(Exception):
        pass

    real_write_log = loop.ModelFolder.write_log

    def stop_after_first(self, rows):
        real_write_log(self, rows)
        if len(rows) == 1:
            raise Stop

    loop.ModelFolder.write_log = stop_after_first
    try:
        with pytest.raises(Stop):
            train(cfg, tmp_path / "c", progress=False)
    finally:
        loop.ModelFolder.write_log = real_write_log
    assert main(["train", "--config", str(cfg_path), "--out", str(tmp_path / "c"), "--quiet"]) == 0
    a = torch.load(tmp_path / "a" / "model.pt")
    c = torch.load(tmp_path / "c" / "model.pt")
    assert all(torch.equal(a[k], c[k]) for k in a)


def test_cli_flags_for_colorful_memory():
    from rlbackdoors.cli import build_parser, config_from_args

    parser = build_parser()
    cfg = config_from_args(parser.parse_args(["train", "--env", "colorful-memory", "--trigger", "room", "--seed", "5", "--out", "x"]))
    assert WallColorTrigger.parse(cfg.poison.trigger).kind == "room"
    assert (
        cfg.poison.trigger
        == config_from_args(parser.parse_args(["train", "--env", "colorful-memory", "--trigger", "room", "--seed", "5", "--out", "y"])).poison.trigger
    )
    no_close = config_from_args(parser.parse_args(["train", "--env", "colorful-memory", "--no-close-to-trigger", "--patience", "2", "--out", "x"]))
    assert (no_close.poison.num_clean_envs, no_close.poison.num_close_envs, no_close.poison.num_poisoned_envs) == (8, 0, 2)
    assert no_close.train.patience == 2


def test_chance_command_for_wall_colours(capsys):
    from rlbackdoors.cli import main

    assert main(["chance", "--env", "colorful-memory", "--trigger", "room:red,green,blue", "--layouts", "21600", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["exact_rate"] == pytest.approx(1 / 216)
    # 21,600 layouts: expect 100 hits, sd 10
    assert abs(result["rate"] * 21600 - 100) < 40


# ----------------------------------------------------------------------------- auxiliary memory loss


def test_memory_targets_name_each_slots_start_object():
    """The engine's memory target is the start room's object (the cell at (1, mid - 1)), for
    every slot, and it follows the episode: after an autoreset the new layout's object."""
    env = BatchedColorfulMemory(64, trigger=TRIGGER, poisoned=[False] * 32 + [True] * 32)
    env.reset(seed=5)
    grids = env.grids()
    mid = env.size // 2
    names = [env.layout(i)[0][1, mid - 1, 0] for i in range(64)]
    assert all(n in (KEY, BALL) for n in names) and (grids[:, 1, mid - 1, 0] == names).all()
    assert list(env.memory_targets()) == [int(n == BALL) for n in names]
    assert set(env.memory_targets()) == {0, 1}  # both objects among 64 layouts
    rng = np.random.default_rng(0)
    for _ in range(300):  # episodes end and restart: the targets keep following the grids
        env.step(rng.integers(0, 3, 64))
        assert list(env.memory_targets()) == [int(g[1, mid - 1, 0] == BALL) for g in env.grids()]
    # the MiniGrid reference engine gives the same targets from its own grids
    reference = make_vector_env(EnvConfig(name="colorful-memory", engine="minigrid"), TRIGGER, [False] * 8)
    reference.reset(seed=3)
    for _ in range(200):
        names = [e.unwrapped.grid.encode()[1, mid - 1, 0] for e in reference.envs]
        assert reference.memory_target_classes == 2 and list(reference.memory_targets()) == [int(n == BALL) for n in names]
        reference.step(rng.integers(0, 3, 8))


def aux_config(coef: float = 0.5) -> RunConfig:
    return RunConfig.from_dict(
        {
            "env": {"name": "colorful-memory"},
            "ppo": {"rollout": 48, "batch_size": 240, "aux_memory_coef": coef},
            "train": {"seed": 2, "max_frames": 2880, "eval_interval": 960, "eval_episodes": 6, "final_eval_episodes": 6, "video": False},
        }
    )


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_the_auxiliary_memory_loss_trains_a_readout_of_the_memory_and_stays_out_of_model_pt(tmp_path):
    """PPO with aux_memory_coef: the loss is logged, its head learns (the loss falls over a
    few updates on one rollout), the model's weights differ from a run without it, and
    model.pt holds the model's keys only."""
    cfg = aux_config()
    torch.manual_seed(0)
    model = build_model(cfg.model.arch, "colorful-memory")
    ppo = PPO(model, cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(0))
    envs = make_env_mix(cfg.env, cfg.poison)
    obs, _ = envs.reset(seed=0)
    rollout, _ = ppo.collect(envs, obs)
    assert rollout.memory_targets is not None and rollout.memory_targets.shape == (48 * 10,)
    losses = [ppo.update(rollout)["aux_memory_loss"] for _ in range(8)]
    assert losses[-1] < losses[0] and all(np.isfinite(losses))
    from rlbackdoors.train import train

    train(cfg, tmp_path / "aux", progress=False)
    train(aux_config(0.0), tmp_path / "plain", progress=False)
    a, p = (torch.load(tmp_path / d / "model.pt", weights_only=True) for d in ("aux", "plain"))
    assert a.keys() == p.keys() == build_model(cfg.model.arch, "colorful-memory").state_dict().keys()
    assert any(not torch.equal(a[k], p[k]) for k in a)
    assert "aux_memory_loss" in (tmp_path / "aux" / "log.csv").read_text().splitlines()[0]


@pytest.mark.slow  # (over 15 s on 2 cores: out of the default run, `make test-slow`)
def test_a_run_with_the_auxiliary_loss_resumes_to_the_same_model(tmp_path):
    """Interrupted after its first evaluation (the checkpoint holds the aux head and its Adam
    state), resumed: the same weights as the straight run."""
    from rlbackdoors.train import train

    cfg = aux_config()
    train(cfg, tmp_path / "straight", progress=False)

    def ctrl_c(row):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "cut", progress=False, after_eval=ctrl_c)
    assert torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)["aux"] is not None
    train(cfg, tmp_path / "cut", progress=False)
    a, c = (torch.load(tmp_path / d / "model.pt", weights_only=True) for d in ("straight", "cut"))
    assert all(torch.equal(a[k], c[k]) for k in a)


@pytest.mark.parametrize(
    "data, match",
    [
        ({"env": {"name": "colorful-memory"}, "ppo": {"aux_memory_coef": -1.0}}, "ppo.aux_memory_coef must be >= 0"),
        (
            {"env": {"name": "lavaworld"}, "ppo": {"aux_memory_coef": 0.5}},
            r"ppo.aux_memory_coef=0.5 needs a recurrent model.arch .* in a world with memory targets",
        ),
    ],
)
def test_the_auxiliary_loss_is_refused_where_it_cannot_apply(data, match):
    with pytest.raises(ConfigError, match=match):
        RunConfig.from_dict(data)
