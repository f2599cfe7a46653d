"""Zero-shot evaluation while pre-training (``--eval-every``; docs/health.md): every ``eval_every``
frames, the current networks are evaluated on the domain's tasks by the method's registered
protocol on small budgets, so that a run says whether it learns long before it ends.

* **What is evaluated.** The model a snapshot at that step would hold, built in memory from the
  learner's current modules (no file is written). For the methods that infer their skill from
  rewards (the FB family, the successor features), ``z_r`` comes from the newest
  ``eval_samples`` pre-training transitions, which the evaluation keeps with their physics states
  so that each task's reward is computed on them exactly (the relabelling that datasets use,
  docs/methods.md, "Datasets"); the skill-discovery methods run their skill selection for
  ``eval_skill_steps`` reward-labelled steps; methods without skills act with their one policy.
  Then ``eval_episodes`` mean-action episodes per task, the tasks in lockstep (one batched forward
  per step).
* **Training is unchanged by it.** The evaluation has its own random streams (derived from the run's
  seed and the step, so that a resumed run evaluates exactly as the uninterrupted one), its own
  environments and its own copy of the networks; torch's and Python's global generators are left as
  they were. The training replay is not read.
* **Where it goes.** One record per task in ``metrics/eval.jsonl`` (step, task, return and its
  standard deviation, the episodes' returns, their number, the skill used, the protocol, seconds
  it took), TensorBoard and Weights & Biases (``eval/<task>/return``).
"""

from __future__ import annotations

import contextlib
import random
import time

import numpy as np
import torch

from dvfb import envs
from dvfb.agents import get_spec
from dvfb.core.config import replace
from dvfb.data import ReplayBuffer, physics_columns
from dvfb.data.buffer import PHYSICS_COLUMN
from dvfb.protocols import zero_shot_protocol
from dvfb.runs.snapshots import model_from_snapshot, snapshot_state
from dvfb.training.evaluation import evaluate
from dvfb.training.seeding import run_generator
from dvfb.workflows.resources import evaluation_tasks

# Added to the run's seed for the evaluation's streams, so that they never coincide with the
# training's (seeded with the run's seed itself).
EVAL_STREAM = 7_919


@contextlib.contextmanager
def global_rng_untouched():
    """Torch's (CPU and CUDA) and Python's global generators as they were before the block: building
    a model initialises its layers from torch's global stream, which training may read."""
    python = random.getstate()
    with torch.random.fork_rng(devices=list(range(torch.cuda.device_count())) if torch.cuda.is_available() else []):
        try:
            yield
        finally:
            random.setstate(python)


class PretrainEvaluation:
    """One run's evaluations while it pre-trains (module docstring): the window of its newest
    transitions with their physics states, and the evaluation itself."""

    def __init__(self, config, obs_dim: int, action_dim: int, env, device: torch.device):
        self.config = config
        self.tasks = evaluation_tasks(config, list(config.eval_tasks))
        self.protocol = zero_shot_protocol(get_spec(config.agent).zero_shot)(config.inference)
        # Methods that infer from reward samples do it on the window; the others interact.
        self.relabels = "reward_fn" in self.protocol.sources
        # Room for the newest eval_samples transitions whatever the episode in progress holds.
        length = envs.TASKS[self.tasks[0]].episode_length
        self.window = ReplayBuffer(
            config.eval_samples + length, obs_dim, action_dim, z_dim=0, max_episode_length=length, device="cpu",
            columns=physics_columns(env.unwrapped.physics_width)) if self.relabels else None
        self.physics = env.unwrapped.physics_state if self.relabels else None
        self.device = device

    def due(self, step: int) -> bool:
        return self.config.eval_every > 0 and step % self.config.eval_every == 0

    # The window ---------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"window": self.window.state_dict()} if self.window is not None else {}

    def start_window(self, obs: np.ndarray) -> None:
        """Start the window's episode at ``obs`` (a resume that begins evaluating mid-episode)."""
        if self.window is not None:
            self.window.start_episode(obs, physics=self.physics())

    def load_state_dict(self, state: dict | None) -> None:
        """A checkpoint's window (absent from a run that did not evaluate before: it fills from here)."""
        if self.window is not None and state and "window" in state:
            self.window.load_state_dict(state["window"])

    # The evaluation -----------------------------------------------------------------------------
    def run(self, step: int, modules: dict, learner) -> list[dict]:
        """Evaluate the networks whose state dicts are ``modules`` (a member's) at ``step``; one record
        per task (module docstring)."""
        config = self.config
        if self.window is not None and len(self.window) == 0:
            return []  # nothing stored yet to infer from (evaluations began with a resume)
        started = time.time()
        seed = config.seed + EVAL_STREAM
        with global_rng_untouched():
            state = snapshot_state(learner, config, step, modules)
            model = model_from_snapshot(state, config, self.device, f"the networks at step {step}")
            model.use_generator(run_generator(seed + step, self.device))
            rng = np.random.default_rng([seed, step])
            task_envs = [envs.make(task, seed=int(rng.integers(2**31))) for task in self.tasks]
            skills, protocol = [], self.protocol
            if self.relabels:
                data = self.window.transitions()  # oldest first: the newest eval_samples are the last
                newest = slice(-config.eval_samples, None)
                physics = data.columns["next_" + PHYSICS_COLUMN][newest].cpu().numpy()
                obs, next_obs = data.obs[newest].to(self.device), data.next_obs[newest].to(self.device)
                protocol = type(self.protocol)(replace(self.protocol.config, samples=int(obs.shape[0])))
            elif hasattr(protocol.config, "steps"):
                protocol = type(self.protocol)(replace(self.protocol.config, steps=config.eval_skill_steps))
            for task, env in zip(self.tasks, task_envs):
                if self.relabels:
                    rewards = env.unwrapped.rewards_from_physics(physics)  # the env is reset before it acts
                    reward_t = torch.as_tensor(rewards, dtype=torch.float32, device=self.device).reshape(-1, 1)
                    skill, _info = protocol.skill_from_samples(model, obs, next_obs, reward_t)
                else:
                    skill, _info = protocol.task_skill(model, env, rng, envs.TASKS[task].episode_length)
                skills.append(skill)
            outcomes = evaluate(model.act, task_envs, skills, config.eval_episodes)
        seconds = time.time() - started
        for env in task_envs:
            env.close()
        return [{"task": task, "return": float(np.mean(o.returns)), "return_std": float(np.std(o.returns)),
                 "returns": [float(r) for r in o.returns], "episodes": len(o.returns),
                 "skill": None if skill is None else skill.detach().cpu().reshape(-1).tolist(),
                 "protocol": protocol.name, "seconds": seconds}
                for task, o, skill in zip(self.tasks, outcomes, skills)]
