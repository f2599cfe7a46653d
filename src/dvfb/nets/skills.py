"""What a method's skill is, declared once by the agent (docs/methods.md, "Skills").

A :class:`SkillSpec` says everything the layers above the agents need to know about a skill:

* its **kind** -- ``none`` (a single policy), ``one_hot`` (one of ``dim`` discrete skills),
  ``sphere`` (a continuous vector on the sphere of radius ``radius``), ``box`` (uniform in
  ``[low, high]^dim``) or ``method`` (the agent draws it itself, :meth:`dvfb.agents.base.Agent.sample_skill`);
* its **width** ``dim`` (what the actor is conditioned on and the replay stores);
* its **prior** (the kind and its parameters);
* its **resampling rule** during pre-training: a new draw when the global step counter is a
  multiple of ``every`` (None: never on a schedule) and, with ``at_episode_start``, at every reset.

The training loop, the zero-shot protocols and the fine-tuners draw, store and pass skills only
through this declaration; none of them knows which method it serves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dvfb.nets import project_to_sphere
from dvfb.nets.members import rand, randint, randn

SKILL_KINDS = ("none", "one_hot", "sphere", "box", "method")


@dataclass(frozen=True)
class SkillSpec:
    """A method's skill: kind, width, prior and resampling rule (see the module docstring)."""

    kind: str = "none"
    dim: int = 0
    every: int | None = None
    at_episode_start: bool = True
    radius: float | None = None  # sphere: None means sqrt(dim) (FB's convention)
    low: float = 0.0  # box
    high: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in SKILL_KINDS:
            raise ValueError(f"skill kind must be one of {SKILL_KINDS}, got {self.kind!r}")
        if (self.kind == "none") != (self.dim == 0):
            raise ValueError(f"a {self.kind!r} skill cannot have width {self.dim}")
        if self.every is not None and self.every < 1:
            raise ValueError(f"skill resampling period must be at least 1, got {self.every}")

    @property
    def has_skill(self) -> bool:
        return self.kind != "none"

    def due(self, step: int, episode_start: bool) -> bool:
        """Whether the rollout skill is redrawn before acting at ``step``."""
        if not self.has_skill:
            return False
        if episode_start and self.at_episode_start:
            return True
        return self.every is not None and step % self.every == 0

    def sample(self, n: int, device: torch.device | str = "cpu",
               generator: torch.Generator | None = None) -> torch.Tensor | None:
        """``n`` draws of the prior, ``(n, dim)`` float32; None for ``kind="none"``.

        ``method`` skills have no generic prior: the agent draws them. A group's
        :class:`~dvfb.nets.members.MemberGenerators` give ``(M, n, dim)``, member k's from its stream.
        """
        if self.kind == "none":
            return None
        if self.kind == "one_hot":
            index = randint(0, self.dim, (n,), generator, device)
            return torch.nn.functional.one_hot(index, self.dim).to(torch.float32)
        if self.kind == "sphere":
            draw = project_to_sphere(randn((n, self.dim), generator, device))
            if self.radius is not None:
                draw = draw * (self.radius / math.sqrt(self.dim))
            return draw
        if self.kind == "box":
            u = rand((n, self.dim), generator, device)
            return self.low + (self.high - self.low) * u
        raise ValueError("a 'method' skill is drawn by its agent (Agent.sample_skill)")


NO_SKILL = SkillSpec()


def skill_index(skill: torch.Tensor) -> torch.Tensor:
    """The index of each one-hot skill row, ``(N,)`` (discriminator targets, ensemble heads)."""
    return skill.argmax(dim=-1)
