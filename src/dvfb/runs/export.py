"""Exported models: a pre-trained agent as the field shares one (docs/sharing.md), one directory per
seed, with no pickle and no run directory::

    DIR/model.safetensors      the model's inference weights (actor, maps or critics), by module
    DIR/config.json            what the weights are: method, domain, spaces, frames, seed, the run
                               config, the zero-shot results, dvfb's version and the format version
    DIR/README.md              a model card with YAML metadata (library, tags, metrics)
    DIR/inference_data.npz     optional: reward-inference samples (observations, next observations,
                               and the physics states of the observations when the run recorded them)

:func:`export_model` writes it from a run's snapshot, :func:`write_export` from a model already
loaded, and :func:`load_export` reads it back into the same :class:`~dvfb.agents.base.Model`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shlex
import shutil
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from dvfb.core.version import __version__
from dvfb.agents import Model, make_model
from dvfb.core.config import to_dict
from dvfb.core.errors import CheckpointError, ConfigError, RunDirError
from dvfb.core.files import read_json, write_json_atomic
from dvfb.data import ReplayBuffer
from dvfb.data.buffer import PHYSICS_COLUMN
from dvfb.runs.checkpoints import save_snapshot
from dvfb.runs.directory import EXPORT_FORMAT, check_writable, is_export_config
from dvfb.runs.layout import PRETRAIN, PretrainRun, run_kind, snapshot_name
from dvfb.runs.run_config import PretrainConfig, run_config_from_dict
from dvfb.runs.snapshots import load_model, snapshot_state

EXPORT_VERSION = 1
MODEL_FILE, CONFIG_FILE, CARD_FILE, INFERENCE_FILE = ("model.safetensors", "config.json", "README.md",
                                                      "inference_data.npz")
# At most this many transitions go into inference_data.npz by default (chosen uniformly, with the
# run's seed): the FB family's inference draws far fewer (inference.samples), and a paper-scale
# replay of 1M transitions would make a share of hundreds of megabytes.
DEFAULT_INFERENCE_SIZE = 100_000


STATISTICS = "statistics"  # the weights file's prefix of the model's data statistics
# The folder an export is written into before its files are moved into place (write_export).
_STAGE = ".export.tmp-"


def is_export(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an exported model directory: its weights, and a config.json that says so."""
    return (Path(path) / MODEL_FILE).is_file() and is_export_config(Path(path) / CONFIG_FILE)


@dataclasses.dataclass
class Export:
    """An exported model read back: its model, run config, config.json and inference data."""

    path: Path
    model: Model
    config: PretrainConfig
    info: dict
    inference_data: dict[str, np.ndarray] | None


def _check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; give a directory for the exported model")
    if out.is_dir() and any(not p.name.startswith(_STAGE) for p in out.iterdir()):
        if not overwrite:
            raise ConfigError(f"--out {out} is not empty; pass --overwrite to replace an exported model there")
        if not is_export(out):
            raise ConfigError(f"--out {out} holds something else than an exported model; it is not replaced")
    check_writable(out)


def _weights(model: Model) -> dict[str, torch.Tensor]:
    tensors = {}
    for module_name, module in model.snapshot_modules().items():
        for name, value in module.state_dict().items():
            if not isinstance(value, torch.Tensor):
                raise ConfigError(f"{module_name}.{name} is not a tensor; the model cannot be exported")
            # Own, contiguous CPU storage: safetensors refuses tensors that share memory.
            tensors[f"{module_name}.{name}"] = value.detach().to("cpu").contiguous().clone()
    # The statistics of the pre-training data a snapshot carries (FB's Cov(B), online task inference).
    for name, value in model.statistics.items():
        tensors[f"{STATISTICS}.{name}"] = value.detach().to("cpu").contiguous().clone()
    return tensors


def inference_samples(run: PretrainRun, size: int, seed: int) -> dict[str, np.ndarray]:
    """Up to ``size`` transitions of the run's pre-training replay, uniformly without replacement
    (``seed``), as the arrays of ``inference_data.npz``."""
    state = run.resume_state()
    if state is None or "replay" not in state:
        raise ConfigError(f"{run.path} has no pre-training replay (no resume checkpoint) to take inference samples "
                          "from; export it without --with-inference-data")
    data = ReplayBuffer.from_state(state["replay"]).transitions()
    n = data.obs.shape[0]
    chosen = np.sort(np.random.default_rng(seed).choice(n, size=min(size, n), replace=False))
    index = torch.as_tensor(chosen)
    arrays = {"obs": data.obs[index].cpu().numpy(), "next_obs": data.next_obs[index].cpu().numpy()}
    for column in (PHYSICS_COLUMN, f"next_{PHYSICS_COLUMN}"):  # of obs, and of next_obs (a task's reward)
        if column in data.columns:
            arrays[column] = data.columns[column][index].cpu().numpy()
    return arrays


def evaluation_budget(result) -> dict:
    """What a zero-shot number cost (docs/sharing.md, "Model card"): evaluation episodes, the task's
    reward-labelled environment steps its skill was found from, and where the skill came from."""
    source = result.skill_source or "rewards"
    inference = result.inference if isinstance(result.inference, dict) else {}
    steps = inference.get("steps", 0) if source == "rewards" else 0
    budget = {"eval_episodes": result.eval_episodes, "labelled_steps": int(steps or 0), "skill_source": source,
              "std_return": result.std_return}
    if result.success_rate is not None:
        budget["success_rate"] = result.success_rate
    return budget


def _yaml(value) -> str:
    """A YAML scalar: JSON's form of numbers, booleans and strings (a double-quoted JSON string is
    a YAML string) needs no YAML library at run time."""
    return json.dumps(value)


def _model_index(name: str, zero_shot: dict[str, float], budgets: dict[str, dict]) -> list[str]:
    """The card's ``model-index`` in the Hugging Face hub's results format: one result per task,
    whose metrics carry the evaluation budget in ``args``; self-reported (``verified: false``)."""
    lines = ["model-index:", f"- name: {_yaml(name)}", "  results:" + ("" if zero_shot else " []")]
    for task, value in sorted(zero_shot.items()):
        budget = budgets.get(task, {})
        args = {key: budget[key] for key in ("eval_episodes", "labelled_steps", "skill_source") if key in budget}
        metrics = [("mean_reward", "zero-shot mean episode return", value)]
        if budget.get("success_rate") is not None:
            metrics.append(("success_rate", "zero-shot success rate", budget["success_rate"]))
        lines += ["  - task:", "      type: reinforcement-learning", f"      name: {_yaml('zero-shot ' + task)}",
                  "    dataset:", f"      type: {_yaml('dvfb/' + task)}", f"      name: {_yaml(task)}", "    metrics:"]
        for kind, label, number in metrics:
            lines += [f"    - type: {kind}", f"      value: {_yaml(round(float(number), 2))}",
                      f"      name: {_yaml(label)}"]
            if args:
                lines.append("      args:")
                lines += [f"        {key}: {_yaml(arg)}" for key, arg in args.items()]
            lines.append("      verified: false")
    return lines


def _budget_text(budget: dict) -> str:
    if not budget:
        return "not recorded"
    episodes = budget.get("eval_episodes")
    source = budget.get("skill_source")
    skill = (f"{budget['labelled_steps']:,} reward-labelled steps" if source == "rewards" else
             "no skill" if source == "none" else f"skill from {source}")
    return f"{episodes} episodes, {skill}"


def model_card(info: dict) -> str:
    """The model card: YAML metadata the hub reads (its ``model-index`` results format), then what
    the model is, every command that made it (the first and each resume) and how to use it; every
    zero-shot number stands beside its budget."""
    agent, domain, frames, preset = info["agent"], info["domain"], info["frames"], info["preset"]
    name = f"{agent}_{domain}_s{info['seed']}"
    zero_shot = info.get("zero_shot", {})
    budgets = info.get("zero_shot_budget") or {}
    metadata = ["---", "library_name: dvfb", "pipeline_tag: reinforcement-learning",
                f"tags: [reinforcement-learning, unsupervised-reinforcement-learning, zero-shot-reinforcement-learning, "
                f"dvfb, {agent}, dm_control, {domain}]",
                *_model_index(name, zero_shot, budgets), "---"]
    scale = ("the paper's scale (2M frames, paper preset)" if preset == "paper" and frames >= 2_000_000 else
             f"{frames:,} frames at the `{preset}` preset, below the paper's 2M frames at the paper preset: its "
             "scores are not comparable with the paper's tables")
    rows = []
    for task, value in sorted(zero_shot.items()):
        budget = budgets.get(task, {})
        std = budget.get("std_return")
        rows.append(f"| {task} | {value:.1f}" + (f" ± {std:.1f}" if std is not None else "")
                    + f" | {_budget_text(budget)} |")
    commands = info.get("commands") or ([info["command"]] if info.get("command") else [])
    made = ["Made with" + (" (the first command, then each resume):" if len(commands) > 1 else ":"), "", "```bash",
            *(commands or ["(command not recorded)"]), "```"]
    body = [f"# {name}", "",
            f"A `{agent}` agent pre-trained without rewards on `{domain}` for {frames:,} frames (seed "
            f"{info['seed']}, `{preset}` preset) with dvfb {info['dvfb_version']}.", "",
            *made, "",
            "## Use", "", "```python", "import dvfb", "", "model = dvfb.load(\"PATH/TO/THIS/DIRECTORY\")",
            "z = model.infer_z(reward_fn=lambda next_obs: next_obs[:, 0])  # or goal=..., or samples",
            "action = model.act(obs, z)", "```", "",
            "Or from the command line, results in `PATH/TO/THIS/DIRECTORY.eval/` (this directory is only read): "
            "`dvfb zeroshot PATH/TO/THIS/DIRECTORY --task TASK`, `dvfb video PATH/TO/THIS/DIRECTORY --task TASK`.", "",
            "`model.safetensors` holds the inference weights only (no optimiser, no pickle); `config.json` says "
            "what they are." + (" `inference_data.npz` holds reward-inference samples from the pre-training "
                                "replay." if info.get("inference_data") else ""), "",
            "## Zero-shot results", "",
            (f"Mean episode return (± std over the episodes) of the zero-shot policy (dvfb's docs/methods.md), "
             f"{scale}. Each beside its budget: the mean-action evaluation episodes, and the reward-labelled "
             f"steps of the task its skill was found from.\n\n| task | return | budget |\n|---|---:|---|\n"
             + "\n".join(rows) if zero_shot else "None recorded in the run (`dvfb zeroshot RUN --task T` "
                                                  "before exporting adds them)."), ""]
    return "\n".join(metadata + body)


def write_export(out: str | os.PathLike, model: Model, config: PretrainConfig, *, frames: int,
                 zero_shot: dict[str, float] | None = None, command: str | None = None,
                 inference_data: dict[str, np.ndarray] | None = None, overwrite: bool = False,
                 commands: list[str] | None = None, zero_shot_budget: dict[str, dict] | None = None) -> Path:
    """Write ``model`` (of run config ``config``, after ``frames`` frames) as an exported model.
    ``out`` must be absent or empty (or, with ``overwrite``, an exported model). ``commands``: every
    command that made the run (``command``, the first, by default); ``zero_shot_budget``: per task,
    what each zero-shot number cost (:func:`evaluation_budget`)."""
    out = Path(out)
    _check_out(out, overwrite)
    weights = _weights(model)
    info = {"format": EXPORT_FORMAT, "format_version": EXPORT_VERSION, "library": "dvfb",
            "dvfb_version": __version__, "agent": config.agent, "domain": config.domain, "frames": int(frames),
            "seed": config.seed, "preset": config.preset, "skill_dim": model.skill_dim,
            "observation_space": {"shape": [model.obs_dim], "dtype": "float32"},
            "action_space": {"shape": [model.action_dim], "dtype": "float32", "low": -1.0, "high": 1.0},
            "zero_shot": dict(sorted((zero_shot or {}).items())),
            "zero_shot_budget": dict(sorted((zero_shot_budget or {}).items())), "command": command,
            "commands": list(commands) if commands else ([command] if command else []),
            "inference_data": INFERENCE_FILE if inference_data is not None else None,
            "run_config": to_dict(config)}
    # The topmost folder this call creates (a nested --out creates its parents too): what a failure
    # removes again, so that nothing is left behind.
    created = out if not out.exists() else None
    while created is not None and not created.parent.exists():
        created = created.parent
    # Every file is written into a folder of its own inside --out first and moved in only when all
    # are written: a full disk leaves an exported model being replaced (--overwrite) as it was.
    stage = out / f"{_STAGE}{os.getpid()}"
    try:
        out.mkdir(parents=True, exist_ok=True)
        _remove_stages(out)  # of a writer killed before it could clean up
        stage.mkdir()
        save_file(weights, str(stage / MODEL_FILE), metadata={"format": EXPORT_FORMAT, "agent": config.agent})
        if inference_data is not None:
            np.savez_compressed(stage / INFERENCE_FILE, **inference_data)
        (stage / CARD_FILE).write_text(model_card(info), encoding="utf-8")
        write_json_atomic(stage / CONFIG_FILE, info)
        shutil.copymode(stage / CONFIG_FILE, stage / MODEL_FILE)  # the umask's mode, as the other files
        (out / CONFIG_FILE).unlink(missing_ok=True)  # first: while files are swapped it is no export
        if inference_data is None:
            (out / INFERENCE_FILE).unlink(missing_ok=True)  # the replaced model's samples
        for name in (MODEL_FILE, INFERENCE_FILE, CARD_FILE, CONFIG_FILE):  # config.json last
            if (stage / name).exists():
                os.replace(stage / name, out / name)  # a rename in one folder: no space needed
        stage.rmdir()
    except BaseException as exc:
        shutil.rmtree(stage, ignore_errors=True)
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        if isinstance(exc, OSError):
            raise RunDirError(f"cannot write the exported model in {out}: {exc.strerror or exc}") from exc
        if isinstance(exc, SafetensorError):  # safetensors' own error for a failed write (a full disk)
            raise RunDirError(f"cannot write the exported model in {out}: {' '.join(str(exc).split())}") from exc
        raise
    return out


def _remove_stages(out: Path) -> None:
    for path in out.glob(f"{_STAGE}*"):
        shutil.rmtree(path, ignore_errors=True)


def export_model(run: PretrainRun, out: str | os.PathLike, *, snapshot: int | None = None,
                 with_inference_data: bool = False, inference_size: int = DEFAULT_INFERENCE_SIZE,
                 overwrite: bool = False) -> Path:
    """Export the run's snapshot (the newest by default) with its final zero-shot results."""
    if inference_size < 1:
        raise ConfigError(f"--inference-size {inference_size} is out of range: it must be >= 1")
    _check_out(Path(out), overwrite)  # before the model is read
    model, frames = load_model(run, snapshot, "cpu")
    results = [result for _, result in run.zeroshot_results()] if frames == run.snapshot_frames()[-1] else []
    data = inference_samples(run, inference_size, run.config.seed) if with_inference_data else None
    commands = run_commands(run)
    return write_export(out, model, run.config, frames=frames,
                        zero_shot={result.task: result.mean_return for result in results},
                        zero_shot_budget={result.task: evaluation_budget(result) for result in results},
                        command=commands[0] if commands else None, commands=commands, inference_data=data,
                        overwrite=overwrite)


def run_commands(run: PretrainRun) -> list[str]:
    """The commands that made a run, as shell lines: the first, then each resume (meta.json)."""
    try:
        meta = read_json(run.meta_path)
    except RunDirError:
        return []
    if not isinstance(meta, dict):
        return []
    argvs = [meta.get("command")] + [r.get("command") for r in meta.get("resumes") or [] if isinstance(r, dict)]
    # argv[0] is the entry point's path: shown as dvfb.
    return [" ".join(["dvfb", *map(shlex.quote, argv[1:])]) for argv in argvs if isinstance(argv, list) and argv]


def load_export(path: str | os.PathLike, device: str | torch.device = "cpu") -> Export:
    """Read an exported model (no pickle is read: weights from safetensors, the rest JSON)."""
    path = Path(path)
    info = read_json(path / CONFIG_FILE, CheckpointError)
    if not isinstance(info, dict) or info.get("format") != EXPORT_FORMAT:
        raise CheckpointError(f"{path / CONFIG_FILE} is not the config of an exported dvfb model")
    if info.get("format_version") != EXPORT_VERSION:
        raise CheckpointError(f"{path} is an exported model of format version {info.get('format_version')!r}; this "
                              f"dvfb ({__version__}) reads version {EXPORT_VERSION}")
    try:
        config = run_config_from_dict(info.get("run_config"), str(path / CONFIG_FILE))
    except ConfigError as exc:  # a damaged file, named where the message does not name it yet
        raise CheckpointError(str(exc) if str(path) in str(exc) else f"{path / CONFIG_FILE} is damaged: {exc}") \
            from exc
    obs_dim, action_dim = _width(info, "observation_space", path), _width(info, "action_space", path)
    frames = info.get("frames")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 0:
        raise CheckpointError(f"{path / CONFIG_FILE} is damaged: 'frames' is {frames!r}, not a count of frames")
    model = make_model(config.agent, obs_dim, action_dim, config, device)
    try:
        tensors = load_file(str(path / MODEL_FILE), device="cpu")
    except (OSError, SafetensorError) as exc:
        raise CheckpointError(f"{path / MODEL_FILE} cannot be read: {exc}") from exc
    modules: dict[str, dict[str, Any]] = {name: {} for name in model.snapshot_modules()}
    statistics = {}
    for key, value in tensors.items():
        module, _, name = key.partition(".")
        if module == STATISTICS:
            statistics[name] = value
            continue
        if module not in modules:
            raise CheckpointError(f"{path / MODEL_FILE} holds {key}, which no module of {config.agent!r} has")
        modules[module][name] = value
    try:
        model.load_snapshot(modules)
    except (KeyError, RuntimeError) as exc:
        reason = " ".join(str(exc).split())  # torch's message spans lines; an error is one
        raise CheckpointError(f"{path / MODEL_FILE} does not fit {config.agent!r}'s networks: {reason}") from exc
    model.eval()
    model.statistics = statistics
    data = _inference_data(path / INFERENCE_FILE, obs_dim) if info.get("inference_data") else None
    return Export(path, model, config, info, data)


def _width(info: dict, space: str, path: Path) -> int:
    """The width of the observation or action space config.json records (one positive integer)."""
    shape = info.get(space, {}).get("shape") if isinstance(info.get(space), dict) else None
    if not (isinstance(shape, list) and len(shape) == 1 and isinstance(shape[0], int)
            and not isinstance(shape[0], bool) and shape[0] > 0):
        raise CheckpointError(f"{path / CONFIG_FILE} is damaged: it has no {space} shape of one positive width "
                              f"({space}: {info.get(space)!r})")
    return shape[0]


def _inference_data(file: Path, obs_dim: int) -> dict[str, np.ndarray]:
    """The arrays of ``inference_data.npz``: observations and next observations of the model's width,
    as many of each (a damaged or truncated file is named, not a zip error from numpy)."""
    try:
        with np.load(file, allow_pickle=False) as npz:
            data = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise CheckpointError(f"{file} cannot be read (damaged or truncated?): {exc}") from exc
    for key in ("obs", "next_obs"):
        array = data.get(key)
        if array is None or array.ndim != 2 or array.shape[1] != obs_dim:
            raise CheckpointError(f"{file} is damaged: {key!r} is "
                                  + ("missing" if array is None else f"of shape {array.shape}")
                                  + f"; it must be (N, {obs_dim})")
    if data["obs"].shape[0] != data["next_obs"].shape[0]:
        raise CheckpointError(f"{file} is damaged: {data['obs'].shape[0]} observations but "
                              f"{data['next_obs'].shape[0]} next observations")
    return data


def unpack_export(path: str | os.PathLike, run_dir: str | os.PathLike, overwrite: bool = False,
                  command: list[str] | None = None) -> PretrainRun:
    """A run directory made from an exported model: its run config and one snapshot, of the
    export's frames (no replay, no checkpoint), which ``dvfb zeroshot``, ``finetune`` and ``video``
    take as they take a finished run's (``dvfb demo`` unpacks its bundled agent so)."""
    return _unpacked(load_export(path, "cpu"), run_dir, overwrite, command)


def _unpacked(export: Export, run_dir: str | os.PathLike, overwrite: bool, command: list[str] | None) -> PretrainRun:
    run = PretrainRun.create(run_dir, export.config, overwrite=overwrite, command=command)
    modules = {name: module.state_dict() for name, module in export.model.snapshot_modules().items()}
    frames = int(export.info["frames"])
    save_snapshot(run, snapshot_state(export.model, export.config, frames, modules, export.model.statistics),
                  snapshot_name(frames))
    return run


EVALUATION_SUFFIX = ".eval"
# What an evaluation directory holds before anything was evaluated in it: removed again when the
# command that made it fails.
_UNPACKED = {"config.json", "meta.json", "snapshots", "exported_from.json", ".lock"}


def default_evaluation_dir(path: str | os.PathLike) -> Path:
    """Where an exported model is evaluated unless told otherwise: ``<DIR>.eval`` beside it."""
    path = Path(path).resolve()
    return path.with_name(path.name + EVALUATION_SUFFIX)


def _digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def evaluation_run(path: str | os.PathLike, eval_dir: str | os.PathLike | None = None,
                   command: list[str] | None = None) -> tuple[PretrainRun, Export, bool]:
    """The run directory in which the exported model at ``path`` is evaluated (docs/sharing.md,
    "Evaluate"), its :class:`Export`, and whether this call made the directory.

    ``eval_dir`` (default :func:`default_evaluation_dir`) is made from the export the first time (its
    run config and one snapshot, as :func:`unpack_export` makes them, and ``exported_from.json``
    with the export's path and the SHA-256 of its weights), and reused afterwards while it holds
    the same weights; a directory that is something else is refused. The export's own files are
    only read.
    """
    path = Path(path)
    export = load_export(path, "cpu")
    record = {"export": str(path.resolve()), "model_sha256": _digest(path / MODEL_FILE), "agent": export.config.agent,
              "domain": export.config.domain, "frames": int(export.info["frames"])}
    out = Path(eval_dir) if eval_dir is not None else default_evaluation_dir(path)
    if out.resolve() == path.resolve():
        raise ConfigError(f"--eval-dir {out} is the exported model itself; its files are never written")
    if out.is_dir() and any(child.name != ".lock" for child in out.iterdir()):
        if run_kind(out) != PRETRAIN:
            raise RunDirError(f"{out} exists and is not the evaluation directory of an exported model; pass another "
                              "--eval-dir")
        run = PretrainRun.open(out)
        made = run.exported_from()
        if made is None:
            raise RunDirError(f"{out} is a run directory that was trained, not made from an exported model; pass "
                              "another --eval-dir")
        if made.get("model_sha256") != record["model_sha256"]:
            raise RunDirError(f"{out} holds the evaluation of another exported model ({made.get('export')}); pass "
                              "another --eval-dir, or remove it")
        return run, export, False
    check_writable(out)
    run = _unpacked(export, out, False, command)
    run.write_exported_from(record)
    return run, export, True


def remove_evaluation_run(run: PretrainRun) -> None:
    """Remove an evaluation directory that a failed command made, when nothing was evaluated in it."""
    if run.path.is_dir() and {child.name for child in run.path.iterdir()} <= _UNPACKED:
        shutil.rmtree(run.path, ignore_errors=True)


def describe_export(path: Path) -> str:
    info = json.loads((path / CONFIG_FILE).read_text())
    return (f"{path}: {info['agent']} on {info['domain']}, {info['frames']} frames, seed {info['seed']} "
            f"({', '.join(f for f in (MODEL_FILE, CONFIG_FILE, CARD_FILE, INFERENCE_FILE) if (path / f).exists())})")
