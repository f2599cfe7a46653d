"""Layers and their plumbing, written once for every method (docs/methods.md §3, "Shared blocks"):
initialisation, EMA targets, freezing, the optimiser, the twin TD loss, MLPs with the LNT first
layer, and :class:`TwinHead` (K heads as one wide and one batched matrix product)."""

from __future__ import annotations

import copy

import torch
from torch import nn
from torch.nn import functional as F_nn


def full_precision(x: torch.Tensor) -> torch.Tensor:
    """``x`` as float32 if it is in a 16-bit float format (autocast output), else ``x`` itself."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


def call_network(net: nn.Module, *inputs: torch.Tensor) -> torch.Tensor:
    """``net(*inputs)``: the default way of calling a network where a caller may pass another
    (e.g. an agent's :class:`~dvfb.nets.execution.NetRunner`, for precision and compilation)."""
    return net(*inputs)


def orthogonal_init_(module: nn.Module) -> nn.Module:
    """Orthogonal weights with gain 1 and zero biases for every layer (§3.2).

    LayerNorm keeps weight 1 / bias 0. :class:`TwinHead` members are initialised independently,
    as K separate Linear layers would be.
    """
    # A TwinHead's fused first layer holds K stacked member blocks: initialising it as one matrix
    # would make only the stack orthogonal, not each member, so it is left to reset_parameters().
    twin_first = {id(sub.first) for sub in module.modules() if isinstance(sub, TwinHead)}
    for sub in module.modules():
        if isinstance(sub, nn.Linear) and id(sub) not in twin_first:
            nn.init.orthogonal_(sub.weight, gain=1.0)
            if sub.bias is not None:
                nn.init.zeros_(sub.bias)
        elif isinstance(sub, TwinHead):
            sub.reset_parameters()
    return module


def make_target(online: nn.Module) -> nn.Module:
    """An exact, gradient-free copy of ``online`` to be tracked by :func:`soft_update_`."""
    target = copy.deepcopy(online)
    for p in target.parameters():
        p.requires_grad_(False)
    return target


@torch.no_grad()
def soft_update_(target: nn.Module, online: nn.Module, tau: float) -> None:
    """EMA ``theta_target <- tau * theta + (1 - tau) * theta_target`` (§3.5), one fused call."""
    torch._foreach_lerp_(list(target.parameters()), list(online.parameters()), tau)


def freeze_(module: nn.Module) -> nn.Module:
    for p in module.parameters():
        p.requires_grad_(False)
    return module


# ---------------------------------------------------------------------------------------------
# Optimisation and TD losses (shared by every agent and fine-tuner)


def adam(params, lr: float, fused: bool) -> torch.optim.Adam:
    """Adam with default betas/eps and no weight decay (§3.6); fused when asked and possible."""
    params = list(params)
    if fused:
        try:
            return torch.optim.Adam(params, lr=lr, fused=True)
        except (RuntimeError, TypeError):  # pragma: no cover - backend without fused Adam
            pass
    return torch.optim.Adam(params, lr=lr, foreach=True)


def twin_td_loss(q: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Sum over the K heads of the mean squared TD error: ``q`` is ``(K, N, 1)``, ``target`` ``(N, 1)``
    (a group: ``(M, K, N, 1)`` and ``(M, N, 1)``, one loss per member, ``(M,)``).

    The critic loss of DVFB's exploration critic, of the fine-tuning task critic and of the DDPG
    core (docs/methods.md, "Shared blocks").
    """
    return (q - target.unsqueeze(-3)).pow(2).mean(dim=(-2, -1)).sum(-1)


# ---------------------------------------------------------------------------------------------
# MLPs


def layernorm_tanh_layer(in_dim: int, out_dim: int) -> nn.Sequential:
    """The "LNT" block that starts every input stream: Linear -> LayerNorm -> Tanh (§3.1)."""
    return nn.Sequential(nn.Linear(in_dim, out_dim), nn.LayerNorm(out_dim), nn.Tanh())


def mlp(*dims: int, first_layer_lnt: bool = False, output_activation: nn.Module | None = None
        ) -> nn.Sequential:
    """An MLP ``dims[0] -> ... -> dims[-1]`` with ReLU between layers.

    With ``first_layer_lnt`` the first layer is an LNT block (its Tanh replaces the ReLU).
    """
    if len(dims) < 2:
        raise ValueError("mlp needs at least an input and an output size")
    layers: list[nn.Module] = []
    for i, (d_in, d_out) in enumerate(zip(dims[:-1], dims[1:])):
        last = i == len(dims) - 2
        if i == 0 and first_layer_lnt:
            layers.extend(layernorm_tanh_layer(d_in, d_out))
            continue
        layers.append(nn.Linear(d_in, d_out))
        if not last:
            # In place: a Linear's backward does not need its output, so this saves one
            # activation-sized allocation and write per layer at no change in the math.
            layers.append(nn.ReLU(inplace=True))
    if output_activation is not None:
        layers.append(output_activation)
    return nn.Sequential(*layers)


TWIN_HEAD_INITS = ("orthogonal", "default")


class TwinHead(nn.Module):
    """K independent two-layer heads ``in -> hidden -> ReLU -> out`` on a shared input.

    The first layers of all heads are one ``(in, K*hidden)`` matrix product; the second layers are
    one batched product. Output shape: ``(K, N, out)``. Mathematically identical to K separate
    ``Linear -> ReLU -> Linear`` heads (tested in tests/test_nets.py).
    """

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, num_heads: int = 2, init: str = "orthogonal"):
        super().__init__()
        if init not in TWIN_HEAD_INITS:
            raise ValueError(f"init must be one of {TWIN_HEAD_INITS}, got {init!r}")
        self.in_dim, self.hidden_dim, self.out_dim, self.num_heads = in_dim, hidden_dim, out_dim, num_heads
        self.init = init
        self.first = nn.Linear(in_dim, num_heads * hidden_dim)
        self.second_weight = nn.Parameter(torch.empty(num_heads, hidden_dim, out_dim))
        self.second_bias = nn.Parameter(torch.empty(num_heads, 1, out_dim))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Each member as its own pair of Linear layers: orthogonal weights and zero biases, or
        (``init="default"``) PyTorch's default Linear initialisation (the URLB ensembles)."""
        if self.init == "default":
            self._reset_default()
            return
        with torch.no_grad():
            for k in range(self.num_heads):
                rows = slice(k * self.hidden_dim, (k + 1) * self.hidden_dim)
                block = torch.empty(self.hidden_dim, self.in_dim)
                nn.init.orthogonal_(block)
                self.first.weight[rows].copy_(block)
                member = torch.empty(self.out_dim, self.hidden_dim)
                nn.init.orthogonal_(member)
                self.second_weight[k].copy_(member.t())
            self.first.bias.zero_()
            self.second_bias.zero_()

    def _reset_default(self) -> None:
        with torch.no_grad():
            for k in range(self.num_heads):
                rows = slice(k * self.hidden_dim, (k + 1) * self.hidden_dim)
                first, second = nn.Linear(self.in_dim, self.hidden_dim), nn.Linear(self.hidden_dim, self.out_dim)
                self.first.weight[rows].copy_(first.weight)
                self.first.bias[rows].copy_(first.bias)
                self.second_weight[k].copy_(second.weight.t())
                self.second_bias[k, 0].copy_(second.bias)

    members: int = 0  # a group's stacked heads (dvfb.nets.members): inputs (M, N, in), outputs (M, K, N, out)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        hidden = F_nn.relu(self.first(h), inplace=True)  # (N, K*H); in place: see mlp()
        if self.members:
            m, n = h.shape[0], h.shape[1]
            k = m * self.num_heads  # every (member, head) pair as one head: the ordinary baddbmm's shapes
            hidden = hidden.view(m, n, self.num_heads, self.hidden_dim).transpose(1, 2).reshape(k, n, self.hidden_dim)
            out = torch.baddbmm(self.second_bias.reshape(k, 1, self.out_dim), hidden,
                                self.second_weight.reshape(k, self.hidden_dim, self.out_dim))
            return out.view(m, self.num_heads, n, self.out_dim)  # (M, K, N, out)
        n = h.shape[0]
        hidden = hidden.view(n, self.num_heads, self.hidden_dim).transpose(0, 1)  # (K, N, H)
        return torch.baddbmm(self.second_bias, hidden, self.second_weight)
