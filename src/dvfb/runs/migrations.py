"""Every older format a run directory may hold, read as today's or refused with one line naming its
format version (docs/architecture.md, "Run directories").

* **Run configs** (``config.json``): a field that moved into a method's section since it was
  written is moved there, and a config from before the evaluations while pre-training records
  ``eval_every`` 0 (:func:`migrate_run_config`); a fine-tuning run of the method's own
  fine-tuner, which recorded no protocol (or an empty one), records its name
  (:func:`migrate_finetune_run_config`).
* **Run kinds**: runs written before ``meta.json`` recorded the kind of run are told apart by
  their config's fields (:func:`kind_from_config`).
* **Resume checkpoints** (``checkpoints/*.pt``): format 2 resumes; format 1, written before runs
  owned their random streams, is refused (:func:`check_resume_format`).
* **Snapshots** (``snapshots/*.pt``): formats 1 (no ``format`` key, DVFB and FB only) and 2 load;
  a newer one is refused (:func:`check_snapshot_format`).
* **Training states inside resume checkpoints**: module keys renamed since
  (:func:`migrate_training_state`: DVFB's contrastive encoders moved under ``contrastive.encoders``).
"""

from __future__ import annotations

from typing import Any

from dvfb.core.errors import CheckpointError

RESUME_FORMAT = 2
SNAPSHOT_FORMAT = 2
# Module keys of training states renamed since they were written, per method: (a key prefix that
# only the old layout has, the old prefix, the new one). DVFB's contrastive encoders moved under
# "contrastive.encoders." when the reward modules moved to dvfb.rewards.
RENAMED_MODULES = {"dvfb": ("contrastive.state_net.", "contrastive.", "contrastive.encoders.")}


def migrate_run_config(data: dict, spec: Any) -> dict:
    """A pre-training config written by an older version, as today's (``spec``: the method's
    :class:`~dvfb.agents.registry.AgentSpec`).

    * A top-level field or section that moved into a method's section (``moved_fields`` of its spec, e.g.
      the skill resampling period ``update_z_every`` -> ``fb.skill_every``) is moved there; one it
      maps to None is dropped (online FB's configs once carried DVFB's unused ``exploration``).
      A skill period of a method without skills, which never used it, is dropped too.
    """
    data = dict(data)
    for old, new in spec.moved_fields.items():
        if old in data:
            value = data.pop(old)
            if new is not None:  # None: a field the method's runs carried but never used
                section, key = new.split(".", 1)
                data[section] = {**data.get(section, {}), key: value}
    data.pop("update_z_every", None)  # methods without skills ignored the global period
    # Written before the evaluations while pre-training existed: the run never evaluated, and a
    # resume keeps it so unless --eval-every asks (the other eval_* fields take their defaults).
    data.setdefault("eval_every", 0)
    return data


def migrate_finetune_run_config(data: dict, spec: Any) -> dict:
    """A fine-tuning config written by an older version, as today's (``spec``: the method's
    :class:`~dvfb.agents.registry.AgentSpec`): a run of the method's own fine-tuner recorded an
    empty ``protocol`` (or, before ``--protocol``, none); today it records the fine-tuner's name."""
    if data.get("protocol", "") == "":
        return {**data, "protocol": spec.finetuner}
    return data


def kind_from_config(data: Any) -> str | None:
    """``"pretrain"``, ``"finetune"`` or None (not a dvfb run config) from a ``config.json``'s
    contents: how runs whose ``meta.json`` records no kind are told apart."""
    if not isinstance(data, dict):
        return None
    if "pretrain_run" in data and "task" in data:
        return "finetune"
    if isinstance(data.get("agent"), str) and "domain" in data and "frames" in data:
        return "pretrain"
    return None


def check_resume_format(state: dict, where) -> None:
    """Resume checkpoints from before runs owned their random streams (format 1) cannot continue
    exactly: refuse them with one line."""
    fmt = state.get("format", 1)
    if fmt != RESUME_FORMAT:
        raise CheckpointError(f"{where}: the resume checkpoint has format {fmt!r}; this dvfb resumes format "
                              f"{RESUME_FORMAT} (format 1 was written before runs owned their random streams and "
                              "cannot continue exactly): start the run again, or finish it with the dvfb version "
                              "that wrote it")


def check_snapshot_format(state: dict, where) -> int:
    """The format of a snapshot this dvfb reads (1: before the agent registry, no ``format`` key;
    2: today's); a newer one is refused with one line."""
    fmt = state.get("format", 1)
    if not isinstance(fmt, int) or fmt > SNAPSHOT_FORMAT:
        raise CheckpointError(f"{where} has snapshot format {fmt!r}, newer than this dvfb reads "
                              f"({SNAPSHOT_FORMAT}); upgrade dvfb")
    return fmt


def migrate_training_state(agent: str, state: dict) -> dict:
    """A learner's training state (``modules`` and ``optimizers``) with module keys renamed since
    it was written brought up to date."""
    rename = RENAMED_MODULES.get(agent)
    modules = state.get("modules")
    if rename is None or not isinstance(modules, dict):
        return state
    marker, old, new = rename
    if not any(key.startswith(marker) for key in modules):
        return state
    return {**state, "modules": {new + key[len(old):] if key.startswith(old) else key: value
                                 for key, value in modules.items()}}


__all__ = ["RESUME_FORMAT", "SNAPSHOT_FORMAT", "check_resume_format", "check_snapshot_format", "kind_from_config",
           "migrate_finetune_run_config", "migrate_run_config", "migrate_training_state"]
