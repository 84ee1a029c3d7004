"""``edmcgs train --poses auto`` then ``edmcgs eval --poses auto``: a recording with no poses becomes a
checkpoint whose camera moves, scored with the poses it was trained with."""

import numpy as np

from edmcgs.cli import main
from edmcgs.model.checkpoint import load_checkpoint
from edmcgs.sensor.events import Events
from edmcgs.sensor.files.recording import Recording, write_recording
from edmcgs.sensor.frames import Frames
from harness.pose_scenes import rigid_sweep, trajectory_error

TINY = ["init_points=500", "num_control_points=24", "deform_width=32", "deform_depth=2", "iterations=4",
        "substeps=4", "max_pair_steps=4", "eval_every=4", "eval_frames=1", "checkpoint_every=4"]


def test_train_and_eval_with_poses_from_the_frames(tmp_path, capsys):
    t_us, images, truth, _ = rigid_sweep(14, 12.5)
    recording = tmp_path / "sweep.h5"  # frames alone: no events, no camera, no poses
    write_recording(recording, Recording(width=173, height=130, events=Events.empty(),
                                         anchors=Frames(t_us, images)))
    ckpt = tmp_path / "sweep.ckpt"
    args = ["train", str(recording), "-o", str(ckpt), "--quiet", "--poses", "auto", "--anchor-every", "3"]
    assert main(args + [a for s in TINY for a in ("--set", s)]) == 0
    out = capsys.readouterr().out
    assert out.count("poses from the frames: 14 of 14 frames registered") == 1
    assert "a static camera" not in out
    model = load_checkpoint(ckpt)
    trajectory = model.meta.trajectory
    assert len(trajectory) == 14 and not trajectory.is_static
    assert np.array_equal(trajectory.t_us, t_us)
    rmse, length = trajectory_error(trajectory.t_us, trajectory.c2w, truth)
    assert rmse <= 0.02 * length
    assert 100 < model.meta.intrinsics.fx < 250  # estimated (the truth: 150)

    assert main(["eval", str(ckpt), str(recording), "--poses", "auto", "-q"]) == 0
    assert "--poses auto: the 14 poses" in capsys.readouterr().out
