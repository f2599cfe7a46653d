"""Shared test set-up.

* Import dvfb.envs first so its headless MUJOCO_GL default applies before any test module imports
  dm_control.
* One torch thread: the tests use tiny networks, for which thread start-up costs more than it
  saves, and results are then independent of the machine's core count.
"""

import torch

import dvfb.envs  # noqa: F401

torch.set_num_threads(1)
