"""The helpers the test modules share, each defined once here (a test module never imports another):

* tiny network sizes and configs (fast on one CPU thread), a replay of real maze transitions, and
  seeded random batches;
* the command lines of the tiny maze pre-trainings (``pretrain_args``, ``fb_physics_args``), which
  ``conftest.py`` runs once per session for the tests that share them, and ``copy_run`` for a test
  that writes into such a run;
* synthetic run directories with known numbers and a markdown table reader (the report tests);
* a group's members built as separate agents (the member and group tests);
* a directory's files (``tree_bytes``) and the ``dvfb`` command as a process (``run_cli``, ``start_cli``).

This directory is on ``sys.path`` (pytest's default rootdir import mode puts a test file's directory
there, and this one has no ``__init__.py``), so every module imports them as ``from tiny import ...``.
"""

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


# Tiny widths for every config section a registered method may have (a section not listed here
# keeps its small-preset widths, which are still fast enough for a few hundred frames).
TINY_SECTIONS = {
    "fb": dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32),
    "conservative": dict(samples=6),
    "fbee": dict(ensemble=3, candidates=8),
    "sf": dict(z_dim=D, hidden_dim=H, feature_dim=E, backward_hidden_dim=H, batch_size=32),
    "exploration": dict(rnd_rep_dim=16, contrastive_hidden_dim=32, ce_k=4),
    "ddpg": dict(hidden_dim=H, batch_size=32),
    "rnd": dict(hidden_dim=H, rep_dim=16),
    "disagreement": dict(hidden_dim=H),
    "icm_apt": dict(hidden_dim=H, rep_dim=16, knn_k=4),
    "proto": dict(pred_dim=16, proj_dim=32, num_protos=16, queue_size=64),
    "cic": dict(hidden_dim=H, knn_k=4),
    "diayn": dict(hidden_dim=H),
    "smm": dict(hidden_dim=H, vae_hidden_dim=16, code_dim=8),
    "aps": dict(hidden_dim=H, knn_k=4),
    "becl": dict(hidden_dim=H),
    "comsd": dict(hidden_dim=H, knn_k=4),
    "cesd": dict(hidden_dim=H, critic_trunk_dim=16, critic_hidden_dim=32, knn_k=4),
}


def tiny_run_config(agent: str, **top_level):
    """The small-preset run config of a registered method with tiny widths, on the maze by default
    (episodes of 1000 cheap steps), seed frames 500 and an update every 4 steps."""
    from dvfb.agents import get_spec
    from dvfb.core.config import merge
    from dvfb.runs.presets import preset_config

    top = dict(domain="point_mass_maze", frames=1000, seed_frames=500, update_every=4, checkpoint_every=1000,
               log_every=250, torch_threads=1)
    top.update(top_level)
    config = preset_config("small", agent, **top)
    return merge(config, {name: TINY_SECTIONS[name] for name in get_spec(agent).sections if name in TINY_SECTIONS})


def filled_replay(agent, steps: int = 400, seed: int = 0):
    """A replay buffer of real maze transitions (two episodes of uniform actions), with skills
    drawn from the agent's prior when it has one."""
    import numpy as np

    from dvfb import envs
    from dvfb.data import ReplayBuffer

    rng = np.random.default_rng(seed)
    env = envs.make("point_mass_maze_reach_top_left", seed=seed)
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    replay = ReplayBuffer(10_000, obs_dim, action_dim, agent.skill_dim, max_episode_length=1000)
    obs, _ = env.reset(seed=seed)
    replay.start_episode(obs)
    for t in range(steps):
        if t == steps // 2:
            obs, _ = env.reset()
            replay.start_episode(obs)
        skill = agent.sample_skill(1)
        action = rng.uniform(-1, 1, action_dim).astype(np.float32)
        obs, reward, terminated, _, _ = env.step(action)
        replay.add(action, reward, 0.0 if terminated else 1.0, obs, None if skill is None else skill[0].numpy())
    return replay


def tiny_flags(agent: str, sections: tuple[str, ...] | None = None) -> list[str]:
    """``dvfb pretrain`` flags of :data:`TINY_SECTIONS`' widths for ``agent``'s sections (or only
    ``sections`` of them): the command-line twin of :func:`tiny_run_config`."""
    from dvfb.agents import get_spec
    from dvfb.core.config import flag_name

    flags = []
    for section in get_spec(agent).sections:
        if sections is not None and section not in sections:
            continue
        for key, value in TINY_SECTIONS.get(section, {}).items():
            flags += [flag_name(f"{section}.{key}"), str(value)]
    return flags


def random_batch(n: int, seed: int = 0, *, obs_dim: int = OBS, action_dim: int = ACT, step: float | None = 0.3,
                 future: bool = False, reward="normal", discount=0.99, skill=None, dtype=None):
    """A batch of ``n`` random transitions from a seeded generator, drawn in this order: ``obs``;
    ``next_obs`` (``obs`` plus ``step`` times noise; with ``step`` None, independent of ``obs``);
    ``future_obs`` (``next_obs`` plus noise, with ``future``); actions uniform in [-1, 1]; the skill
    (``skill(n, generator)``, or a fixed tensor); the discount (a number, ``"random"`` in [0.9, 1),
    or a tensor); the reward (``"normal"``, ``"positive"`` (uniform + 0.1), ``"zeros"`` or a tensor)."""
    import torch

    from dvfb.data import Batch

    g = torch.Generator().manual_seed(seed)
    kw = {"generator": g, "dtype": dtype}
    obs = torch.randn(n, obs_dim, **kw)
    next_obs = torch.randn(n, obs_dim, **kw) if step is None else obs + step * torch.randn(n, obs_dim, **kw)
    future_obs = next_obs + (step or 0.3) * torch.randn(n, obs_dim, **kw) if future else None
    action = torch.rand(n, action_dim, **kw) * 2 - 1
    z = skill(n, generator=g) if callable(skill) else skill
    if isinstance(discount, str):
        discount = 0.9 + 0.1 * torch.rand(n, 1, **kw)
    elif not isinstance(discount, torch.Tensor):
        discount = torch.full((n, 1), float(discount), dtype=dtype)
    if isinstance(reward, str):
        reward = {"normal": lambda: torch.randn(n, 1, **kw), "positive": lambda: torch.rand(n, 1, **kw) + 0.1,
                  "zeros": lambda: torch.zeros(n, 1, dtype=dtype)}[reward]()
    return Batch(obs, action, reward, discount, next_obs, future_obs, z)


def skill_batch(n: int, skill, seed: int = 0, **kw):
    """:func:`random_batch` of the skill methods' updates: a skill (a tensor, or ``skill(n, generator)``
    drawn from the batch's generator) and the discount 0.99 ** 3 of their 3-step returns."""
    return random_batch(n, seed, skill=skill, discount=0.99 ** 3, **kw)


def per_row_discount_batch(n: int, seed: int, dtype, **kw):
    """:func:`random_batch` in ``dtype`` with s'' and a discount of its own in every row, drawn in
    [0.9, 1) (as an n-step replay's episode ends give)."""
    return random_batch(n, seed, future=True, discount="random", dtype=dtype, **kw)


def replayed_return(run, task: str, z, seed: int) -> float:
    """The return of one mean-action episode of ``run``'s model with the skill ``z`` (None for a
    single policy) in ``task``'s environment made with ``seed``, stepped here by hand: what a
    zero-shot result's first return must be."""
    import numpy as np

    import dvfb
    from dvfb import envs

    model = dvfb.load(run)
    env = envs.make(task, seed=seed)
    obs, _ = env.reset()
    total, done = 0.0, False
    skill = None if z is None else np.asarray(z, dtype=np.float32)
    while not done:
        obs, reward, terminated, truncated, _ = env.step(model.act(obs, skill))
        total += float(reward)
        done = terminated or truncated
    return total


# ---------------------------------------------------------------------------------------------
# The tiny maze pre-trainings of the command-line tests (conftest.py runs each shared one once)

# A network small enough that an update costs a few milliseconds.
WORKFLOW_FB = ["--fb.z-dim", "16", "--fb.hidden-dim", "32", "--fb.feature-dim", "16", "--fb.backward-hidden-dim", "32",
               "--fb.batch-size", "64", "--log-every", "250"]
# DVFB's own section (an FB run has no --exploration.* flags).
WORKFLOW_EXPLORATION = ["--exploration.contrastive-hidden-dim", "32", "--exploration.rnd-rep-dim", "16",
                        "--exploration.ce-k", "4"]
# The maze with updates from 500 frames, every 4 steps, and a checkpoint at each episode's end.
MAZE_SCHEDULE = ["--domain", "point_mass_maze", "--seed-frames", "500", "--update-every", "4",
                 "--checkpoint-every", "1000"]
FAST_INFERENCE = ["--inference.steps", "300", "--inference.random-action-steps", "100",
                  "--inference.samples", "300", "--inference.eval-episodes", "1"]


def pretrain_args(run_dir, frames: int, agent: str = "dvfb", extra=()) -> list[str]:
    """``dvfb pretrain`` of ``agent`` on the maze with the workflow widths (conftest's
    ``dvfb_maze_run`` is ``pretrain_args(run_dir, 2000)``)."""
    return ["pretrain", "--agent", agent, *MAZE_SCHEDULE, "--frames", str(frames), "--run-dir", str(run_dir),
            "--no-progress", *WORKFLOW_FB, *(WORKFLOW_EXPLORATION if agent == "dvfb" else ()), *extra]


# tiny_flags("fb") and the maze's schedule, one torch thread.
FB_PHYSICS_FLAGS = [*tiny_flags("fb"), "--torch-threads", "1", "--update-every", "4", "--checkpoint-every", "1000"]


def fb_physics_args(run_dir, frames: int, *extra: str) -> list[str]:
    """``dvfb pretrain`` of FB on the maze recording physics (conftest's ``fb_maze_physics_run`` is
    ``fb_physics_args(run_dir, 2000)``); a resume of that run is ``fb_physics_args(copy, N, "--resume")``."""
    return ["pretrain", "--agent", "fb", "--domain", "point_mass_maze", "--frames", str(frames), "--seed-frames",
            "500", "--run-dir", str(run_dir), "--replay.record-physics", "true", "--no-progress", *FB_PHYSICS_FLAGS,
            *extra]


def copy_run(run, into):
    """A copy of ``run`` at ``into/<run's name>``, for a test that writes into a shared run (zero-shot
    results, fine-tunings, analyses): the shared one stays as conftest made it."""
    import shutil
    from pathlib import Path

    return Path(shutil.copytree(run, Path(into) / Path(run).name))


# ---------------------------------------------------------------------------------------------
# Synthetic run directories with known numbers (the report tests)


def make_pretrain_run(path, agent: str = "dvfb", domain: str = "walker", seed: int = 0,
                      use_ce: bool = True, zeroshot: dict[str, float] | None = None,
                      snapshot_frames: int = 100_000):
    """A pre-training run directory of the small preset's config (no training) with one zero-shot
    result per task of ``zeroshot`` (task -> mean return) at ``snapshot_frames``."""
    from dvfb.core.config import merge, save_json
    from dvfb.runs import write_json_atomic
    from dvfb.runs.presets import preset_config

    config = preset_config("small", agent=agent, domain=domain, seed=seed)
    if not use_ce:
        config = merge(config, {"exploration": {"use_ce": False}})
    path.mkdir(parents=True)
    save_json(config, path / "config.json")
    for task, value in (zeroshot or {}).items():
        write_json_atomic(path / "zeroshot" / f"{task}.json", {
            "task": task, "domain": domain, "agent": agent, "preset": "small", "pretrain_seed": seed,
            "seed": seed, "snapshot_frames": snapshot_frames, "mean_return": value, "std_return": 0.0,
            "returns": [value], "eval_episodes": 1, "z": [0.0] * 4})
    return path


def make_finetune_run(run, task: str, points: list[tuple[int, float]], name: str | None = None,
                      seed: int | None = None, finished: bool = True, **finetune):
    """A fine-tuning run of ``run`` (from its 100,000-frame snapshot) whose curve is ``points``
    (frames, mean return), finished unless ``finished`` is False; ``finetune`` sets FinetuneConfig."""
    import json

    from dvfb.core.config import save_json
    from dvfb.protocols import protocols_of
    from dvfb.protocols.dual_value import FinetuneConfig
    from dvfb.runs import write_json_atomic
    from dvfb.runs.run_config import FinetuneRunConfig

    parent = json.loads((run / "config.json").read_text())
    seed = parent["seed"] if seed is None else seed
    zero_shot, finetuner = protocols_of(parent["agent"])
    config = FinetuneRunConfig(
        pretrain_run=str(run), agent=parent["agent"], domain=parent["domain"], task=task, snapshot=100_000, seed=seed,
        protocol=finetuner.name, inference=zero_shot.config_cls(), finetune=FinetuneConfig(**finetune))
    path = run / "finetune" / (name or task)
    path.mkdir(parents=True)
    save_json(config, path / "config.json")
    write_json_atomic(path / "curve.json", {
        "task": task, "domain": parent["domain"], "agent": parent["agent"], "seed": seed,
        "curve": [{"frames": f, "mean_return": r, "std_return": 0.0, "returns": [r]} for f, r in points]})
    if finished:
        write_json_atomic(path / "finetune_summary.json", {"task": task, "frames": points[-1][0]})
    return path


def md_row(markdown: str, domain: str, task: str) -> list[str]:
    """The cells after domain and task of a markdown table's row (a bold task name too)."""
    for line in markdown.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 2 and cells[0] == domain and cells[1].strip("*") == task:
            return cells[2:]
    raise AssertionError(f"no row {domain}/{task} in\n{markdown}")


# ---------------------------------------------------------------------------------------------
# A group's members as separate agents (the member and group tests)

MEMBERS = 3
# SMM's discriminator bias rounds differently, by ~1e-10 after three updates, and on some CPUs one
# APS feature bias by one ulp (docs/members.md).
NOT_BITWISE = {"smm": 1e-9, "aps": 1e-7}


def member_agents(name: str, dtype, batch_size: int | None = None):
    """``MEMBERS`` agents built as separate runs with seeds 0, 1, 2 would build them, their replays,
    and each member's twin (a separate agent with its own copy of the same stream)."""
    import copy

    import torch

    from dvfb import envs
    from dvfb.agents import make_agent
    from dvfb.core.config import merge

    env = envs.make("point_mass_maze_reach_top_left")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        agents, twins, replays = [], [], []
        for k in range(MEMBERS):
            torch.manual_seed(100 + k)
            config = tiny_run_config(name, seed=k)
            if batch_size is not None:
                config = merge(config, {s: {"batch_size": batch_size} for s in ("fb", "sf", "ddpg")
                                        if hasattr(config, s)})
            agent = make_agent(name, obs_dim, action_dim, config, "cpu")
            agent.use_generator(torch.Generator().manual_seed(1000 + k))
            replays.append(filled_replay(agent, seed=k))
            twin = copy.deepcopy(agent)
            twin.use_generator(torch.Generator().manual_seed(0))
            twin.generator.set_state(agent.generator.get_state())
            twin.use_generator(twin.generator)
            agents.append(agent)
            twins.append(twin)
    finally:
        torch.set_default_dtype(previous)
    return agents, twins, replays


def cast_batch(batch, dtype):
    """``batch`` with every tensor (the extra columns too) in ``dtype``."""
    from dvfb.data import Batch

    def cast(x):
        return None if x is None else x.to(dtype)
    return Batch(cast(batch.obs), cast(batch.action), cast(batch.reward), cast(batch.discount), cast(batch.next_obs),
                 cast(batch.future_obs), cast(batch.z), {k: cast(v) for k, v in batch.columns.items()})


# ---------------------------------------------------------------------------------------------
# Files and processes


def tree_bytes(root) -> dict:
    """Every path under ``root`` and its bytes (None for a directory), a lock file's holder pid aside
    (taking the lock is how a command looks at a run safely): equal before and after means nothing
    was written, created or removed."""
    from pathlib import Path

    root = Path(root)
    return {str(p.relative_to(root)): p.read_bytes() if p.is_file() and p.name != ".lock" else None
            for p in sorted(root.rglob("*"))}


def run_cli(*args: str, env=None, timeout=None):
    """``python -m dvfb ARGS`` as a separate process (what a user types), run to its end; text output."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "dvfb", *args], capture_output=True, text=True, env=env,
                          timeout=timeout)


def start_cli(*args: str):
    """``python -m dvfb ARGS`` started as a separate process, its output in pipes (text)."""
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-m", "dvfb", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
