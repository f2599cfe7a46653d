"""Tiny network sizes and configs shared by the agent and network tests (fast on one CPU thread)."""

from dvfb.agents.dvfb import ExplorationConfig
from dvfb.agents.fb import FBConfig

OBS, ACT, D, H, E = 5, 3, 8, 32, 16


def tiny_config(**overrides) -> FBConfig:
    """An FBConfig with the tiny widths (z_dim D, hidden H, feature E) and a batch of 32."""
    kw = dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32)
    kw.update(overrides)
    return FBConfig(**kw)


def tiny_exploration(**overrides) -> ExplorationConfig:
    """An ExplorationConfig with tiny RND / contrastive widths and k = 4 neighbours."""
    kw = dict(rnd_rep_dim=16, contrastive_hidden_dim=32, ce_k=4)
    kw.update(overrides)
    return ExplorationConfig(**kw)
