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

from dvfb.core.errors import NonFiniteLossError


class MetricWindow:
    """Per-update metric tensors kept on the device, read back once per window.

    :meth:`check` stacks the rows added since the last read into one tensor and copies it to the
    host (the only sync), raises :class:`NonFiniteLossError` naming the first update and loss that
    went NaN/inf, and keeps the rows on the host; :meth:`flush` checks and returns the means of
    every row kept since the last flush. Every checkpoint checks first, so a non-finite value is
    never checkpointed, and saves the rows kept so far (:meth:`state`), so that a run resumed from
    it logs the same window means at the same steps as one that never stopped (docs/methods.md,
    "Training loop"). (A non-finite value is reported at the next check, at most ``log_every``
    steps later, naming the exact step.)

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
        # The checked rows of the window, on the host, by member (None: a single run's):
        # (metric names, [(updates, metrics) arrays]).
        self.kept: dict[object, tuple[list[str], list[np.ndarray]]] = {}

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        self.steps.append(step)
        self.rows.append(metrics)

    def _read(self, shape: tuple) -> tuple[list[str], np.ndarray, list[int]]:
        """The new rows as ``(keys, values (updates, metrics, *shape), steps)`` in one host sync, emptied."""
        keys = list(self.rows[0])
        table = torch.stack([torch.stack([row[k].float().reshape(shape) for k in keys]) for row in self.rows])
        steps, self.steps, self.rows = self.steps, [], []
        return keys, table.cpu().numpy(), steps

    def _keep(self, who, keys: list[str], values: np.ndarray) -> None:
        names, chunks = self.kept.setdefault(who, (keys, []))
        if names != keys:  # pragma: no cover - a learner's metrics do not change names mid-run
            raise RuntimeError(f"the update's metrics changed from {names} to {keys} within a window")
        chunks.append(values)

    def check(self) -> None:
        """Read the new rows to the host, stop at (or, in a group, report) non-finite values, and
        keep the rest for the next :meth:`flush`."""
        if not self.rows:
            return
        if self.members is None:
            keys, values, steps = self._read(())
            message = nonfinite_message(keys, values, steps, self.hint)
            if message is not None:
                raise NonFiniteLossError(message)
            self._keep(None, keys, values)
            return
        keys, values, steps = self._read((-1,))  # values: (updates, metrics, members)
        faults = []
        for i, member in enumerate(self.members()):
            message = nonfinite_message(keys, values[:, :, i], steps, self.hint)
            if message is None:
                self._keep(id(member), keys, values[:, :, i])
            else:
                faults.append((member, message))
        for member, message in faults:
            self.on_fault(member, message)

    def take(self, who=None) -> dict[str, float]:
        """The means of ``who``'s kept rows (one array, so that they do not depend on where checks
        split the window), which the window then forgets; {} when there are none."""
        if who not in self.kept:
            return {}
        keys, chunks = self.kept.pop(who)
        values = chunks[0] if len(chunks) == 1 else np.concatenate(chunks)
        return dict(zip(keys, values.mean(0).tolist()))

    def flush(self) -> dict[str, float]:
        """:meth:`check`, then a single run's window means ({} for a group: see :meth:`member_window`)."""
        self.check()
        return self.take(None) if self.members is None else {}

    def state(self, who=None) -> dict | None:
        """``who``'s kept rows, for a resume checkpoint (call :meth:`check` first); None when empty."""
        if who not in self.kept:
            return None
        keys, chunks = self.kept[who]
        return {"keys": list(keys), "values": torch.from_numpy(np.concatenate(chunks))}

    def load_state(self, state: dict | None, who=None) -> None:
        """Start with the rows a checkpoint's :meth:`state` saved (None: an empty window)."""
        self.kept.pop(who, None)
        if state is not None:
            self.kept[who] = (list(state["keys"]), [state["values"].numpy()])

    def member_window(self, member) -> MemberWindow:
        return MemberWindow(self, member)


class MemberWindow:
    """One member's view of a group's :class:`MetricWindow`: :meth:`flush` gives its own window
    means, :meth:`state` its own kept rows."""

    def __init__(self, group: MetricWindow, member) -> None:
        self.group, self.member = group, member

    def add(self, step: int, metrics: dict[str, torch.Tensor]) -> None:
        raise RuntimeError("a group's metrics go to its window")

    def check(self) -> None:
        self.group.check()

    def flush(self) -> dict[str, float]:
        self.group.check()
        return self.group.take(id(self.member))

    def state(self) -> dict | None:
        return self.group.state(id(self.member))

    def load_state(self, state: dict | None) -> None:
        self.group.load_state(state, id(self.member))


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
