"""The group trainer on a CUDA device: the GPU path that ``--group-size`` / ``train.device cuda``
take. These tests need a GPU and are skipped without one (CI has none); they are run on a GPU
machine when one is lent (docs/results/zoos.md records the last run).

What must hold on the GPU: the stacked rollout and update compute what the CPU group computes (to
float rounding: other kernels), the Adam state keeps ``torch.optim.Adam``'s own format (a plain
Adam's step count on the CPU), and a run trained on the GPU ends as an ordinary model folder whose
files load on a machine without one and whose checkpoint resumes there.
"""

from __future__ import annotations

import copy
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from rlbackdoors.algos import group
from rlbackdoors.config import RunConfig
from rlbackdoors.train.driver import resolve_device
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run as zoo_run
from rlbackdoors.zoo.spec import parse_spec
from test_group import KernelCount, group_cycle_ops, learner, opac2_learner, zoo_spec

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device: the group trainer's GPU path (run on a GPU machine)")

# The device as training takes it (train/driver.resolve_device): cuDNN's deterministic kernels and
# no TF32. A bare torch.device("cuda") leaves cuDNN's TF32 on (torch's default), which rounds
# convolutions to 10 bits: on an H200 (2026-11-26) the Randomized LavaWorld CNN's
# gradient norms came 1 % and its update 0.17 (cosine 0.985) away from the CPU's, failing this file
# (the FC net, without convolutions, agreed to 1e-5). Taken this way, on an H200 (2026-11-27) the CNN
# agreed to 2.5e-3 at most: TF32 was the cause.
CUDA = resolve_device("cuda") if torch.cuda.is_available() else torch.device("cuda")


def one_step(learners: list) -> tuple[list, list]:
    ppos = [g[0] for g in learners]
    results = group.collect(ppos, [g[1] for g in learners], [g[2] for g in learners])
    return results, group.update(ppos, [r for r, _ in results])


CM_SECTIONS = {"ppo": {"rollout": 24, "batch_size": 120, "aux_memory_coef": 0.5}}


@pytest.mark.parametrize(
    "env,arch,sections,conv",
    [
        ("lavaworld", "fc", {}, "each"),
        ("randomized-lavaworld", "cnn", {}, "each"),
        ("colorful-memory", None, CM_SECTIONS, "each"),
        # one grouped conv2d for all agents on the GPU (models.minigrid.STACKED_CONV's "grouped")
        ("randomized-lavaworld", "cnn", {}, "grouped"),
        ("colorful-memory", None, CM_SECTIONS, "grouped"),
    ],
)
def test_cuda_group_computes_what_the_cpu_group_computes(env, arch, sections, conv, monkeypatch):
    """Three agents (one poisoned through the attack seam), one rollout and one update on each
    device: the same actions and rewards, the same gradient norms to 1 %, and the same update of
    the weights to rounding. Why a relative bound on the update, not on each weight: Adam divides
    by the gradient's running scale, so a weight whose gradient is near zero moves by up to the
    learning rate on either device's rounding; the update as a whole agrees (printed: -rP).
    Measured on an H200 (docs/results/zoos.md) with cuDNN's TF32 still on in this test: LavaWorld FC 2e-6
    to 1e-5, Colorful Memory 0.02 to 0.06, Randomized LavaWorld CNN 0.11 and 0.17 (cosine 0.985:
    failed). With the training's settings (``CUDA`` above), H200 2026-11-27: LavaWorld FC 2e-6 to
    1e-5, Colorful Memory 4e-7 to 6e-6, Randomized LavaWorld CNN 4e-6 to 2.5e-3 (cosine 0.999999).
    ``conv``: how the GPU group computes its convolutions (the CPU's one conv2d per agent either way)."""
    from rlbackdoors.models import minigrid

    monkeypatch.setitem(minigrid.STACKED_CONV, "cuda", conv)
    poisons = [None, {"trigger": "additive:135", "attack": "trojdrl", "attack_params": {"budget": 0.05}} if env == "lavaworld" else None, None]
    on_cpu = [learner(env, arch, s, p, torch.device("cpu"), **copy.deepcopy(sections)) for s, p in enumerate(poisons)]
    on_gpu = [learner(env, arch, s, p, CUDA, **copy.deepcopy(sections)) for s, p in enumerate(poisons)]
    start = [torch.cat([p.detach().reshape(-1) for p in g[0].model.parameters()]) for g in on_cpu]
    (cpu_results, cpu_stats), (gpu_results, gpu_stats) = one_step(on_cpu), one_step(on_gpu)
    for k in range(3):
        ours, theirs = gpu_results[k][0], cpu_results[k][0]
        assert torch.equal(ours.actions.cpu(), theirs.actions)  # the same uniforms over the same weights (a flip needs a draw within rounding of a bucket edge)
        # the rollout stayed on the device (issue 55): only observations and actions crossed per step
        kept = {f: getattr(ours, f) for f in ("actions", "logprobs", "values", "advantages", "returns", "memories", "masks", "memory_targets")}
        kept.update({f"obs.{key}": v for key, v in ours.obs.items()} if isinstance(ours.obs, dict) else {"obs": ours.obs})
        assert {f: v.device.type for f, v in kept.items() if v is not None} == {f: "cuda" for f, v in kept.items() if v is not None}
        np.testing.assert_array_equal(ours.rewards, theirs.rewards)
        assert gpu_stats[k]["grad_norm"] == pytest.approx(cpu_stats[k]["grad_norm"], rel=1e-2)
        assert all(p.device.type == "cuda" for p in on_gpu[k][0].model.parameters())
        moved_cpu = torch.cat([p.detach().reshape(-1) for p in on_cpu[k][0].model.parameters()]) - start[k]
        moved_gpu = torch.cat([p.detach().cpu().reshape(-1) for p in on_gpu[k][0].model.parameters()]) - start[k]
        rel = float((moved_gpu - moved_cpu).norm() / moved_cpu.norm())
        cosine = float(torch.nn.functional.cosine_similarity(moved_gpu, moved_cpu, dim=0))
        print(
            f"{env} agent {k}: update relative difference {rel:.2e}, cosine {cosine:.6f}, grad norm {gpu_stats[k]['grad_norm']:.6g} vs {cpu_stats[k]['grad_norm']:.6g}"
        )
        assert rel < 0.25 and cosine > 0.99  # a wrong gradient or a crossed agent gives rel ~ 1
    # the Adam state in torch.optim.Adam's own layout on this device: as a lone learner's after its update
    lone, envs, obs = learner(env, arch, 0, None, CUDA, **copy.deepcopy(sections))
    lone.update(lone.collect(envs, obs)[0])
    for mine, theirs in zip(on_gpu[0][0].model.parameters(), lone.model.parameters()):
        a, b = on_gpu[0][0].optimizer.state[mine], lone.optimizer.state[theirs]
        assert {key: (v.device.type, v.dtype) for key, v in a.items()} == {key: (v.device.type, v.dtype) for key, v in b.items()}


def test_a_gpu_zoo_is_reproducible_resumes_after_a_kill_and_loads_without_a_gpu(tmp_path):
    """A GPU zoo (``train.device cuda``) in one group of four, twice: the same bytes (the GPU path
    is deterministic). ``zoo run --group-size 3``, killed (SIGTERM) once a checkpoint is on disk,
    then run again: the same bytes as well (an agent's bytes depend on its config, not on its
    group or a resume). Weights are stored as CPU tensors, loadable without a GPU."""
    spec = zoo_spec()
    spec["overrides"]["train"]["device"] = "cuda"
    # Half the CPU test's length (3 evaluations): on an H200 (2026-11-26) the whole test at
    # 9,600 frames a model, four zoo runs, outlasted two time limits of about 110 s.
    spec["overrides"]["train"]["max_frames"] = 4800
    whole, again, cut = tmp_path / "whole", tmp_path / "again", tmp_path / "cut"
    for path in (whole, again, cut):
        plan(parse_spec(spec), path)
    log = io.StringIO()
    summary = zoo_run(whole, workers=1, group_size="auto", progress_interval=5.0, out=log)
    assert "--group-size auto: by each model's algorithm and train.device" in log.getvalue() and summary["done"] == 4 and summary["failed"] == 0
    assert zoo_run(again, workers=1, group_size="auto", progress_interval=5.0)["done"] == 4
    proc = subprocess.Popen(
        [sys.executable, "-m", "rlbackdoors.zoo.cli", "run", str(cut), "--workers", "1", "--group-size", "3"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None and not list((cut / "models").glob("*/checkpoint.pt")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=240) != 0 and list((cut / "models").glob("*/checkpoint.pt")), "the GPU group stopped without checkpoints"
    summary = zoo_run(cut, workers=1, group_size=3, progress_interval=5.0)
    assert summary["done"] == 4 and summary["failed"] == 0
    same = {
        other.name: sum((f / "model.pt").read_bytes() == (other / "models" / f.name / "model.pt").read_bytes() for f in (whole / "models").iterdir())
        for other in (again, cut)
    }
    print(f"GPU zoo model.pt bytes equal to the first run's: {same} of 4")
    assert same["again"] == 4
    for folder in sorted((whole / "models").iterdir()):
        assert json.loads((folder / "metrics.json").read_text())["trainer"] == "group"
        weights = torch.load(folder / "model.pt", weights_only=True)  # no map_location: stored on the CPU
        assert all(t.device.type == "cpu" for t in weights.values())
        assert (folder / "model.pt").read_bytes() == (cut / "models" / folder.name / "model.pt").read_bytes()


def test_cuda_opac2_group_computes_what_the_cpu_group_computes():
    """OPAC² (the Safety Car Goal learner): three agents, five batched updates on each device
    from the same replays: losses within 1 %, the weights' update the same to rounding (relative
    L2 < 0.25, cosine > 0.99, as for PPO above), the same noise drawn (generators on the CPU),
    and the Adam state in the layout a lone CUDA agent's fused Adam keeps."""
    from rlbackdoors.algos import group_opac2

    sides = {name: [opac2_learner(s, torch.device(name)) for s in range(3)] for name in ("cpu", "cuda")}
    start = [torch.cat([p.detach().reshape(-1) for net in ("policy", "q", "v") for p in getattr(a, net).parameters()]) for a, _ in sides["cpu"]]
    stats = {
        name: group_opac2.update([a for a, _ in pairs], [r for _, r in pairs], [np.random.default_rng([s, 1]) for s in range(3)], 5)
        for name, pairs in sides.items()
    }
    for k in range(3):
        for ours, theirs in zip(stats["cuda"][k], stats["cpu"][k]):
            assert all(ours[key] == pytest.approx(theirs[key], rel=1e-2, abs=1e-4) for key in ours)
        moved = {
            name: torch.cat([p.detach().cpu().reshape(-1) for net in ("policy", "q", "v") for p in getattr(pairs[k][0], net).parameters()]) - start[k]
            for name, pairs in sides.items()
        }
        rel = float((moved["cuda"] - moved["cpu"]).norm() / moved["cpu"].norm())
        cosine = float(torch.nn.functional.cosine_similarity(moved["cuda"], moved["cpu"], dim=0))
        print(f"OPAC² agent {k}: update relative difference {rel:.2e}, cosine {cosine:.6f}")
        assert rel < 0.25 and cosine > 0.99
        assert torch.equal(sides["cuda"][k][0].generator.get_state(), sides["cpu"][k][0].generator.get_state())
    lone, replay = opac2_learner(0, CUDA)
    lone.update(replay, np.random.default_rng(0))
    for net in ("policy", "q", "v"):
        mine, theirs = getattr(sides["cuda"][0][0], f"{net}_opt"), getattr(lone, f"{net}_opt")
        for x, y in zip(mine.param_groups[0]["params"], theirs.param_groups[0]["params"]):
            assert {key: (v.device.type, v.dtype) for key, v in mine.state[x].items()} == {key: (v.device.type, v.dtype) for key, v in theirs.state[y].items()}


def test_cuda_lockstep_evaluations_do_not_depend_on_group_mates_and_match_the_cpu():
    """Three LavaWorld FC agents evaluated in lockstep on the GPU (greedy, 16 episodes per
    condition): agent 1 reads the same numbers with and without its mates (the group computes at
    a fixed width), and every agent's numbers are the CPU lone evaluation's up to rounding (a
    greedy policy: success rates within 1/16 of them)."""
    from rlbackdoors.config import RunConfig
    from rlbackdoors.models import build_model
    from rlbackdoors.train.driver import evaluate_run, evaluate_runs

    cfgs = [
        RunConfig.from_dict({"poison": poison, "train": {"seed": s, "eval_policy": "greedy"}})
        for s, poison in enumerate([{"poisoned": False}, {}, {"attack": "action_target"}])
    ]
    models = []
    for cfg in cfgs:
        torch.manual_seed(cfg.train.seed)
        models.append(build_model(cfg.model.arch, cfg.env.name))
    cpu = [evaluate_run(m, c, 16) for m, c in zip(models, cfgs)]
    gpu = [copy.deepcopy(m).to(CUDA) for m in models]
    together = evaluate_runs(gpu, cfgs, [16] * 3, group.stacked_act)
    assert evaluate_runs(gpu[1:2], cfgs[1:2], [16], group.stacked_act)[0].to_dict() == together[1].to_dict()
    for a, b in zip(cpu, together):
        assert abs(a.clean_sr - b.clean_sr) <= 1 / 16 and abs(a.poisoned_sr - b.poisoned_sr) <= 1 / 16


def test_cuda_group_with_clean_teachers_computes_what_the_cpu_group_computes():
    """The fine-tuning evasion's teacher on the GPU (issue 34's ``teacher``): three LavaWorld FC
    agents under TrojDRL, each with its own frozen clean teacher (coefficients 0.1, 1 and 0.5; the
    same teacher weights on both devices), one rollout and update on each: the same actions and
    untriggered masks, the teachers' log-probabilities to rounding, and the teacher KL and
    gradient norms within 1 %. A teacher left on the CPU, or a KL over the triggered frames,
    fails here."""
    coefs = [0.1, 1.0, 0.5]
    poisons = [{"trigger": t, "attack": "trojdrl", "attack_params": {"budget": 0.2}} for t in ("additive:135", "multiplicative:12", "additive:60")]
    on_cpu = [learner("lavaworld", "fc", k, poisons[k]) for k in range(3)]
    on_gpu = [learner("lavaworld", "fc", k, poisons[k], CUDA) for k in range(3)]
    for k, coef in enumerate(coefs):
        torch.manual_seed(100 + k)
        teacher = copy.deepcopy(on_cpu[k][0].model)
        for p in teacher.parameters():
            torch.nn.init.normal_(p, std=0.1)
        on_cpu[k][0].set_teacher(teacher, coef)
        on_gpu[k][0].set_teacher(copy.deepcopy(teacher).to(CUDA), coef)
    (cpu_results, cpu_stats), (gpu_results, gpu_stats) = one_step(on_cpu), one_step(on_gpu)
    triggered = 0
    for k in range(3):
        ours, theirs = gpu_results[k][0], cpu_results[k][0]
        assert torch.equal(ours.actions.cpu(), theirs.actions) and torch.equal(ours.untriggered.cpu(), theirs.untriggered)
        torch.testing.assert_close(ours.teacher_logp.cpu(), theirs.teacher_logp, rtol=1e-4, atol=1e-5)
        print(
            f"teacher agent {k}: KL {gpu_stats[k]['teacher_kl']:.6g} vs {cpu_stats[k]['teacher_kl']:.6g}, grad norm {gpu_stats[k]['grad_norm']:.6g} vs {cpu_stats[k]['grad_norm']:.6g}"
        )
        assert gpu_stats[k]["teacher_kl"] == pytest.approx(cpu_stats[k]["teacher_kl"], rel=1e-2) and gpu_stats[k]["teacher_kl"] > 0
        assert gpu_stats[k]["grad_norm"] == pytest.approx(cpu_stats[k]["grad_norm"], rel=1e-2)
        triggered += int((~theirs.untriggered).sum())
    assert triggered > 0  # some frames carried the trigger and were left out of the KL


# Run in a process of its own: JAX must start with deterministic GPU kernels (algos.xla.start),
# which a JAX started earlier in this process (by a CPU test) would not have.
JAX_ON_CUDA = r"""
import copy, hashlib, json, sys
import torch
from rlbackdoors.algos import group
from rlbackdoors.train.driver import resolve_device
from test_group import learner

cuda = resolve_device("cuda")
sections = {"ppo": {"epochs": 1, "batch_size": 1280}}
def made(backend, seeds):
    out = [learner("lavaworld", "fc", s, None, cuda, ppo={**sections["ppo"], "update_backend": backend}) for s in seeds]
    ppos = [m[0] for m in out]
    return ppos, [r for r, _ in group.collect(ppos, [m[1] for m in out], [m[2] for m in out])]
def digest(model):
    return hashlib.sha256(b"".join(p.detach().cpu().numpy().tobytes() for p in model.parameters())).hexdigest()
torch_ppos, rollouts = made("torch", [0, 1, 2])
jax_ppos, same = made("jax", [0, 1, 2])
expected, got = group.update(torch_ppos, rollouts), group.update(jax_ppos, same)
moved = []
for a, b in zip(torch_ppos, jax_ppos):
    diff = torch.cat([(p.detach() - q.detach()).abs().reshape(-1) for p, q in zip(a.model.parameters(), b.model.parameters())])
    moved.append({"over_1e-5": float((diff > 1e-5).float().mean()), "max": float(diff.max()), "device": next(b.model.parameters()).device.type})
digests = []
for seeds in ([0], [0, 1, 2], [0, 1, 2]):
    ppos, rollouts = made("jax", seeds)
    for _ in range(2):
        group.update(ppos, rollouts)
    digests.append(digest(ppos[0].model))
step = float(jax_ppos[0].optimizer.state[next(jax_ppos[0].model.parameters())]["step"])
print(json.dumps({"expected": expected, "got": got, "moved": moved, "digests": digests, "step": step}))
"""


def test_the_jax_update_on_cuda_is_torchs_and_does_not_depend_on_the_group(tmp_path):
    """``ppo.update_backend = "jax"`` on the GPU (one XLA program, the weights and rollout handed
    over through DLPack, agents in chunks of 64): three LavaWorld FC agents' rollout on CUDA, one
    epoch of one minibatch: the loss parts and gradient norm of torch's group update to 1e-4, the
    weights as on the CPU (tests/test_jax_update.py: to 1e-5 but for Adam's sign on near-zero
    gradients), left on the GPU, with torch.optim.Adam's step; agent 0's bytes the same alone,
    with two mates and again (deterministic GPU kernels)."""
    import jax

    try:
        if not jax.devices("gpu"):
            pytest.skip("this JAX has no GPU")
    except RuntimeError:
        pytest.skip("this JAX has no GPU backend (jax[cuda])")
    tests = str(Path(__file__).resolve().parent)
    out = subprocess.run(
        [sys.executable, "-c", JAX_ON_CUDA],
        capture_output=True,
        text=True,
        cwd=tests,
        timeout=300,
        env={**os.environ, "PYTHONPATH": tests + os.pathsep + os.environ.get("PYTHONPATH", "")},
    )
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    print(json.dumps(result["moved"]), result["digests"])
    for e, g in zip(result["expected"], result["got"]):
        for key in e:
            assert g[key] == pytest.approx(e[key], rel=1e-4), key
    for m in result["moved"]:
        assert m["device"] == "cuda" and m["over_1e-5"] <= 1e-3 and m["max"] <= 2.1e-3
    assert len(set(result["digests"])) == 1 and result["step"] == 1.0


@pytest.mark.parametrize("arch,conv", [("fc", "each"), ("cnn", "gemm"), ("cnn", "grouped")])
def test_cuda_group_work_does_not_grow_with_its_agents(arch, conv, monkeypatch):
    """On the GPU, where every operation is a launch or a transfer (``.to(device)`` dispatches here,
    unlike on the CPU): a LavaWorld group's rollout and update (TrojDRL on half, clean teachers and
    anchors; the CNN's convolutions in one call, ``models.minigrid.STACKED_CONV``'s "gemm" (a
    setting since an H200 timed it slower than one conv2d per agent) or "grouped") run the same
    operations for 2 agents as for 6, bar each agent's own host draws; and an OPAC² group's update
    and act (replay batches stacked on the host, copied once per field)."""
    from rlbackdoors.algos import group_opac2
    from rlbackdoors.models import minigrid

    monkeypatch.setitem(minigrid.STACKED_CONV, "cuda", conv)

    two, six = group_cycle_ops(2, True, CUDA, arch), group_cycle_ops(6, True, CUDA, arch)
    grown = {op: six[op] - two[op] for op in six.keys() | two.keys() if six[op] != two[op]}
    epochs = RunConfig.from_dict({"env": {"name": "lavaworld"}}).ppo.epochs
    assert grown == {"aten.rand": 4, "aten.randperm": 4 * epochs}, grown

    def opac2_ops(k: int) -> tuple:
        agents, replays = zip(*[opac2_learner(s, CUDA) for s in range(k)])
        rngs = [np.random.default_rng(s) for s in range(k)]
        group_opac2.update(list(agents), list(replays), rngs, 2)
        with KernelCount() as update:
            group_opac2.update(list(agents), list(replays), rngs, 2)
        with KernelCount() as act:
            group_opac2.act(list(agents), [np.random.default_rng(s).normal(size=(10, 6)) for s in range(k)])
        return update.ops, act.ops

    (update2, act2), (update6, act6) = opac2_ops(2), opac2_ops(6)
    for small, large, own in ((update2, update6, 4 * 2 * 2), (act2, act6, 4)):  # randn: the noise each agent draws on its host generator
        assert {op: large[op] - small[op] for op in large.keys() | small.keys() if large[op] != small[op]} == {"aten.randn": own}


def test_cuda_group_over_64_computes_each_agent_as_a_small_group_does():
    """A CUDA group computes 64 agents at a time (``algos.group.chunks``): in a group of 65, agent 0
    (first chunk) and agent 64 (the second, padded) end a rollout and update with the bytes they
    have in a group of 2 (width 64 both times; before, the 65 computed at width 128)."""
    from test_group import weights_digest

    def digests(seeds: list[int]) -> dict[int, str]:
        learners = [learner("lavaworld", "fc", s, device=CUDA, ppo={"rollout": 16}) for s in seeds]
        one_step(learners)
        return {s: weights_digest(copy.deepcopy(ppo.model).cpu()) for s, (ppo, _, _) in zip(seeds, learners)}

    wide = digests(list(range(65)))
    small = digests([0, 64])
    assert wide[0] == small[0] and wide[64] == small[64]


@pytest.mark.parametrize(
    "size,crossings,max_steps,see,refill_every,trigger,graph",
    [(9, 1, 250, False, 8, "multiplicative:12", False), (11, 3, 60, True, 3, "additive:100", False), (9, 1, 40, False, 8, "multiplicative:12", True)],
)
def test_the_lavaworld_device_engine_on_cuda_steps_as_the_numba_engine(size, crossings, max_steps, see, refill_every, trigger, graph):
    """The device engine (envs/lavaworld_device.py) on the GPU: every output of 600 steps, 48 slots,
    the bytes of the numba engine (as tests/test_lavaworld_device.py checks on the CPU), also with
    the step captured as a CUDA graph (its state in static buffers, warm-up on copies). (A bad
    action is refused by a device-side assert, which ends the process's CUDA context: not tried here.)"""
    from test_lavaworld_device import engine, step_both

    from rlbackdoors.envs.lavaworld_device import DeviceLavaWorld

    numba_side = engine(48, size, crossings, max_steps, see, trigger)
    device = DeviceLavaWorld(engine(48, size, crossings, max_steps, see, trigger), CUDA, refill_every, graph=graph)
    assert len(step_both(numba_side, numba_side.step, device, 600)) > 48 * 600 / max_steps


def test_a_cuda_group_on_the_device_engine_collects_the_bytes_of_the_numba_engine():
    """LavaWorld FC, four agents (clean and env mix) on the GPU: three rollouts and updates with the
    slots on the device engine, as one CUDA graph a step (collect's device_engine=True), against
    the numba engines: the same rollouts, next observations, weights and engines' state."""
    from test_group import engine_cycles

    (numba, _), (device, ends) = engine_cycles(False, CUDA), engine_cycles(True, CUDA)
    assert len(numba) == 12 and numba == device and ends > 0
