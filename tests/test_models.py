import pytest
import torch

from rlbackdoors.io import UnsafeFileError
from rlbackdoors.models import CNNModel, FCModel, build_model, load_weights

FC_SHAPES = {
    "state_emb.0.weight": (100, 147),
    "state_emb.0.bias": (100,),
    "state_emb.2.weight": (64, 100),
    "state_emb.2.bias": (64,),
    "actor.0.weight": (32, 64),
    "actor.0.bias": (32,),
    "actor.2.weight": (3, 32),
    "actor.2.bias": (3,),
    "critic.0.weight": (32, 64),
    "critic.0.bias": (32,),
    "critic.2.weight": (1, 32),
    "critic.2.bias": (1,),
}
CNN_SHAPES = {
    "state_emb.0.weight": (16, 3, 2, 2),
    "state_emb.0.bias": (16,),
    "state_emb.3.weight": (32, 16, 2, 2),
    "state_emb.3.bias": (32,),
    "state_emb.5.weight": (64, 32, 2, 2),
    "state_emb.5.bias": (64,),
    "actor.0.weight": (64, 64),
    "actor.0.bias": (64,),
    "actor.2.weight": (3, 64),
    "actor.2.bias": (3,),
    "critic.0.weight": (64, 64),
    "critic.0.bias": (64,),
    "critic.2.weight": (1, 64),
    "critic.2.bias": (1,),
}


@pytest.mark.parametrize("arch, shapes", [("fc", FC_SHAPES), ("cnn", CNN_SHAPES)])
def test_state_dict_layout_matches_trojai(arch, shapes):
    model = build_model(arch)
    assert {k: tuple(v.shape) for k, v in model.state_dict().items()} == shapes
    logits, value = model(torch.zeros(5, 7, 7, 3, dtype=torch.uint8))
    assert logits.shape == (5, 3) and value.shape == (5,)


def test_fc_flattens_channels_first():
    """Only input 0 of the first layer is weighted: that must be channel 0 at view (x=0, y=0),
    and input 49 must be channel 1 at (0, 0) — the TrojAI transpose(1,3).transpose(2,3) order."""
    model = FCModel()
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        model.state_emb[0].weight[0, 49] = 1.0  # channel 1, x 0, y 0
        model.state_emb[2].weight[0, 0] = 1.0
        model.critic[0].weight[0, 0] = 1.0
        model.critic[2].weight[0, 0] = 1.0
    obs = torch.zeros(1, 7, 7, 3, dtype=torch.uint8)
    obs[0, 0, 0, 1] = 7  # (x=0, y=0, colour channel)
    obs[0, 0, 1, 0] = 99  # somewhere the weight is zero
    _, value = model(obs)
    assert value.item() == pytest.approx(7.0)


def test_known_weights_forward_cnn():
    """All-ones conv kernels on an all-ones image: every number is computable by hand."""
    model = CNNModel()
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.fill_(1.0 if "state_emb" in name and "weight" in name else 0.0)
        model.critic[2].weight.fill_(1.0)
        model.actor[2].weight.fill_(0.0)
    obs = torch.ones(2, 7, 7, 3, dtype=torch.uint8)
    logits, value = model(obs)
    # conv1: 3*4 = 12 per unit; pool keeps 12; conv2: 16*4*12 = 768; conv3: 32*4*768 = 98304
    # critic hidden: tanh(0 * ...) = 0 since its weights are 0 -> value 0; logits 0.
    assert torch.allclose(logits, torch.zeros(2, 3)) and torch.allclose(value, torch.zeros(2))
    emb = model.embed(obs)
    assert emb.shape == (2, 64) and torch.allclose(emb, torch.full((2, 64), 98304.0))


def test_init_rows_have_unit_norm():
    model = FCModel()
    for layer in (model.state_emb[0], model.actor[2], model.critic[0]):
        assert torch.allclose(layer.weight.norm(dim=1), torch.ones(layer.weight.shape[0]), atol=1e-5)
        assert (layer.bias == 0).all()


def test_load_weights_round_trip_and_alias(tmp_path):
    src = build_model("cnn")
    state = {k.replace("state_emb.", "image_conv."): v for k, v in src.state_dict().items()}
    torch.save(state, tmp_path / "w.pt")
    dst = load_weights(build_model("cnn"), tmp_path / "w.pt")
    x = torch.randint(0, 11, (4, 7, 7, 3), dtype=torch.uint8)
    assert torch.equal(src(x)[0], dst(x)[0])
    torch.save(src, tmp_path / "module.pt")  # a whole pickled module, as some tools save: never unpickled
    with pytest.raises(UnsafeFileError, match="holds Python objects"):
        load_weights(build_model("cnn"), tmp_path / "module.pt")


def test_load_weights_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_weights(build_model("fc"), tmp_path / "missing.pt")
    torch.save(build_model("fc").state_dict(), tmp_path / "fc.pt")
    with pytest.raises(ValueError, match="do not fit CNNModel"):
        load_weights(build_model("cnn"), tmp_path / "fc.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="cannot read"):
        load_weights(build_model("fc"), tmp_path / "junk.pt")
    with pytest.raises(ValueError, match="arch 'rnn'"):
        build_model("rnn")


@pytest.mark.parametrize("arch", ["fc", "cnn"])
def test_lean_forward_equals_calling_the_modules(arch):
    """The forward skips Module.__call__ for speed; it must compute exactly what the modules do."""
    from rlbackdoors.models.minigrid import channels_first

    torch.manual_seed(0)
    model = build_model(arch)
    obs = torch.randint(0, 12, (9, 7, 7, 3), dtype=torch.uint8)
    x = channels_first(obs)
    emb = model.state_emb(x.reshape(9, -1) if arch == "fc" else x).reshape(9, -1)
    logits, value = model(obs)
    assert torch.equal(logits, model.actor(emb)) and torch.equal(value, model.critic(emb).squeeze(1))


@pytest.mark.parametrize(
    "arch, keys",
    [
        (
            "fc",
            {
                "state_emb.1.weight": (512, 147),
                "state_emb.3.weight": (256, 512),
                "actor.0.weight": (64, 257),
                "actor.2.weight": (32, 64),
                "actor.4.weight": (3, 32),
                "critic.4.weight": (1, 32),
            },
        ),
        (
            "cnn",
            {
                "state_emb.0.weight": (16, 3, 2, 2),
                "state_emb.4.weight": (64, 32, 2, 2),
                "actor.0.weight": (144, 1025),
                "actor.2.weight": (3, 144),
                "critic.2.weight": (1, 144),
            },
        ),
    ],
)
def test_randomized_lavaworld_models_have_the_trojai_layout(arch, keys):
    state = build_model(arch, "randomized-lavaworld").state_dict()
    for key, shape in keys.items():
        assert tuple(state[key].shape) == shape, key


@pytest.mark.parametrize("arch", ["fc", "cnn"])
def test_randomized_lavaworld_models_read_the_direction(arch):
    torch.manual_seed(0)
    model = build_model(arch, "randomized-lavaworld")
    image = torch.randint(0, 11, (4, 7, 7, 3), dtype=torch.uint8)
    logits, value = model({"image": image, "direction": torch.tensor([0, 1, 2, 3])})
    assert logits.shape == (4, 3) and value.shape == (4,)
    same_image = {"image": image[:1].expand(4, -1, -1, -1), "direction": torch.arange(4)}
    logits, _ = model(same_image)
    assert not torch.allclose(logits[0], logits[3])  # the direction input changes the policy


def test_build_model_names_the_env_and_arch_on_error():
    with pytest.raises(ValueError, match="env 'pong'"):
        build_model("fc", "pong")
