"""Deprecated: datasets moved to :mod:`dvfb.data.datasets` (``from dvfb.data import read_dataset``);
``dvfb dataset export`` is :func:`dvfb.workflows.datasets.export_run`."""

import warnings

from dvfb.data.datasets import (  # noqa: F401
    DATASET_FORMAT, DatasetInfo, describe, load_episode, read_dataset, read_info, relabel, write_dataset)

warnings.warn("dvfb.datasets is deprecated; import from dvfb.data", DeprecationWarning, stacklevel=2)
