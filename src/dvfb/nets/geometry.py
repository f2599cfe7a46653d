"""Geometry of the skill vectors z (docs/methods.md §5.1): the sphere projection and the prior."""

from __future__ import annotations

import math

import torch

from dvfb.nets.members import randn

# Numerical floor of the norm in the sphere projection (docs/methods.md conventions).
NORM_FLOOR = 1e-12


def project_to_sphere(v: torch.Tensor) -> torch.Tensor:
    """``proj(v) = sqrt(d) * v / ||v||`` row-wise, with the norm floored at 1e-12."""
    d = v.shape[-1]
    norm = v.norm(dim=-1, keepdim=True).clamp_min(NORM_FLOOR)
    return math.sqrt(d) * v / norm


def sample_z_prior(n: int, z_dim: int, device: torch.device | str = "cpu",
                   generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` draws uniform on the sphere of radius sqrt(z_dim) (§5.1, norm_z = true)."""
    g = randn((n, z_dim), generator, device)  # a group's MemberGenerators: (M, n, z_dim)
    return project_to_sphere(g)
