"""The data layer: what updates learn from (docs/methods.md §6, "Datasets").

* :mod:`~dvfb.data.batch` -- :class:`Batch`, the transitions an update receives;
* :mod:`~dvfb.data.buffer` -- :class:`ReplayBuffer`, the preallocated episodic replay, and its
  declared :class:`Column` s (the physics states of a dataset);
* :mod:`~dvfb.data.samplers` -- how batches are drawn: uniform, or the authors' loader shards;
* :mod:`~dvfb.data.datasets` -- datasets in ExORL's layout: read, written, relabelled exactly.

The folders beside the modules are the package's shipped data (the bundled demo agent).
"""

from dvfb.data.batch import Batch
from dvfb.data.buffer import PHYSICS_COLUMN, Column, ReplayBuffer, physics_columns
from dvfb.data.datasets import DatasetInfo, read_dataset, read_info, relabel
from dvfb.data.samplers import REPLAY_SAMPLINGS, LoaderShards, ReplaySamplingConfig

__all__ = ["PHYSICS_COLUMN", "REPLAY_SAMPLINGS", "Batch", "Column", "DatasetInfo", "LoaderShards", "ReplayBuffer",
           "ReplaySamplingConfig", "physics_columns", "read_dataset", "read_info", "relabel"]
