"""Agents: one module per method, each registering its :class:`~dvfb.agents.registry.AgentSpec`.

A method is a model (:class:`~dvfb.agents.base.Model`: what a pre-trained agent is used with) and a
learner (:class:`~dvfb.agents.base.Agent`: how it is trained without rewards). The layers above use
them only through those interfaces and the registry (:func:`make_agent`, :func:`make_model`,
:func:`get_spec`). Importing this package registers every method: a new method adds one import line
below (docs/adding_a_method.md).
"""

from __future__ import annotations

import torch

from dvfb.agents.base import Agent, Model, ReplayNeeds, TrainingSettings
from dvfb.agents.registry import AGENTS, AgentSpec, agent_names, get_spec, register

# Registration: one line per method.
from dvfb.agents import fb  # noqa: E402,F401  (also registers the FB fine-tuner)
from dvfb.agents import dvfb  # noqa: E402,F401
from dvfb.agents import rnd  # noqa: E402,F401
from dvfb.agents import disagreement  # noqa: E402,F401
from dvfb.agents import icm_apt  # noqa: E402,F401
from dvfb.agents import proto  # noqa: E402,F401
from dvfb.agents import diayn  # noqa: E402,F401
from dvfb.agents import aps  # noqa: E402,F401
from dvfb.agents import smm  # noqa: E402,F401
from dvfb.agents import cic  # noqa: E402,F401
from dvfb.agents import becl  # noqa: E402,F401
from dvfb.agents import comsd  # noqa: E402,F401
from dvfb.agents import cesd  # noqa: E402,F401
from dvfb.agents import sf  # noqa: E402,F401
from dvfb.agents import conservative_fb  # noqa: E402,F401
from dvfb.agents import fbee  # noqa: E402,F401
from dvfb.agents import supervised  # noqa: E402,F401

from dvfb.agents.dvfb import DVFBAgent, ExplorationConfig  # noqa: E402
from dvfb.agents.fb import FBAgent, FBConfig  # noqa: E402
from dvfb.nets.execution import PerfConfig  # noqa: E402


def make_agent(name: str, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu") -> Agent:
    """Build the learner of the registered method ``name`` from a run config (its sections and ``perf``)."""
    return get_spec(name).agent_cls.from_config(obs_dim, action_dim, config, device)


def make_model(name: str, obs_dim: int, action_dim: int, config, device: str | torch.device = "cpu") -> Model:
    """Build the model of the registered method ``name`` alone (no optimiser): what a snapshot loads into."""
    return get_spec(name).agent_cls.model_from_config(obs_dim, action_dim, config, device)


__all__ = ["AGENTS", "Agent", "AgentSpec", "DVFBAgent", "ExplorationConfig", "FBAgent", "FBConfig", "Model", "PerfConfig",
           "ReplayNeeds", "TrainingSettings", "agent_names", "get_spec", "make_agent", "make_model", "register"]
