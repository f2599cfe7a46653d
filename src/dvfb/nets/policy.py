"""The policy (docs/methods.md §3.3, §4.1): its sampling helpers, the actor ``mu(s, z)`` and
:class:`HostActor`, the actor's numpy twin for acting at batch 1 on the CPU."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from dvfb.nets.members import MemberGenerators, randn
from dvfb.nets.layers import full_precision, layernorm_tanh_layer, mlp, orthogonal_init_

# Actions are clamped strictly inside the box so that tanh-space quantities stay finite (§3.3).
ACTION_EPS = 1e-6


def standard_normal(like: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """N(0, 1) noise shaped like ``like``, from ``generator`` (None: torch's global stream, with the
    same values ``randn_like`` gives)."""
    if generator is None:
        return torch.randn_like(like)
    if isinstance(generator, MemberGenerators):  # a group: member k draws its own slice
        return randn(like.shape[1:], generator, like.device, like.dtype)
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

    def __init__(self, actor: Actor, member: int | None = None):
        # member: member k's slice of a group's stacked actor (docs/members.md), evaluated exactly
        # as its separate run's actor is.
        self.actor, self.member = actor, member
        self._params = list(actor.parameters())
        if any(p.device.type != "cpu" or p.dtype != torch.float32 for p in self._params):
            raise ValueError("HostActor needs a float32 actor on the CPU")
        self._storage: tuple[int, ...] = ()
        self._bind()

    def _bind(self) -> None:
        actor = self.actor
        if actor.encoder is not None:
            self._streams = (_host_layers(actor.encoder.first, self.member),
                             _host_layers(actor.encoder.second, self.member))
        else:
            self._streams = None
        self._head = _host_layers(actor.head, self.member)
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


def _host_layers(seq: nn.Sequential, member: int | None = None) -> list[tuple]:
    """(kind, numpy views...) per layer of an MLP built from Linear/LayerNorm/Tanh/ReLU."""
    layers: list[tuple] = []

    def view(param: torch.Tensor) -> np.ndarray:
        array = param.detach().numpy()
        return array if member is None else array[member]

    for module in seq:
        if isinstance(module, nn.Linear):
            # weight.T is a transposed view; BLAS reads it without a copy.
            layers.append(("linear", view(module.weight).T, view(module.bias)))
        elif isinstance(module, nn.LayerNorm):
            (width,) = module.normalized_shape
            layers.append(("layer_norm", view(module.weight), view(module.bias),
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
