"""Skill-value analysis (paper §4, Fig. 3b): does the FB value rank trajectories by their return?

Protocol (``dvfb analyze-value RUN --task T``):

1. infer z_r for the task exactly as zero-shot does (docs/methods.md §8.1-8.2, through
   the run's zero-shot protocol, budgets from ``--inference.*``);
2. build K skills: z_r itself and K-1 skills ``proj((1 - lam) z_r + lam z_k)`` with prior draws
   ``z_k ~ p(z)`` and ``lam`` evenly spaced in (0, 1] (``lam = 1`` is a pure prior draw), so the
   returns range from z_r's down to a random skill's;
3. roll out R mean-action episodes per skill in the task (the §8.3 evaluation policy);
4. per trajectory: its return, and the skill value at its start
   ``Q_M = min_k F_k(s0, a0, z_r) . z_r`` (:meth:`Agent.skill_value`, ``a0`` the trajectory's
   first action) -- the value the dual-value fine-tuning uses for the task. Also recorded:
   ``F(s0, a0, z) . z_r`` with the trajectory's own skill z (the FB estimate of that skill's
   task value);
5. the Spearman rank correlation (``scipy.stats.spearmanr``) between value and return, over all
   trajectories and within equal-count return bins (quantile bins by rank).

Outputs under ``RUN/analysis/``: ``value_<task>.csv`` (one row per trajectory), ``value_<task>.png``
(scatter) and ``value_<task>.json`` (the correlations and the settings).
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import numpy as np
import torch

from dvfb import envs
from dvfb.analysis.common import AnalysisError, json_safe
from dvfb.analysis.statistics import binned_spearman, spearman
from dvfb.core.config import to_dict
from dvfb.nets import project_to_sphere
from dvfb.runs import check_writable, write_json_atomic
from dvfb.runs.snapshots import load_model
from dvfb.training.evaluation import run_episode
from dvfb.training.rollout import Observer
from dvfb.training.seeding import run_generator, seed_everything
from dvfb.workflows.resources import check_task_in_domain, open_run
from dvfb.workflows.zeroshot import run_protocol

# ---------------------------------------------------------------------------------------------
# skills and rollouts


def skill_set(z_r: torch.Tensor, count: int, generator: torch.Generator) -> tuple[torch.Tensor, np.ndarray]:
    """``count`` skills: z_r first, then projected mixtures with prior draws; returns (z, lam)."""

    if count < 1:
        raise AnalysisError("--skills must be at least 1")
    d = z_r.shape[-1]
    z_r = z_r.detach().cpu().reshape(1, d)
    others = count - 1
    lam = np.linspace(0.0, 1.0, others + 1)[1:] if others else np.zeros(0)
    prior = project_to_sphere(torch.randn(others, d, generator=generator))
    lam_t = torch.as_tensor(lam, dtype=torch.float32).reshape(-1, 1)
    mixed = project_to_sphere((1 - lam_t) * z_r + lam_t * prior) if others else torch.zeros(0, d)
    return torch.cat([z_r, mixed]), np.concatenate([[0.0], lam])


class FirstStep(Observer):
    """The first observation and action of an episode, and its steps."""

    obs0 = action0 = None
    steps = 0

    def episode_started(self, lane: int, obs: np.ndarray) -> None:
        self.obs0, self.action0, self.steps = obs.copy(), None, 0

    def transition(self, lane: int, step: int, action, reward, discount, next_obs, info) -> None:
        if self.action0 is None:
            self.action0 = np.array(action, copy=True)
        self.steps += 1


def skill_episode(model, env, z: torch.Tensor, max_steps: int | None, explore: bool = False) -> dict:
    """One episode with a fixed skill (at most ``max_steps`` steps); its return, s0, a0 and steps."""
    first = FirstStep()
    lane = run_episode(env, model.act, z, explore, [first], max_steps)
    return {"return": lane.state.episode_return, "obs0": first.obs0, "action0": first.action0, "steps": first.steps}


def analyze_value(run_path: str | Path, task: str, *, skills: int = 16, episodes_per_skill: int = 2,
                  bins: int = 4, max_steps: int | None = None, inference: dict | None = None,
                  snapshot: int | None = None, seed: int | None = None, overwrite: bool = False,
                  device: str | None = None, torch_threads: int | None = None) -> dict:
    """Run the analysis of the module docstring on a pre-trained run; returns the JSON summary
    (``torch_threads``: the command's, :func:`~dvfb.workflows.resources.use_threads`)."""

    if episodes_per_skill < 1:
        raise AnalysisError("--episodes-per-skill must be at least 1")
    if max_steps is not None and max_steps < 1:
        raise AnalysisError("--max-steps must be at least 1")
    run = open_run(run_path, torch_threads)
    config = run.config
    check_task_in_domain(task, config.domain)
    protocol = run_protocol(config, inference)
    out_dir = run.analysis_dir
    outputs = [out_dir / f"value_{task}.{ext}" for ext in ("csv", "png", "json")]
    existing = [p for p in outputs if p.exists()]
    if existing and not overwrite:
        raise AnalysisError(f"{existing[0]} exists; pass --overwrite to replace it")
    model, snapshot = load_model(run, snapshot, device)
    if not model.learns_skill_value:
        raise AnalysisError(f"agent {config.agent!r} learns no skill value (analyze-value needs a method that does, "
                            "such as fb or dvfb)")
    check_writable(out_dir)  # a read-only run fails now, not after the rollouts
    seed = config.seed if seed is None else seed
    rng = seed_everything(seed)
    model.use_generator(run_generator(seed, model.device))  # the analysis' own random stream
    started = time.time()
    max_len = envs.TASKS[task].episode_length

    env = envs.make(task, seed=seed)
    z_r, info = protocol.task_skill(model, env, rng, max_len)
    generator = torch.Generator().manual_seed(seed)
    zs, lam = skill_set(z_r, skills, generator)

    eval_env = envs.make(task, seed=seed)
    rows = []
    for k in range(zs.shape[0]):
        z = zs[k].to(model.device)
        for episode in range(episodes_per_skill):
            result = skill_episode(model, eval_env, z, max_steps)
            rows.append({"skill": k, "lam": float(lam[k]), "episode": episode, **result})
    obs0 = torch.as_tensor(np.stack([r["obs0"] for r in rows]), dtype=torch.float32, device=model.device)
    act0 = torch.as_tensor(np.stack([r["action0"] for r in rows]), dtype=torch.float32, device=model.device)
    own_z = zs[[r["skill"] for r in rows]].to(model.device)
    task_z = z_r.to(model.device)
    value = model.skill_value(obs0, act0, task_z).cpu().numpy().astype(float)
    # The task value of following each trajectory's own skill (FB: F(s0, a0, z) . z_r).
    own_value = model.skill_value(obs0, act0, own_z, task=task_z).cpu().numpy().astype(float)
    returns = np.array([r["return"] for r in rows], dtype=float)

    out_dir.mkdir(parents=True, exist_ok=True)
    with open(outputs[0], "w", newline="", encoding="utf-8") as file:
        writer = csv.writer(file, lineterminator="\n")
        writer.writerow(["trajectory", "skill", "lam", "kind", "episode", "steps", "return", "value",
                         "value_own_skill"])
        for i, r in enumerate(rows):
            kind = "z_r" if r["lam"] == 0 else ("prior" if r["lam"] == 1 else "interpolated")
            writer.writerow([i, r["skill"], repr(r["lam"]), kind, r["episode"], r["steps"], repr(float(r["return"])),
                             repr(float(value[i])), repr(float(own_value[i]))])
    rho = spearman(value, returns)
    summary = {
        "analysis": "skill value vs return (paper §4, Fig. 3b)", "task": task, "domain": config.domain,
        "agent": config.agent, "run": str(run.path), "snapshot_frames": snapshot, "seed": seed,
        "skills": int(zs.shape[0]), "episodes_per_skill": episodes_per_skill, "trajectories": len(rows),
        "max_steps": max_steps, "actions": "mean (evaluation policy, §8.3)",
        "value": "min_k F_k(s0, a0, z_r) . z_r at each trajectory's first state and action",
        "spearman": rho, "spearman_own_skill": spearman(own_value, returns), "bins": binned_spearman(value, returns, bins),
        "return_mean": float(returns.mean()), "return_min": float(returns.min()), "return_max": float(returns.max()),
        "z_r_return_mean": float(returns[lam[[r["skill"] for r in rows]] == 0].mean()),
        "inference": to_dict(protocol.config), "inference_info": info, "wall_clock_s": time.time() - started,
        "files": [str(p) for p in outputs],
    }
    _scatter(outputs[1], value, returns, lam[[r["skill"] for r in rows]], task, config.agent, rho)
    summary = json_safe(summary)
    write_json_atomic(outputs[2], summary)
    return summary


def _scatter(path: Path, value: np.ndarray, returns: np.ndarray, lam: np.ndarray, task: str, agent: str,
             rho: float) -> None:
    # here, not at the top: matplotlib takes ~0.35 s to import and only the plots need it
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.6, 4.4), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    points = ax.scatter(value, returns, c=lam, cmap="viridis", vmin=0, vmax=1, s=18, edgecolors="none")
    best = lam == 0
    ax.scatter(value[best], returns[best], facecolors="none", edgecolors="red", s=60, label="z_r")
    fig.colorbar(points, ax=ax, label="lam (0 = z_r, 1 = prior draw)")
    rho_text = "n/a" if math.isnan(rho) else f"{rho:.3f}"
    fig.suptitle(f"{agent} on {task}\nSpearman(value, return) = {rho_text}, n = {value.size}", fontsize=10)
    ax.set_xlabel("skill value  F(s0, a0, z_r) . z_r")
    ax.set_ylabel("episode return")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.savefig(path)
