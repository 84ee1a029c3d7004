"""A new model warm-started from one trained on a shorter stretch of the same stream.

A model's Gaussians and control points are lifted from its own anchor frames, so a model over more
anchors starts them afresh; what carries over is what every anchor shares: the networks (the time prior
f_theta, Phi and g_phi), the event branch's warm-in scale, and a background layer of the same coverage.
The time prior reads time normalised over the span, so on a longer span it starts from a compressed
copy of the motion it learnt, which training corrects.
"""

from __future__ import annotations

import torch

from edmcgs.model.dynamic import EdMCGS


@torch.no_grad()
def warm_start(model: EdMCGS, previous: EdMCGS) -> list[str]:
    """Copy into ``model`` (in place) every shared part of ``previous`` whose shapes match; returns the
    names of the parts copied."""
    copied = []
    parts = [("prior", model.prior, previous.prior), ("encoder", model.encoder, previous.encoder),
             ("transition", model.transition, previous.transition),
             ("background layer", model.bg_layer, previous.bg_layer)]
    for name, ours, theirs in parts:
        if ours is None or theirs is None:
            continue
        state, mine = theirs.state_dict(), ours.state_dict()
        if state.keys() != mine.keys() or any(state[k].shape != v.shape for k, v in mine.items()):
            continue
        # a layer's buffers place its texture: only the same placement (the same views) carries over
        if any(not torch.equal(state[k], v) for k, v in ours.named_buffers()):
            continue
        ours.load_state_dict(state)
        copied.append(name)
    if "transition" in copied:
        model.event_scale.copy_(previous.event_scale)
    return copied
