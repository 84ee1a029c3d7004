"""The events' bounds on each pixel: the sensor's own log-intensity model, and a render clipped into it."""

import numpy as np
import pytest

from edmcgs.errors import InvalidInputError
from edmcgs.luminance import LOG_EPS
from edmcgs.model.online.bounds import integrate, project

C = 0.2


def test_integration_is_the_log_intensity_model_and_stays_finite():
    frame = np.full((2, 3, 1), 0.5, np.float32)
    events = np.array([[3, 0, -2], [0, 1e6, -1e6]], np.float32)  # a burst either way saturates
    got = integrate(frame, events, C)
    want = (0.5 + LOG_EPS) * np.exp(C * np.array([[3, 0, -2], [0, 0, 0]])) - LOG_EPS
    assert np.allclose(got[0, :, 0], want[0], atol=1e-6)
    assert got[1, 1, 0] == 1.0 and got[1, 2, 0] == 0.0 and np.isfinite(got).all()
    # events at half the frame's resolution: each pixel takes its nearest event pixel
    big = integrate(np.full((4, 6, 3), 0.5, np.float32), events, C)
    assert big.shape == (4, 6, 3) and np.allclose(big[::2, ::2, 0], got[..., 0], atol=1e-6)
    # at another output size, the frame is taken at its nearest pixel too
    half = integrate(np.full((4, 6, 3), 0.5, np.float32), events, C, size=(3, 2))
    assert np.allclose(half, got.repeat(3, axis=2), atol=1e-6)


def test_project_keeps_what_the_events_allow_and_overrules_the_rest():
    frame = np.full((1, 4, 1), 0.2, np.float32)
    events = np.array([[0, 0, 5, -5]], np.float32)
    render = np.array([[[0.21], [0.5], [0.21], [0.07]]], np.float32)
    out = project(render, frame, events, C)
    lo = (0.2 + LOG_EPS) * np.exp(C * np.array([0, 0, 5, -5]) - C) - LOG_EPS
    hi = (0.2 + LOG_EPS) * np.exp(C * np.array([0, 0, 5, -5]) + C) - LOG_EPS
    assert out[0, 0, 0] == pytest.approx(0.21)  # no events, within a threshold of the frame: kept
    assert out[0, 1, 0] == pytest.approx(hi[1], abs=1e-6)  # no events, yet far brighter: clipped down
    assert out[0, 2, 0] == pytest.approx(lo[2], abs=1e-6)  # five ON events: at least that much brighter
    assert out[0, 3, 0] == pytest.approx(0.07)  # five OFF events: darker, as the render already is
    assert (out >= lo[None, :, None] - 1e-6).all() and (out <= hi[None, :, None] + 1e-6).all()


def test_project_at_the_render_size_and_never_lets_a_nan_through():
    frame = np.random.default_rng(0).random((13, 17, 3)).astype(np.float32)
    events = np.random.default_rng(1).integers(-50, 50, (13, 17)).astype(np.float32)
    render = np.full((26, 34, 3), np.nan, np.float32)
    render[::2] = np.inf
    out = project(render, frame, events, C)
    assert out.shape == (26, 34, 3) and np.isfinite(out).all() and (out >= 0).all() and (out <= 1).all()
    # the bounds at the render's size are the frame's at each pixel's nearest source pixel
    lo = integrate(frame, events, C, shift=-C)
    assert np.array_equal(out[1::2, ::2], lo[:, :, :])  # the NaN rows took the lower bound


@pytest.mark.parametrize("bad", [
    dict(contrast=0.0), dict(contrast=float("nan")), dict(events=np.full((2, 2), np.inf)),
    dict(frame=np.zeros((2, 2))), dict(image=np.zeros((2, 2, 1))),
])
def test_bad_input_is_refused_by_name(bad):
    args = dict(image=np.zeros((2, 2, 3)), frame=np.zeros((2, 2, 3)), events=np.zeros((2, 2)),
                contrast=C) | bad
    with pytest.raises(InvalidInputError):
        project(args["image"], args["frame"], args["events"], args["contrast"])
