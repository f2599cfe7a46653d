"""Shared network building blocks (docs/methods.md §3-§5, "Shared blocks"), one room per kind:

* :mod:`~dvfb.nets.layers` -- init, EMA targets, Adam, the twin TD loss, MLPs, :class:`TwinHead`;
* :mod:`~dvfb.nets.geometry` -- the sphere projection and the z prior;
* :mod:`~dvfb.nets.policy` -- the policy's sampling helpers, :class:`Actor`, :class:`HostActor`;
* :mod:`~dvfb.nets.maps` -- F, B, the skill values, the twin critic and the orthonormality loss;
* :mod:`~dvfb.nets.features` -- the SF family's feature learners (registered by name);
* :mod:`~dvfb.nets.stats` -- :class:`RunningMeanStd`.

Every name is also importable from ``dvfb.nets``. The layer also holds what a method's networks
stand on: :mod:`~dvfb.nets.skills` (a method's skill), :mod:`~dvfb.nets.execution`
(precision, compilation, the device), :mod:`~dvfb.nets.learner` (the learner contract) and
:mod:`~dvfb.nets.members` (the member axis of groups). The intrinsic-reward networks live in
:mod:`dvfb.rewards`.
"""

from dvfb.nets.geometry import NORM_FLOOR, project_to_sphere, sample_z_prior  # noqa: F401
from dvfb.nets.layers import (  # noqa: F401
    TWIN_HEAD_INITS, TwinHead, adam, call_network, freeze_, full_precision, layernorm_tanh_layer, make_target, mlp,
    orthogonal_init_, soft_update_, twin_td_loss)
from dvfb.nets.maps import (  # noqa: F401
    BackwardMap, ForwardMap, TwinCritic, implicit_reward, offdiag_mean, orthonormality_loss, skill_values)
from dvfb.nets.policy import (  # noqa: F401
    ACTION_EPS, Actor, HostActor, TwoStreamEncoder, rollout_action, standard_normal, training_action)
from dvfb.nets.stats import RunningMeanStd  # noqa: F401
