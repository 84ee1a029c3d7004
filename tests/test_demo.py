"""The bundled demo scene (`make demo` regenerates it) loads, and its checkpoint fits its recording."""

import numpy as np

from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.sensor.event_map import accumulate
from edmcgs.sensor.files.recording import read_recording
from edmcgs.server import demo


def test_demo_checkpoint_renders_its_recording():
    ckpt, rec_path = demo.files()
    model = load_checkpoint(ckpt)
    rec = read_recording(rec_path)
    meta = model.meta
    assert (meta.event_width, meta.event_height) == (rec.width, rec.height)
    np.testing.assert_array_equal(meta.anchors_us, rec.anchors.t_us)
    t = int(rec.held_out.t_us[len(rec.held_out.t_us) // 2])
    tau = model.tau(t)
    window = rec.events.time_slice(tau, t)
    state = model.deform(t, accumulate(window, rec.width, rec.height))
    image = model.render(state, rec.trajectory_c2w[0] if meta.trajectory is None else meta.trajectory.at(t),
                         meta.intrinsics)
    assert image.shape == (rec.height, rec.width, meta.channels)
    assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1
    # A trained scene, not noise: close to the held-out ground truth.
    truth = rec.held_out.images[len(rec.held_out.t_us) // 2].astype(np.float32) / 255
    psnr = -10 * np.log10(np.mean((image - truth) ** 2))
    assert psnr > 20
