"""The runs layer: the one place that knows the run directory (docs/architecture.md, "Run directories").

Every run (pre-training, fine-tuning) owns one directory; the kinds of run, their paths and records
are :mod:`~dvfb.runs.layout`'s. What every run directory has::

    <run>/
      config.json              the full resolved typed config (dvfb.runs.run_config)
      meta.json                kind of run, config class, dvfb version, creation time, command line
      metrics/<prefix>.jsonl   one JSON object per MetricsLogger.log call: {"step": 1000, "x": 0.5}
      tb/                      TensorBoard event files, scalar tags "<prefix>/<name>"
      checkpoints/<name>.pt    resume checkpoints (torch.save of a state dict)
      checkpoints/latest       text file holding the file name of the current resume checkpoint
      snapshots/<name>.pt      checkpoints kept for good (e.g. the model after N steps)
      results/                 machine-readable results, written with write_json_atomic

Writes that a crash must not leave half done (checkpoints, the ``latest`` pointer, results, meta)
go to a temporary file in the same directory, are flushed and fsync'ed, and then renamed over the
target with ``os.replace``, which is atomic on POSIX and Windows: a reader sees the old file or the
new one, never a mixture. ``save_checkpoint`` moves ``latest`` only after the new checkpoint is
complete, and deletes the checkpoint it replaced only after that, so at every instant ``latest``
names a complete file. One process writes a run directory at a time.

Checkpoints are read with ``torch.load(weights_only=True)`` by default, so a state should hold
only tensors, numbers, strings, ``None`` and lists/tuples/dicts of these (``torch.get_rng_state()``
and ``numpy.random.Generator.bit_generator.state`` qualify; legacy ``np.random.get_state()``
does not).

The rooms: :mod:`~dvfb.runs.directory` (the run directory and its lock),
:mod:`~dvfb.runs.metrics`, :mod:`~dvfb.runs.checkpoints` (their public names are importable from
``dvfb.runs``, with the atomic files of :mod:`dvfb.core.files`); :mod:`~dvfb.runs.layout` (the kinds of
run, their paths, records and discovery), :mod:`~dvfb.runs.records`, :mod:`~dvfb.runs.run_config`,
:mod:`~dvfb.runs.presets`, :mod:`~dvfb.runs.snapshots` and :mod:`~dvfb.runs.migrations` (imported
by name: they load the agents' registry).
"""

from dvfb.core.files import read_json, write_json_atomic  # noqa: F401
from dvfb.runs.checkpoints import (  # noqa: F401
    CHECKPOINT_SUFFIX,
    LATEST_POINTER,
    PRETRAIN_RESUME_KIND,
    latest_checkpoint,
    list_snapshots,
    load_checkpoint,
    load_snapshot,
    remove_orphaned_checkpoints,
    save_checkpoint,
    save_snapshot,
)
from dvfb.runs.directory import CONFIG_FILE, LOCK_FILE, META_FILE, RunDir, RunLock, check_writable  # noqa: F401
from dvfb.runs.metrics import MetricsLogger, last_metric_record, read_metrics, recent_rate  # noqa: F401
