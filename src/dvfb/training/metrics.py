"""Metric windows: per-update metric tensors kept on the device and read back once per window,
with the non-finite check (docs/methods.md, "Training loop").

* :class:`MetricWindow` -- one host sync every ``log_every`` steps, checking for NaN/inf values;
* :class:`GroupWindow` / :class:`MemberWindow` -- a group's window (docs/members.md), one entry per
  member, and each member's view of it;
* :func:`check_action` -- stops on a non-finite action before the physics rejects it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from dvfb.errors import NonFiniteLossError


class MetricWindow:
    """Per-update metric tensors kept on the device, read back once per window.

    ``flush`` stacks the window into one tensor, copies it to the host (the only sync), raises
    :class:`NonFiniteLossError` naming the first update and loss that went NaN/inf, and returns
    the window means. (So a non-finite value is reported at the next flush, at most ``log_every``
    steps later, naming the exact step; no checkpoint is written in between, because every
    checkpoint flushes first.)
    """

    def __init__(self, hint: Callable[[list[str]], str] | None = None) -> None:
        self.steps: list[int] = []
        self.rows: list[dict[str, torch.Tensor]] = []
        # What the method can tell about its non-finite metrics (Agent.nonfinite_hint).
        self.hint = hint

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
        keys, values, steps = self._read(())
        message = nonfinite_message(keys, values, steps, self.hint)
        if message is not None:
            raise NonFiniteLossError(message)
        return dict(zip(keys, values.mean(0).tolist()))


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


class GroupWindow(MetricWindow):
    """A group's metric window (docs/members.md): per-update metrics of shape ``(M,)``, one entry
    per live member, read back in one host sync per window for all members.

    A member whose metrics went non-finite is reported to ``on_fault(member, message)`` (which
    stops it) and the others go on; :meth:`member_window` gives each member a window of its own
    to read its means from. ``members()`` lists the live members in stack order.
    """

    def __init__(self, members: Callable[[], list], on_fault: Callable[[object, str], None],
                 hint: Callable[[list[str]], str] | None = None) -> None:
        super().__init__(hint)
        self.members, self.on_fault = members, on_fault
        self.pending: dict[int, dict[str, float]] = {}

    def flush(self) -> dict[str, float]:
        if not self.rows:
            return {}
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


class MemberWindow:
    """One member's view of a :class:`GroupWindow`: :meth:`flush` gives its own window means."""

    def __init__(self, group: GroupWindow, member) -> None:
        self.group, self.member = group, member

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        raise RuntimeError("a group's metrics go to its GroupWindow")

    def flush(self) -> dict[str, float]:
        self.group.flush()
        return self.group.pending.pop(id(self.member), {})


def check_action(action: np.ndarray, step: int, window: MetricWindow) -> None:
    """Stop on a non-finite action (a diverged actor) before MuJoCo rejects it.

    Flushing the window first names the first non-finite loss when one is there.
    """
    if not np.isfinite(action).all():
        window.flush()
        raise NonFiniteLossError(f"the policy produced a non-finite action at step {step}")
