"""Deprecated: the replay moved to :mod:`dvfb.data` (``from dvfb.data import ReplayBuffer, Batch``)."""

import warnings

from dvfb.data.batch import Batch  # noqa: F401
from dvfb.data.buffer import PHYSICS_COLUMN, Column, ReplayBuffer, physics_columns  # noqa: F401
from dvfb.data.samplers import REPLAY_SAMPLINGS, LoaderShards, ReplaySamplingConfig  # noqa: F401

warnings.warn("dvfb.replay is deprecated; import from dvfb.data", DeprecationWarning, stacklevel=2)
