"""Metric windows: per-update metric tensors kept on the device and read back once per window,
with the non-finite check (docs/methods.md, "Training loop").

* :class:`MetricWindow` -- one host sync every ``log_every`` steps, checking for NaN/inf values
  (a group's: one entry per member, docs/members.md);
* :class:`MemberWindow` -- a group member's view of it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from dvfb.errors import NonFiniteLossError


class MetricWindow:
    """Per-update metric tensors kept on the device, read back once per window.

    ``flush`` stacks the window into one tensor and copies it to the host (the only sync). For a run,
    it raises :class:`NonFiniteLossError` naming the first update and loss that went NaN/inf, and
    returns the window means. (So a non-finite value is reported at the next flush, at most
    ``log_every`` steps later, naming the exact step; no checkpoint is written in between, because
    every checkpoint flushes first.)

    For a group (docs/members.md), ``members()`` lists the live members in stack order and every
    metric of an update has shape ``(M,)``, one entry per member: a member whose metrics went
    non-finite is reported to ``on_fault(member, message)`` (which stops it) and the others go on;
    :meth:`member_window` gives each member a window of its own to read its means from.
    """

    def __init__(self, hint: Callable[[list[str]], str] | None = None, members: Callable[[], list] | None = None,
                 on_fault: Callable[[object, str], None] | None = None) -> None:
        self.steps: list[int] = []
        self.rows: list[dict[str, torch.Tensor]] = []
        # What the method can tell about its non-finite metrics (Model.nonfinite_hint).
        self.hint = hint
        self.members, self.on_fault = members, on_fault
        self.pending: dict[int, dict[str, float]] = {}

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        self.steps.append(step)
        self.rows.append(metrics)

    def _read(self, shape: tuple) -> tuple[list[str], np.ndarray, list[int]]:
        """The window as ``(keys, values (updates, metrics, *shape), steps)`` in one host sync, emptied."""
        keys = list(self.rows[0])
        table = torch.stack([torch.stack([row[k].float().reshape(shape) for k in keys]) for row in self.rows])
        steps, self.steps, self.rows = self.steps, [], []
        return keys, table.cpu().numpy(), steps

    def flush(self) -> dict[str, float]:
        if not self.rows:
            return {}
        if self.members is None:
            keys, values, steps = self._read(())
            message = nonfinite_message(keys, values, steps, self.hint)
            if message is not None:
                raise NonFiniteLossError(message)
            return dict(zip(keys, values.mean(0).tolist()))
        keys, values, steps = self._read((-1,))  # values: (updates, metrics, members)
        faults = []
        for i, member in enumerate(self.members()):
            message = nonfinite_message(keys, values[:, :, i], steps, self.hint)
            if message is None:
                self.pending[id(member)] = dict(zip(keys, values[:, :, i].mean(0).tolist()))
            else:
                faults.append((member, message))
        for member, message in faults:
            self.on_fault(member, message)
        return {}

    def member_window(self, member) -> MemberWindow:
        return MemberWindow(self, member)


def nonfinite_message(keys: list[str], values: np.ndarray, steps: list[int], hint) -> str | None:
    """The one line naming the first update and loss of a ``(updates, metrics)`` table that went
    NaN/inf (with the method's hint), or None when every value is finite."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    row, col = np.argwhere(bad)[0]
    bad_keys = [keys[c] for c in np.flatnonzero(bad[row])]
    hint = hint(bad_keys) if hint is not None else ""
    hint = f"; {hint}" if hint else ""
    return (f"non-finite value {keys[col]}={values[row, col]} at step {steps[row]} "
            f"(non-finite there: {', '.join(bad_keys)}){hint}")


class MemberWindow:
    """One member's view of a group's :class:`MetricWindow`: :meth:`flush` gives its own window means."""

    def __init__(self, group: MetricWindow, member) -> None:
        self.group, self.member = group, member

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        raise RuntimeError("a group's metrics go to its window")

    def flush(self) -> dict[str, float]:
        self.group.flush()
        return self.group.pending.pop(id(self.member), {})
