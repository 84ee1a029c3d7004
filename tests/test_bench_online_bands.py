"""bench.online's drift summary: bands of mean PSNR, and beside them the pooled PSNR that a few
near-exact frames cannot outweigh."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from bench.online import bands, pooled


def test_pooled_psnr_weighs_every_pixel_alike():
    assert pooled([]) is None
    assert pooled([(20.0, 5)]) == pytest.approx(20.0)
    # mean squared errors 1e-2 and 1e-4, equally many pixels: 10 log10(1 / 5.05e-3), not the mean of dB
    assert pooled([(20.0, 1), (40.0, 1)]) == pytest.approx(-10 * math.log10(0.5 * (1e-2 + 1e-4)))
    assert pooled([(20.0, 3), (40.0, 1)]) == pytest.approx(-10 * math.log10((3e-2 + 1e-4) / 4))


def test_a_band_where_hold_last_is_near_exact_on_one_frame():
    # live wins 3 frames of 4 by 2 dB; on the fourth the scene is back at its anchor: hold-last 40 dB
    row = {"live_model": 21.0, "no_corr": 20.0, "no_events": 20.0, "hold_projected": 24.5, "integrate": 25.0}
    # numpy scores, as bench.online's renders give them: the summary must still be plain JSON
    rows = [row | {"since_end_s": 0.1 * (i + 1), "live": np.float64(24.0), "hold_last": np.float64(22.0)}
            for i in range(3)]
    rows.append(row | {"since_end_s": 0.5, "live": 24.0, "hold_last": 40.0})
    rows = [r | {"blend": 23.0} for r in rows]  # the anchors either side, in the first band only
    rows.append(row | {"since_end_s": 1.5, "live": 23.0, "hold_last": 23.0})
    first, second = bands(rows)
    assert first["frames"] == 4 and first["live_wins"] == 3
    assert first["live"] - first["hold_last"] == pytest.approx(24.0 - 26.5)  # the mean of dB: lost
    assert first["live_pooled"] == pytest.approx(24.0)
    assert first["hold_last_pooled"] == pytest.approx(-10 * math.log10((3 * 10 ** -2.2 + 1e-4) / 4))
    assert first["live_pooled"] > first["hold_last_pooled"]  # pooled: won
    assert first["blend"] == first["blend_pooled"] == pytest.approx(23.0)
    assert second["blend"] is None and second["blend_pooled"] is None  # past the last anchor: no blend
    assert second["live_wins"] == 1 and (second["from_s"], second["to_s"]) == (1.0, 2.0)
    assert json.loads(json.dumps([first, second])) == [first, second]
