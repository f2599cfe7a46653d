"""The member axis: N independent seeds of one method as one stacked agent (docs/members.md).

A *group* of N members is one agent whose every parameter, buffer and optimiser state carries a
leading axis of size N: member k's slice is exactly the tensor a separate run with seed k holds.
A method file stays written for one seed; the shared blocks carry the axis:

* :func:`stack_agents` turns N ordinary learners (:class:`~dvfb.nets.learner.Learner`: agents or
  fine-tuners, built as N separate runs would build them), or N models, into one over stacked
  tensors, in place of the first; :func:`member_training_state` and :func:`member_slice` give
  member k's ordinary state back (checkpoints, snapshots);
* ``nn.Linear`` and ``nn.LayerNorm`` become :class:`MemberLinear` / :class:`MemberLayerNorm` (one
  batched product for all members); the blocks with their own parameters (``TwinHead``,
  ``RunningMeanStd``, the reward modules) read ``module.members``;
* :class:`MemberGenerators` is one random stream per member: every draw helper here gives member k
  the numbers its separate run draws, in the same order;
* :func:`member_mean` / :func:`member_sum` reduce everything but the member axis, so that each
  member's loss is its own mean; :func:`minimise` backpropagates their sum, so no gradient mixes
  members (Adam is element-wise: its step stays exactly per member).

``members == 0`` is an ordinary agent (no member axis anywhere): every helper is then the plain
torch operation it replaces.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F_nn

from dvfb.nets.learner import Learner


class MemberGenerators(tuple):
    """One ``torch.Generator`` per member, in member order (member k's is its separate run's)."""


def members_of(generator) -> int:
    """The number of members a random stream serves (0: an ordinary stream or None)."""
    return len(generator) if isinstance(generator, MemberGenerators) else 0


# Random draws ------------------------------------------------------------------------------------
# Each helper takes an ordinary generator (or None: torch's global stream) or MemberGenerators; with
# members, member k's slice is the draw its own generator makes with the same arguments.

def randn(shape, generator=None, device=None, dtype=None) -> torch.Tensor:
    if isinstance(generator, MemberGenerators):
        return torch.stack([torch.randn(shape, generator=g, device=device, dtype=dtype) for g in generator])
    return torch.randn(shape, generator=generator, device=device, dtype=dtype)


def rand(shape, generator=None, device=None, dtype=None) -> torch.Tensor:
    if isinstance(generator, MemberGenerators):
        return torch.stack([torch.rand(shape, generator=g, device=device, dtype=dtype) for g in generator])
    return torch.rand(shape, generator=generator, device=device, dtype=dtype)


def randint(low: int, high: int, shape, generator=None, device=None) -> torch.Tensor:
    if isinstance(generator, MemberGenerators):
        return torch.stack([torch.randint(low, high, shape, generator=g, device=device) for g in generator])
    return torch.randint(low, high, shape, generator=generator, device=device)


def randperm(n: int, generator=None, device=None) -> torch.Tensor:
    if isinstance(generator, MemberGenerators):
        return torch.stack([torch.randperm(n, generator=g, device=device) for g in generator])
    return torch.randperm(n, generator=generator, device=device)


def take_rows(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``x[index]`` along the batch axis: ``(N, ...)[(n,)]``, or per member ``(M, N, ...)[(M, n)]``."""
    if index.dim() == 1:
        return x[index]
    return x[torch.arange(index.shape[0], device=index.device).unsqueeze(-1), index]


# Reductions ----------------------------------------------------------------------------------------

# A reduction over a member's slice is the very reduction its separate run makes on the same shape
# and strides, so it rounds the same; one reduction over a reshaped group would sum in another order.

def member_mean(x: torch.Tensor, members: int) -> torch.Tensor:
    """The mean over everything but the member axis: ``()`` for an agent, ``(M,)`` for a group."""
    return x.mean() if not members else torch.stack([x[k].mean() for k in range(members)])


def member_sum(x: torch.Tensor, members: int) -> torch.Tensor:
    """The sum over everything but the member axis: ``()`` for an agent, ``(M,)`` for a group."""
    return x.sum() if not members else torch.stack([x[k].sum() for k in range(members)])


def per_member(stat: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A per-member statistic (``()`` or ``(M,)``) shaped to broadcast against ``like``."""
    return stat.reshape(stat.shape + (1,) * (like.dim() - stat.dim()))


def with_head_axis(x: torch.Tensor, members: int) -> torch.Tensor:
    """``x`` ready to broadcast against a twin head's ``(M, K, ...)`` output: ``(M, ...)`` gets a
    head axis after the member axis; an ordinary agent's ``x`` already broadcasts as it is."""
    return x.unsqueeze(1) if members else x


def minimise(optimizer: torch.optim.Optimizer, loss: torch.Tensor, inputs=None) -> None:
    """One optimiser step on ``loss``: ``()``, or ``(M,)`` (the members' own losses, whose sum is
    differentiated: member k's gradient is its own loss's). ``inputs`` restricts the leaves that
    receive gradients (the actor losses)."""
    optimizer.zero_grad(set_to_none=True)
    (loss if loss.dim() == 0 else loss.sum()).backward(inputs=inputs)
    optimizer.step()


class _RowProducts(torch.autograd.Function):
    """``x @ rows^T (+ bias)`` per member: ``x`` ``(M, P, d)``, ``rows`` ``(M, N, d)``, ``bias``
    ``(M, N)`` or None, one batched product, differentiated as the ordinary ``mm`` / ``addmm``
    is: ``grad_x = g rows``, ``grad_rows = g^T x`` (in ``rows``' layout; autograd's ``bmm`` forms
    ``(x^T g)^T``, which some CPU kernels round otherwise for narrow ``d``, docs/members.md) and
    ``grad_bias`` the sum of ``g`` over the ``P`` rows."""

    @staticmethod
    def forward(ctx, x, rows, bias):
        ctx.save_for_backward(x, rows)
        ctx.has_bias = bias is not None
        if bias is None:
            return torch.bmm(x, rows.mT)
        return torch.baddbmm(bias.unsqueeze(1), x, rows.mT)

    @staticmethod
    def backward(ctx, grad):
        x, rows = ctx.saved_tensors
        grad_x = torch.bmm(grad, rows) if ctx.needs_input_grad[0] else None
        grad_rows = torch.bmm(grad.mT, x) if ctx.needs_input_grad[1] else None
        grad_bias = grad.sum(1) if ctx.has_bias and ctx.needs_input_grad[2] else None
        return grad_x, grad_rows, grad_bias


def row_products(x: torch.Tensor, rows: torch.Tensor, members: int) -> torch.Tensor:
    """``x @ rows^T``: ``x`` ``(..., P, d)`` and ``rows`` ``(N, d)`` give ``(..., P, N)`` (F B^T of
    every head, B B^T, the SF and conservative-FB measures). A group (``(M, ..., P, d)``,
    ``(M, N, d)``) folds x's leading axes into rows as the ordinary ``matmul`` does, one product per
    member: bit for bit the ordinary one, forward and backward (:class:`_RowProducts`)."""
    if not members:
        return torch.matmul(x, rows.T)
    product = _RowProducts.apply(x.reshape(members, -1, x.shape[-1]), rows, None)
    return product.reshape(*x.shape[:-1], rows.shape[-2])


# Layers ------------------------------------------------------------------------------------------

class MemberLinear(nn.Linear):
    """``nn.Linear`` over stacked weights ``(M, out, in)`` and biases ``(M, out)``: inputs
    ``(M, ..., in)``, one batched product for all members, forward and backward."""

    members: int = 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.members:
            return F_nn.linear(x, self.weight, self.bias)
        flat = x.reshape(self.members, -1, x.shape[-1])
        out = _RowProducts.apply(flat, self.weight, self.bias)
        return out.reshape(*x.shape[:-1], out.shape[-1])


class MemberLayerNorm(nn.LayerNorm):
    """``nn.LayerNorm`` over the last axis with stacked affine parameters ``(M, width)``."""

    members: int = 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.members:
            return F_nn.layer_norm(x, self.normalized_shape, self.weight, self.bias, self.eps)
        # One fused call per member: its backward accumulates the affine gradients in the order a
        # separate run's does (a broadcast affine after a plain normalisation rounds them otherwise).
        return torch.stack([F_nn.layer_norm(x[k], self.normalized_shape,
                                            None if self.weight is None else self.weight[k],
                                            None if self.bias is None else self.bias[k], self.eps)
                            for k in range(self.members)])


MEMBER_CLASSES = {nn.Linear: MemberLinear, nn.LayerNorm: MemberLayerNorm}


# Stacking and unstacking -----------------------------------------------------------------------------

def _tensor_slots(module: nn.Module):
    """(owner module, kind, name) of every parameter and buffer, each tensor once."""
    seen: set[int] = set()
    for owner in module.modules():
        for kind in ("_parameters", "_buffers"):
            for name, tensor in getattr(owner, kind).items():
                if tensor is None or id(tensor) in seen:
                    continue
                seen.add(id(tensor))
                yield owner, kind, name


def _stack_tensors(modules: list[nn.Module], mismatch: str) -> None:
    """Every parameter and buffer of ``modules[0]`` becomes the stack of the modules' tensors (a
    parameter keeps its identity: its ``.data`` is replaced)."""
    slots = [list(_tensor_slots(module)) for module in modules]
    if any(len(s) != len(slots[0]) for s in slots):
        raise ValueError(mismatch)
    for i, (owner, kind, name) in enumerate(slots[0]):
        stacked = torch.stack([getattr(s[i][0], s[i][1])[s[i][2]].detach() for s in slots])
        if kind == "_parameters":
            owner._parameters[name].data = stacked
        else:
            owner._buffers[name] = stacked


def stack_agents(agents: list[nn.Module]) -> nn.Module:
    """One learner (or model) whose tensors stack those of ``agents`` (learners or models of one
    method and config, built and seeded as separate runs): the first, modified in place and returned.

    Parameters keep their identity (``.data`` is replaced), so every optimiser, EMA list and cache
    that refers to them stays valid; optimiser states are stacked likewise. The stacked agent's
    ``generator`` is a :class:`MemberGenerators` of the agents' own generators.
    """
    if not agents:
        raise ValueError("a group needs at least one member")
    lead, m = agents[0], len(agents)
    optimizer_states = [_optimizer_tensors(a) for a in agents]
    _stack_tensors(agents, "the members of a group must be the same method with the same config")
    _stack_optimizer_states(lead, optimizer_states)
    for module in _with_model(lead):
        cls = MEMBER_CLASSES.get(type(module))
        if cls is not None:
            module.__class__ = cls
        module.members = m
    lead.use_generator(MemberGenerators(a.generator for a in agents))
    return lead


def _with_model(agent: nn.Module) -> list[nn.Module]:
    """The agent's modules and, for a learner whose model is not one of them (a pre-training
    agent's), the model itself (its networks are the learner's; its own ``members`` and
    ``generator`` must follow)."""
    modules = list(agent.modules())
    if isinstance(agent, Learner) and all(agent.model is not m for m in modules):
        modules.append(agent.model)
    return modules


def _optimizers(agent: nn.Module) -> dict[str, torch.optim.Optimizer]:
    """The optimisers of a learner; a model (inference only) has none."""
    return agent.optimizers() if isinstance(agent, Learner) else {}


def _optimizer_tensors(agent: nn.Module) -> dict[str, list[dict]]:
    """Each optimiser's per-parameter state, in parameter order."""
    out = {}
    for name, opt in _optimizers(agent).items():
        params = [p for group in opt.param_groups for p in group["params"]]
        out[name] = [dict(opt.state.get(p, {})) for p in params]
    return out


def _stack_optimizer_states(lead: nn.Module, states: list[dict[str, list[dict]]]) -> None:
    for name, opt in _optimizers(lead).items():
        params = [p for group in opt.param_groups for p in group["params"]]
        for i, p in enumerate(params):
            per_member = [s[name][i] for s in states]
            if not per_member[0]:
                continue
            opt.state[p] = {key: _stack_state_value(key, [s[key] for s in per_member]) for key in per_member[0]}


def _stack_state_value(key: str, values: list):
    if key == "step":  # lockstep: one count for all members
        if any(float(v) != float(values[0]) for v in values):
            raise ValueError("the members of a group must have made the same number of updates")
        return values[0].clone() if isinstance(values[0], torch.Tensor) else values[0]
    return torch.stack([v.detach() for v in values])


def member_optimizer_state(state: dict, k: int) -> dict:
    """Member k's slice of a stacked optimiser ``state_dict``."""
    return {"param_groups": state["param_groups"],
            "state": {i: {key: (v if key == "step" else v[k].clone()) for key, v in s.items()}
                      for i, s in state["state"].items()}}


def member_slice(state, k: int):
    """Member k's part of a group's nested state (dicts of stacked tensors and optimiser state
    dicts, as a training state or a fine-tuner's resumable state holds them)."""
    if isinstance(state, dict):
        if "param_groups" in state and "state" in state:
            return member_optimizer_state(state, k)
        return {key: member_slice(value, k) for key, value in state.items()}
    return state[k].clone() if isinstance(state, torch.Tensor) else state


def member_training_state(agent: Learner, k: int) -> dict:
    """Member k's :meth:`~dvfb.nets.learner.Learner.training_state`, as its separate run holds it."""
    return member_slice(agent.training_state(), k)


def drop_members(agent: Learner, keep: list[int]) -> None:
    """Keep only the members ``keep`` (indices, in order) of a stacked learner, in place: what a
    group does when one member stops (a non-finite loss); the others continue unchanged."""
    index = torch.as_tensor(keep, dtype=torch.long)
    for owner, kind, name in list(_tensor_slots(agent)):
        tensor = getattr(owner, kind)[name]
        if kind == "_parameters":
            tensor.data = tensor.data[index.to(tensor.device)].clone()
        else:
            owner._buffers[name] = tensor[index.to(tensor.device)].clone()
    for opt in _optimizers(agent).values():
        for state in opt.state.values():
            for key, value in list(state.items()):
                if key != "step" and isinstance(value, torch.Tensor):
                    state[key] = value[index.to(value.device)].clone()
    for module in _with_model(agent):
        module.members = len(keep)
    agent.use_generator(MemberGenerators(agent.generator[i] for i in keep))


# Ensembles ---------------------------------------------------------------------------------------
# An ensemble is E networks of one architecture inside one agent (FBEE's forward maps), stacked as
# a group stacks its members: one batched product per layer for all of them. Its layers read the
# stacked axes from their own weights, so that the ensemble of a group's member (weights
# ``(M, E, ...)``) runs as M*E networks on inputs ``(M*E, N, in)`` with no code of its own.

class EnsembleLinear(nn.Linear):
    """E stacked ``nn.Linear`` (weights ``(..., E, out, in)``): inputs ``(C, N, in)`` with C the
    number of stacked networks (E, or M*E in a group), one batched product."""

    members: int = 0  # set by a group's stacking; the stacked axes are read from the weight

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        weight = self.weight.reshape(-1, *self.weight.shape[-2:])
        bias = None if self.bias is None else self.bias.reshape(-1, self.bias.shape[-1])
        return _RowProducts.apply(x, weight, bias)


class EnsembleLayerNorm(nn.LayerNorm):
    """E stacked ``nn.LayerNorm`` over the last axis (affine ``(..., E, width)``): inputs ``(C, N, width)``."""

    members: int = 0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F_nn.layer_norm(x, self.normalized_shape, None, None, self.eps)
        if self.weight is None:
            return out
        width = self.weight.shape[-1]
        return out * self.weight.reshape(-1, 1, width) + self.bias.reshape(-1, 1, width)


ENSEMBLE_CLASSES = {nn.Linear: EnsembleLinear, nn.LayerNorm: EnsembleLayerNorm}


def stack_ensemble(networks: list[nn.Module]) -> nn.Module:
    """One network that runs ``networks`` (one architecture, each initialised on its own) as a
    stack: the first, modified in place. It takes inputs ``(C, N, ...)``, network c's rows at c."""
    lead = networks[0]
    _stack_tensors(networks, "the networks of an ensemble must have one architecture")
    for module in lead.modules():
        cls = ENSEMBLE_CLASSES.get(type(module))
        if cls is not None:
            module.__class__ = cls
        elif hasattr(module, "members") and not isinstance(module, (EnsembleLinear, EnsembleLayerNorm)):
            module.members = len(networks)  # blocks with their own stacked path (TwinHead)
    return lead
