"""The run's random streams: seeding, and their state for exact resume.

A run seeds torch, Python and a numpy ``Generator`` from its seed; a resume checkpoint keeps all
of them (and CUDA's) so that the resumed run draws exactly what the uninterrupted one would.
"""

from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int) -> np.random.Generator:
    """Seed torch and Python; return the numpy Generator the workflow draws uniform actions from."""
    torch.manual_seed(seed)
    random.seed(seed)
    return np.random.default_rng(seed)



def rng_state(generator: np.random.Generator) -> dict:
    return {"torch": torch.get_rng_state(), "python": random.getstate(),
            "numpy": generator.bit_generator.state,
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def restore_rng_state(state: dict, generator: np.random.Generator) -> None:
    torch.set_rng_state(state["torch"])
    random.setstate(state["python"])
    generator.bit_generator.state = state["numpy"]
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def run_generator(seed: int, device: torch.device | str) -> torch.Generator:
    """The run's own torch stream on its device, seeded from the run's seed: every draw of its agent
    and batches comes from it, never from torch's global generator."""
    return torch.Generator(device=device).manual_seed(seed)
