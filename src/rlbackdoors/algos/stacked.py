"""K agents' parameters stacked in one tensor and their Adam state, read from and written back to
each agent's own torch model and ``torch.optim.Adam``: what a group's update works on, whatever
computes it (the torch group update, :mod:`rlbackdoors.algos.group`, OPAC²'s, and the compiled
update of the torch trainer's rollouts, :mod:`rlbackdoors.algos.compiled`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch


def parameters_by_name(ppo: Any) -> dict[str, torch.nn.Parameter]:
    """An agent's parameters by their stacked names: the model's, then ``aux.*``, PPO's auxiliary
    memory head's. Built once per call for all names (``Module.get_parameter`` walks the module
    tree per name: K x P walks a group update before)."""
    named = dict(ppo.model.named_parameters())
    if ppo.aux is not None:
        named.update((f"aux.{name}", p) for name, p in ppo.aux.named_parameters())
    return named


@torch.no_grad()
def stacked_parameters(ppos: list[Any]) -> dict[str, torch.Tensor]:
    """Every agent's parameters (its auxiliary memory head's included), name -> (K, ...), copies
    on the group's device: one stack per name (no per-agent detach: no graph is recorded here)."""
    named = [parameters_by_name(ppo) for ppo in ppos]
    return {name: torch.stack([n[name] for n in named]) for name in named[0]}


class FlatParameters:
    """K agents' parameters in one (K, P) tensor, each agent's row all its parameters end to end,
    with a (K, ...) leaf view per stacked name for the forward.

    Why: the optimiser step is then a handful of ops on one tensor (per-agent scalars broadcast
    over its row) instead of a handful per parameter: a feed-forward grid model has 10 parameters,
    and per-parameter dispatch was a third of a group's update on a CPU."""

    def __init__(self, stacked: dict[str, torch.Tensor]):
        first = next(iter(stacked.values()))
        K = first.shape[0]
        self.flat = torch.cat([v.reshape(K, -1) for v in stacked.values()], 1)
        self.layout: dict[str, tuple[slice, torch.Size]] = {}  # name -> its columns of a row, its shape
        offset = 0
        for name, value in stacked.items():
            self.layout[name] = (slice(offset, offset + value[0].numel()), value.shape)
            offset += value[0].numel()
        self.views = {name: self.like(self.flat, name).requires_grad_() for name in stacked}

    def like(self, rows: torch.Tensor, name: str) -> torch.Tensor:
        """``name``'s (K, ...) view of a (K, P) tensor laid out as :attr:`flat` (an Adam moment, say)."""
        columns, shape = self.layout[name]
        return rows[:, columns].view(shape)

    def grad(self, loss: torch.Tensor) -> torch.Tensor:
        """The gradient of ``loss`` as one (K, P) tensor, laid out as :attr:`flat`."""
        grads = torch.autograd.grad(loss, list(self.views.values()))
        return torch.cat([g.reshape(g.shape[0], -1) for g in grads], 1)


class StackedAdam:
    """Adam over a group's :class:`FlatParameters`, every agent with its own moments, step count
    and learning rate, read from and written back to each agent's ``torch.optim.Adam`` state (the
    same update rule: moments by lerp, bias-corrected step size, ``eps`` added to the corrected
    second moment's root). ``members``: per agent (real ones, then pad copies), its optimiser and
    its parameters by stacked name (:func:`parameters_by_name`).

    Reading and writing back are a few calls over all K agents' tensors (a stack per name, one
    multi-tensor copy), not a copy per agent and parameter: on a GPU each would be a kernel
    launch, five per agent and parameter an update (15,360 at K = 256 for a 12-parameter grid model)."""

    def __init__(self, members: Sequence[tuple[torch.optim.Optimizer, Mapping[str, torch.Tensor]]], params: FlatParameters):
        self.members, self.params = members, params
        group = members[0][0].param_groups[0]
        self.eps, (self.beta1, self.beta2) = float(group["eps"]), group["betas"]
        self.on_device = bool(group.get("capturable") or group.get("fused"))  # where torch keeps the step: a plain Adam's on the CPU
        flat = params.flat
        # each agent's own rate: a run's schedule (by its own frames) may differ from its group-mates'
        self.lr = torch.tensor([float(opt.param_groups[0]["lr"]) for opt, _ in members], dtype=torch.float32, device=flat.device)
        names = list(params.layout)
        # each agent's state per name (empty before its first update: zero moments, step 0)
        states = [[opt.state.get(named[name], {}) for name in names] for opt, named in members]
        # every parameter of an agent has stepped as often: its last one's count (one stack, not a
        # read per agent and parameter: a fused Adam keeps its counts on the GPU, each read a sync)
        counts = [next((state["step"] for state in reversed(row) if "exp_avg" in state), None) for row in states]
        present = [c for c in counts if c is not None]
        if not present:
            self.step = torch.zeros(len(members), dtype=torch.float64, device=flat.device)
        else:
            zero = torch.zeros((), dtype=present[0].dtype, device=present[0].device)
            self.step = torch.stack([(c if c is not None else zero).reshape(()) for c in counts]).to(flat.device, torch.float64)
        self.exp_avg, self.exp_avg_sq = (self._gathered(states, names, key) for key in ("exp_avg", "exp_avg_sq"))

    def _gathered(self, states: list[list[dict]], names: list[str], key: str) -> torch.Tensor:
        """The (K, P) moment ``key`` of every agent, laid out as the flat parameters (zero where absent)."""
        flat = self.params.flat
        if not any("exp_avg" in state for row in states for state in row):
            return torch.zeros_like(flat)
        columns = []
        for i, name in enumerate(names):
            zero = torch.zeros(self.params.layout[name][1][1:], dtype=flat.dtype, device=flat.device)
            columns.append(torch.stack([row[i][key] if "exp_avg" in row[i] else zero for row in states]).reshape(len(states), -1))
        return torch.cat(columns, 1).to(flat.device)

    def _views(self):
        """(name, exp_avg view, exp_avg_sq view) per stacked name, shaped as its parameter."""
        for name in self.params.layout:
            yield name, self.params.like(self.exp_avg, name), self.params.like(self.exp_avg_sq, name)

    @torch.no_grad()
    def apply(self, grad: torch.Tensor) -> None:
        """One step on the (K, P) gradient."""
        self.step += 1
        bias1 = (1 - self.beta1**self.step).float()
        bias2_root = (1 - self.beta2**self.step).sqrt().float()
        step_size = bias1.reciprocal() * self.lr  # lr / bias1 as torch rounds a float over a tensor: reciprocal, then times
        self.exp_avg.lerp_(grad, 1 - self.beta1)
        self.exp_avg_sq.mul_(self.beta2).addcmul_(grad, grad, value=1 - self.beta2)
        # the same ops in the same order, in place: a (K, P) temporary less per op
        denom = self.exp_avg_sq.sqrt().div_(bias2_root[:, None]).add_(self.eps)
        self.params.flat.sub_(torch.div(self.exp_avg, denom, out=denom).mul_(step_size[:, None]))

    @torch.no_grad()
    def write_back(self, real: int) -> None:
        """Parameters into each of the ``real`` agents' models (the pad copies after them are
        dropped), moments and step into its optimiser's state (``torch.optim.Adam``'s format: a
        float32 step, moments shaped as the parameter, each agent's own tensors; those already
        there are written in place), with one multi-tensor copy per device."""
        steps = self.step[:real].float()
        steps = steps if self.on_device else steps.cpu()  # (one device sync, not one per parameter)
        rows = {name: (value.unbind(0), avg.unbind(0), sq.unbind(0)) for (name, avg, sq), value in zip(self._views(), self.params.views.values())}
        targets: list[torch.Tensor] = []
        sources: list[torch.Tensor] = []
        step_targets: list[torch.Tensor] = []
        step_sources: list[torch.Tensor] = []
        step_of = steps.unbind(0)
        for k, (opt, named) in enumerate(self.members[:real]):
            for name, (value, avg, sq) in rows.items():
                param = named[name]
                state = opt.state.get(param)
                if state is None or not _reusable(state, param, self.on_device):
                    state = {
                        "step": torch.zeros((), dtype=torch.float32, device=param.device if self.on_device else "cpu"),
                        "exp_avg": torch.empty_like(param, memory_format=torch.contiguous_format),
                        "exp_avg_sq": torch.empty_like(param, memory_format=torch.contiguous_format),
                    }
                else:  # the same three entries, in torch's order, as a fresh state would have
                    state = {"step": state["step"], "exp_avg": state["exp_avg"], "exp_avg_sq": state["exp_avg_sq"]}
                opt.state[param] = state
                targets += [param, state["exp_avg"], state["exp_avg_sq"]]
                sources += [value[k], avg[k], sq[k]]
                step_targets.append(state["step"])
                step_sources.append(step_of[k])
        torch._foreach_copy_(targets, sources)
        torch._foreach_copy_(step_targets, step_sources)


def _reusable(state: dict, param: torch.Tensor, on_device: bool) -> bool:
    """Whether an optimiser state can be written in place: Adam's three tensors, shaped and placed
    as a fresh one (a checkpoint's are, once loaded and checked)."""
    if not state or set(state) != {"step", "exp_avg", "exp_avg_sq"}:
        return False
    step, avg, sq = state["step"], state["exp_avg"], state["exp_avg_sq"]
    where = param.device if on_device else torch.device("cpu")
    return (
        step.dtype == torch.float32
        and step.dim() == 0
        and step.device == where
        and all(t.shape == param.shape and t.dtype == param.dtype and t.device == param.device and t.is_contiguous() for t in (avg, sq))
    )
