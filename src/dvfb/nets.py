"""Shared network building blocks (docs/methods.md §3-§5).

Every method in :mod:`dvfb.agents` builds its networks from the pieces here, so that an MLP, a twin
head or an EMA target is written once:

* :func:`mlp` and :func:`layernorm_tanh_layer` -- the "LNT" first layer (Linear, LayerNorm, Tanh)
  followed by ReLU layers (§3.1);
* :class:`TwinHead` -- K independent heads on a shared input, evaluated as one wide matrix product
  plus one batched matrix product instead of K separate MLPs (§4.2, §4.4, D13);
* :class:`ForwardMap`, :class:`BackwardMap`, :class:`Actor`, :class:`TwinCritic` (§4.1-§4.4);
* the policy distribution helpers (§3.3), sphere projection and the z prior (§5.1);
* :func:`orthogonal_init_`, :func:`soft_update_` (EMA, §3.5) and :class:`RunningMeanStd` (§3.4);
* :func:`adam` and :func:`twin_td_loss`, the optimiser and critic loss of every agent.

The intrinsic-reward networks (RND, contrastive encoders, ...) live in :mod:`dvfb.rewards`.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F_nn

# Actions are clamped strictly inside the box so that tanh-space quantities stay finite (§3.3).
ACTION_EPS = 1e-6
# Numerical floor of the norm in the sphere projection (docs/methods.md conventions).
NORM_FLOOR = 1e-12


# ---------------------------------------------------------------------------------------------
# Initialisation and targets


def full_precision(x: torch.Tensor) -> torch.Tensor:
    """``x`` as float32 if it is in a 16-bit float format (autocast output), else ``x`` itself."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


def call_network(net: nn.Module, *inputs: torch.Tensor) -> torch.Tensor:
    """``net(*inputs)``: the default way of calling a network where a caller may pass another
    (e.g. an agent's :class:`~dvfb.agents.perf.NetRunner`, for precision and compilation)."""
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
    """Sum over the K heads of the mean squared TD error: ``q`` is ``(K, N, 1)``, ``target`` ``(N, 1)``.

    The critic loss of DVFB's exploration critic, of the fine-tuning task critic and of the DDPG
    core (docs/methods.md, "Shared blocks").
    """
    return (q - target).pow(2).mean(dim=(1, 2)).sum()


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

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        n = h.shape[0]
        hidden = F_nn.relu(self.first(h), inplace=True)  # (N, K*H); in place: see mlp()
        hidden = hidden.view(n, self.num_heads, self.hidden_dim).transpose(0, 1)  # (K, N, H)
        return torch.baddbmm(self.second_bias, hidden, self.second_weight)


# ---------------------------------------------------------------------------------------------
# Geometry of z


def project_to_sphere(v: torch.Tensor) -> torch.Tensor:
    """``proj(v) = sqrt(d) * v / ||v||`` row-wise, with the norm floored at 1e-12."""
    d = v.shape[-1]
    norm = v.norm(dim=-1, keepdim=True).clamp_min(NORM_FLOOR)
    return math.sqrt(d) * v / norm


def sample_z_prior(n: int, z_dim: int, device: torch.device | str = "cpu",
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` draws uniform on the sphere of radius sqrt(z_dim) (§5.1, norm_z = true)."""
    g = torch.randn(n, z_dim, device=device, generator=generator)
    return project_to_sphere(g)


# ---------------------------------------------------------------------------------------------
# Policy distribution (§3.3)


def standard_normal(like: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """N(0, 1) noise shaped like ``like``, from ``generator`` (None: torch's global stream, with the
    same values ``randn_like`` gives)."""
    if generator is None:
        return torch.randn_like(like)
    return torch.randn(like.shape, generator=generator, device=like.device, dtype=like.dtype)


def rollout_action(mean: torch.Tensor, std: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Data-collection sample: ``clamp(mu + sigma*eps)`` with unclipped noise."""
    noise = standard_normal(mean, generator) * std
    return (mean + noise).clamp(-1 + ACTION_EPS, 1 - ACTION_EPS)


def training_action(mean: torch.Tensor, std: float, noise_clip: float,
                    generator: torch.Generator | None = None) -> torch.Tensor:
    """Reparameterised training sample with noise clipped at ``noise_clip``.

    The outer clamp is straight-through: the value is clamped, the gradient w.r.t. ``mean`` is 1.
    """
    noise = (standard_normal(mean, generator) * std).clamp(-noise_clip, noise_clip)
    raw = mean + noise
    clamped = raw.clamp(-1 + ACTION_EPS, 1 - ACTION_EPS)
    return raw + (clamped - raw).detach()


# ---------------------------------------------------------------------------------------------
# Networks of the FB family (§4)


class TwoStreamEncoder(nn.Module):
    """Two input streams, ``LNT(in_k -> H) -> Linear(H -> E) -> ReLU`` each, concatenated (§4.1)."""

    def __init__(self, first_dim: int, second_dim: int, hidden_dim: int, feature_dim: int):
        super().__init__()
        self.first = nn.Sequential(*layernorm_tanh_layer(first_dim, hidden_dim),
                                   nn.Linear(hidden_dim, feature_dim), nn.ReLU(inplace=True))
        self.second = nn.Sequential(*layernorm_tanh_layer(second_dim, hidden_dim),
                                    nn.Linear(hidden_dim, feature_dim), nn.ReLU(inplace=True))
        self.out_dim = 2 * feature_dim

    def forward(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.first(first), self.second(second)], dim=-1)


class Actor(nn.Module):
    """z-conditioned deterministic mean ``mu(s, z)`` in (-1, 1) (§4.1).

    ``arch = "two_stream"``: streams ``[s]`` and ``[s, z]``, head ``2E -> H -> U``.
    ``arch = "mlp"``: Table 4's plain MLP ``[s, z] -> LNT(H) -> H -> U``.
    """

    def __init__(self, obs_dim: int, z_dim: int, action_dim: int, hidden_dim: int,
                 feature_dim: int, arch: str = "two_stream"):
        super().__init__()
        self.arch = arch
        if arch == "two_stream":
            self.encoder = TwoStreamEncoder(obs_dim, obs_dim + z_dim, hidden_dim, feature_dim)
            self.head = mlp(self.encoder.out_dim, hidden_dim, action_dim)
        elif arch == "mlp":
            self.encoder = None
            self.head = mlp(obs_dim + z_dim, hidden_dim, hidden_dim, action_dim, first_layer_lnt=True)
        else:
            raise ValueError(f"unknown actor_arch {arch!r}; expected 'two_stream' or 'mlp'")
        orthogonal_init_(self)

    def forward(self, obs: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        obs_z = torch.cat([obs, z], dim=-1)
        h = self.encoder(obs, obs_z) if self.encoder is not None else obs_z
        return torch.tanh(full_precision(self.head(h)))  # float32 output under bf16 autocast too


class HostActor:
    """The mean ``mu(s, z)`` of a CPU :class:`Actor` for one observation, evaluated with numpy.

    Acting needs one actor forward per environment step at batch 1, where torch's per-module and
    per-operator dispatch costs several times the arithmetic (docs/methods.md §7.1 acts every step).
    This evaluator runs the same layers as plain numpy calls on zero-copy views of the actor's
    parameters: optimiser steps and ``load_state_dict`` write those tensors in place, so the views
    always see the current weights, and the result equals ``Actor.forward`` up to float32 rounding
    (tests/test_nets.py). If a parameter's storage is ever replaced (``.to()``, ``.data = ...``),
    the views are rebuilt on the next call. CPU float32 only.
    """

    def __init__(self, actor: Actor):
        self.actor = actor
        self._params = list(actor.parameters())
        if any(p.device.type != "cpu" or p.dtype != torch.float32 for p in self._params):
            raise ValueError("HostActor needs a float32 actor on the CPU")
        self._storage: tuple[int, ...] = ()
        self._bind()

    def _bind(self) -> None:
        actor = self.actor
        if actor.encoder is not None:
            self._streams = (_host_layers(actor.encoder.first), _host_layers(actor.encoder.second))
        else:
            self._streams = None
        self._head = _host_layers(actor.head)
        self._storage = self._storage_key()

    def _storage_key(self) -> tuple[int, ...]:
        return tuple(p.data_ptr() for p in self._params)

    def __call__(self, obs: np.ndarray, z: np.ndarray) -> np.ndarray:
        """``tanh(head(...))`` for a single ``obs`` (O,) and ``z`` (d,): the action mean (U,)."""
        if self._storage != self._storage_key():
            self._bind()
        obs = np.asarray(obs, dtype=np.float32)
        obs_z = np.concatenate([obs, np.asarray(z, dtype=np.float32)])
        if self._streams is None:
            h = _run_host_layers(self._head, obs_z)
        else:
            first, second = self._streams
            h = np.concatenate([_run_host_layers(first, obs), _run_host_layers(second, obs_z)])
            h = _run_host_layers(self._head, h)
        return np.tanh(h, out=h)


def _host_layers(seq: nn.Sequential) -> list[tuple]:
    """(kind, numpy views...) per layer of an MLP built from Linear/LayerNorm/Tanh/ReLU."""
    layers: list[tuple] = []
    for module in seq:
        if isinstance(module, nn.Linear):
            # weight.T is a transposed view; BLAS reads it without a copy.
            layers.append(("linear", module.weight.detach().numpy().T, module.bias.detach().numpy()))
        elif isinstance(module, nn.LayerNorm):
            (width,) = module.normalized_shape
            layers.append(("layer_norm", module.weight.detach().numpy(), module.bias.detach().numpy(),
                           float(module.eps), np.float32(1.0 / width)))
        elif isinstance(module, nn.Tanh):
            layers.append(("tanh",))
        elif isinstance(module, nn.ReLU):
            layers.append(("relu",))
        else:
            raise TypeError(f"HostActor cannot evaluate a {type(module).__name__} layer")
    return layers


def _run_host_layers(layers: list[tuple], x: np.ndarray) -> np.ndarray:
    for layer in layers:
        kind = layer[0]
        if kind == "linear":
            x = x @ layer[1]
            x += layer[2]
        elif kind == "layer_norm":
            # Scalars stay Python/numpy scalars: each array call costs ~1 us at this size.
            x -= x.sum() * layer[4]
            var = float(np.dot(x, x) * layer[4])  # biased variance, as nn.LayerNorm
            x *= np.float32(1.0 / math.sqrt(var + layer[3]))
            x *= layer[1]
            x += layer[2]
        elif kind == "tanh":
            np.tanh(x, out=x)
        else:
            np.maximum(x, 0.0, out=x)
    return x


class ForwardMap(nn.Module):
    """``F_k(s, a, z)``, k = 1..num_heads, on shared ``[s, a]`` and ``[s, z]`` streams (§4.2).

    Returns ``(K, N, d)``. The skill value is ``Q_M,k = F_k . z`` (:func:`skill_values`).
    """

    def __init__(self, obs_dim: int, action_dim: int, z_dim: int, hidden_dim: int,
                 feature_dim: int, num_heads: int = 2):
        super().__init__()
        self.encoder = TwoStreamEncoder(obs_dim + action_dim, obs_dim + z_dim, hidden_dim, feature_dim)
        self.heads = TwinHead(self.encoder.out_dim, hidden_dim, z_dim, num_heads)
        orthogonal_init_(self)

    def forward(self, obs: torch.Tensor, action: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        h = self.encoder(torch.cat([obs, action], dim=-1), torch.cat([obs, z], dim=-1))
        return self.heads(h)


def skill_values(forward_out: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """``Q_M,k = F_k . z`` for every head: ``(K, N, d), (N, d) -> (K, N)``."""
    return (forward_out * z.unsqueeze(0)).sum(-1)


class BackwardMap(nn.Module):
    """``B(x) = proj(MLP(x))`` with ``||B(x)|| = sqrt(d)`` (§4.3).

    ``input_dim`` is O in ``state`` mode and 2*O in ``transition`` / ``code_exact`` modes.
    """

    def __init__(self, input_dim: int, hidden_dim: int, z_dim: int):
        super().__init__()
        self.net = mlp(input_dim, hidden_dim, hidden_dim, z_dim, first_layer_lnt=True)
        orthogonal_init_(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The projection is a reduction: float32 even under bf16 autocast.
        return project_to_sphere(full_precision(self.net(x)))


class TwinCritic(nn.Module):
    """``Q_k(s, a, z)``: a shared ``LNT([s, z, a] -> H)`` trunk and K heads ``H -> H -> 1`` (§4.4).

    Used for the exploration critic Q_P (pre-training), the task critic Q_F (fine-tuning) and the
    DDPG core. Returns ``(K, N, out_dim)``.
    """

    def __init__(self, obs_dim: int, action_dim: int, z_dim: int, hidden_dim: int, num_heads: int = 2,
                 out_dim: int = 1):
        super().__init__()
        self.trunk = layernorm_tanh_layer(obs_dim + z_dim + action_dim, hidden_dim)
        # out_dim > 1: successor features psi_k (APS), whose values are psi_k . w (the caller's).
        self.heads = TwinHead(hidden_dim, hidden_dim, out_dim, num_heads)
        orthogonal_init_(self)

    def forward(self, obs: torch.Tensor, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.heads(self.trunk(torch.cat([obs, z, action], dim=-1)))


# ---------------------------------------------------------------------------------------------
# Running statistics (§3.4)


class RunningMeanStd(nn.Module):
    """Scalar running mean and variance with the (0, 1, 1e-4) prior of §3.4.

    State lives in buffers on the module's device; :meth:`update` never syncs with the host.
    """

    def __init__(self, epsilon_count: float = 1e-4):
        super().__init__()
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("var", torch.ones((), dtype=torch.float64))
        self.register_buffer("count", torch.full((), epsilon_count, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fold in a batch (Bessel-corrected batch variance) and return the new ``(mean, var)``."""
        x = x.detach().reshape(-1).double()
        b = x.numel()
        batch_mean = x.mean()
        batch_var = x.var(unbiased=True) if b > 1 else torch.zeros_like(batch_mean)
        n = self.count
        total = n + b
        delta = batch_mean - self.mean
        self.mean.add_(delta * b / total)
        self.var.copy_((self.var * n + batch_var * b + delta.pow(2) * n * b / total) / total)
        self.count.add_(b)
        return self.mean, self.var
