"""Anchor windows (config.anchor_windows): which Gaussians and control points one window draws and moves.

With anchor windows a Gaussian is drawn only in the gap after the anchor it was lifted from, moved by
that window's control points; a static set (config.static_set) is drawn in every gap, moved by none.
Whatever the recording's length, a query at t (a render, a training step) then needs one window's rows
alone: its Gaussians, the control points they are bound to, the points born in the window and their
graph neighbours (a window with fewer than K points binds some of its Gaussians to a neighbouring
window's), and the static set. ``WindowRows`` are those rows, local indices included, so that the work
of a step or a render follows the window, not the number of windows.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from edmcgs.model.motion.gaussians import STATIC


@dataclass(frozen=True)
class WindowRows:
    """The rows of one anchor window (indices into the model's tensors, int64, on their device).

    gaussians: Tensor  # [Nw] the Gaussians living in the window, ascending
    control: Tensor    # [Mw] the control points the window needs: its own first (ascending), then the
                       #      others its Gaussians are bound to or its own points neighbour (ascending)
    own: int           # how many of ``control`` are born in the window (the first ``own``)
    bind: Tensor       # [Nw, K] each Gaussian's control points, as indices into ``control``
    graph: Tensor      # [own, K_conn] the own points' graph neighbours, as indices into ``control``
    drawn: Tensor      # [Nd] what a query in the window draws, ascending: ``gaussians`` and the static set
    skinned: Tensor    # [Nw] where ``gaussians`` stand in ``drawn`` (all of it without a static set)
    """

    gaussians: Tensor
    control: Tensor
    own: int
    bind: Tensor
    graph: Tensor
    drawn: Tensor
    skinned: Tensor


def window_rows(gaussian_birth: Tensor, control_birth: Tensor, bind: Tensor, graph: Tensor,
                window: int) -> WindowRows:
    """The rows of ``window`` from the Gaussians' and control points' windows, the binding [N, K] and
    the control points' graph [M, K_conn]."""
    drawn = torch.nonzero((gaussian_birth == window) | (gaussian_birth == STATIC))[:, 0]
    skinned = torch.nonzero(gaussian_birth[drawn] == window)[:, 0]
    gaussians = drawn[skinned]
    own = torch.nonzero(control_birth == window)[:, 0]
    needed = torch.cat([bind[gaussians].reshape(-1), graph[own].reshape(-1)])
    others = torch.unique(needed[control_birth[needed] != window])  # ascending
    control = torch.cat([own, others])
    local = torch.full((control_birth.shape[0],), -1, dtype=torch.long, device=control.device)
    local[control] = torch.arange(control.shape[0], device=control.device)
    return WindowRows(gaussians, control, int(own.shape[0]), local[bind[gaussians]], local[graph[own]], drawn,
                      skinned)


def with_static(rows: WindowRows, gaussian_birth: Tensor, static: Tensor) -> WindowRows:
    """``rows`` drawing, beside the window's Gaussians, only the static rows ``static`` (int64, ascending):
    those a training step's cameras can see (``render.projection.may_draw``)."""
    mask = torch.zeros(gaussian_birth.shape[0], dtype=torch.bool, device=gaussian_birth.device)
    mask[rows.gaussians] = True
    mask[static] = True
    drawn = torch.nonzero(mask)[:, 0]
    return replace(rows, drawn=drawn, skinned=torch.nonzero(gaussian_birth[drawn] != STATIC)[:, 0])


WINDOWS_KEPT = 16
"""Windows whose rows an index keeps (the last used): each holds a copy of the static set's indices,
which for every window of a long moving-camera recording would grow as windows x static set."""


class WindowIndex:
    """Windows' rows, built on use and kept (the ``WINDOWS_KEPT`` last used) while the tensors they derive
    from are unchanged (``key``: the binding and the windows of a model; a rebind or a densification
    changes it)."""

    def __init__(self, key: tuple):
        self.key = key
        self._rows: dict[int, WindowRows] = {}

    def rows(self, window: int, gaussian_birth: Tensor, control_birth: Tensor, bind: Tensor,
             graph: Tensor) -> WindowRows:
        found = self._rows.pop(window, None)
        if found is None:
            found = window_rows(gaussian_birth, control_birth, bind, graph, window)
        self._rows[window] = found  # newest last
        for old in list(self._rows)[:-WINDOWS_KEPT]:
            self._rows.pop(old, None)
        return found
