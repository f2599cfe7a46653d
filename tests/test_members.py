"""A group of N members (docs/members.md) equals N separate agents: every registered method, after
several updates on the same batches and random streams, in float64 to 1e-10 and in float32 within
a float tolerance; and the stacking itself (states in, states out) is exact."""

from __future__ import annotations

import pytest
import torch

from dvfb.agents import agent_names
from dvfb.nets.members import MemberGenerators, member_training_state, stack_agents
from dvfb.data import Batch
from tiny import MEMBERS, NOT_BITWISE, cast_batch, member_agents

UPDATES = 3


def _run(name: str, dtype: torch.dtype, batch_size: int | None = None):
    agents, twins, replays = member_agents(name, dtype, batch_size)
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        group = stack_agents(agents)
        assert group.members == MEMBERS and isinstance(group.generator, MemberGenerators)
        needs = group.replay_needs()
        group_metrics, twin_metrics = [], []
        for _ in range(UPDATES):
            batches = [cast_batch(needs.sample(replay, twin_gen), dtype)
                       for replay, twin_gen in zip(replays, [torch.Generator().manual_seed(7 + k + 10 * _)
                                                             for k in range(MEMBERS)])]
            group_metrics.append(group.update(Batch.stack(batches)))
            twin_metrics.append([twin.update(batch) for twin, batch in zip(twins, batches)])
    finally:
        torch.set_default_dtype(previous)
    return group, twins, group_metrics, twin_metrics


def _assert_close(group, twins, group_metrics, twin_metrics, rtol, atol, metric_rtol=None, optimizers=True,
                  skip_metrics=(), optimizer_rtol=None):
    for k, twin in enumerate(twins):
        member = member_training_state(group, k)
        separate = twin.training_state()
        assert member["modules"].keys() == separate["modules"].keys()
        for key, value in separate["modules"].items():
            if isinstance(value, torch.Tensor):
                torch.testing.assert_close(member["modules"][key], value, rtol=rtol, atol=atol,
                                           msg=lambda m, key=key, k=k: f"member {k}, {key}: {m}")
        for opt_name, opt_state in (separate["optimizers"].items() if optimizers else ()):
            for i, state in opt_state["state"].items():
                for key, value in state.items():
                    torch.testing.assert_close(member["optimizers"][opt_name]["state"][i][key].double(), value.double(),
                                               rtol=optimizer_rtol if optimizer_rtol is not None else rtol, atol=atol)
        for update, (stacked, separate_metrics) in enumerate(zip(group_metrics, twin_metrics)):
            assert stacked.keys() == separate_metrics[k].keys()
            for key, value in separate_metrics[k].items():
                if key in skip_metrics:
                    continue
                assert stacked[key].shape == (len(twins),), (key, stacked[key].shape)
                torch.testing.assert_close(stacked[key][k], value, rtol=metric_rtol or rtol, atol=atol,
                                           msg=lambda m, key=key, k=k, u=update: f"update {u}, member {k}, {key}: {m}")


@pytest.mark.parametrize("name", agent_names())
def test_group_member_equals_separate_agent_in_float64(name):
    _assert_close(*_run(name, torch.float64), rtol=1e-10, atol=1e-10)


# NOT_BITWISE (tiny.py) holds SMM's and APS's float32 differences. Adam's moments of a few ensemble
# heads (Disagreement, APS) differ in their last bit, without changing any parameter.
MOMENT_RTOL = 1e-6


@pytest.mark.parametrize("name", agent_names())
def test_group_member_equals_separate_agent_bit_for_bit_in_float32(name):
    # The stacked blocks round as the ordinary ones do: one product per member (row_products,
    # MemberLinear), each member's own reductions (member_mean, RunningMeanStd, LayerNorm).
    tolerance = NOT_BITWISE.get(name, 0.0)
    _assert_close(*_run(name, torch.float32), rtol=0.0, atol=tolerance, optimizer_rtol=MOMENT_RTOL)


def _stacked_networks(group, batch):
    """The networks of a group's update with inputs of the group's shapes: what ``--perf.compile``
    and ``--perf.cuda-graphs`` compile."""
    z = batch.z if batch.z is not None and batch.z.shape[-1] else batch.obs.new_zeros(*batch.obs.shape[:-1], 0)
    nets = [("actor", group.actor, (batch.obs, z))]
    if hasattr(group, "forward_map"):
        nets.append(("forward_map", group.forward_map, (batch.obs, batch.action, z)))
        nets.append(("backward_map", group.backward_map, (group.model.label_input(batch.obs, batch.next_obs),)))
    if hasattr(group, "core"):
        nets.append(("critic", group.core.critic, (batch.obs, z, batch.action)))
    return nets


@pytest.mark.parametrize("name", ["fb", "dvfb", "rnd", "diayn"])
def test_stacked_networks_trace_as_one_graph_with_equal_outputs_and_gradients(name):
    """The member path compiles without graph breaks (``fullgraph``; tracing only, the eager
    backend), as ``--perf.compile`` and the CUDA graphs of ``--perf.cuda-graphs`` need, and the
    traced networks give the eager outputs and parameter gradients."""
    agents, _twins, replays = member_agents(name, torch.float32)
    group = stack_agents(agents)
    needs = group.replay_needs()
    batch = Batch.stack([needs.sample(r, torch.Generator().manual_seed(k)) for k, r in enumerate(replays)])
    for label, net, inputs in _stacked_networks(group, batch):
        results = []
        for run in (net, torch.compile(net, fullgraph=True, backend="eager", dynamic=False)):
            net.zero_grad(set_to_none=True)
            out = run(*inputs)
            out.square().sum().backward()
            results.append((out.detach(), [p.grad.clone() for p in net.parameters() if p.grad is not None]))
        (eager, eager_grads), (traced, traced_grads) = results
        assert eager.shape[0] == MEMBERS, label
        assert torch.equal(traced, eager), label
        assert len(traced_grads) == len(eager_grads) > 0 and all(
            torch.equal(a, b) for a, b in zip(traced_grads, eager_grads)), label
        torch._dynamo.reset()
