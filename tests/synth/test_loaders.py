"""The public-layout loaders, on small datasets written here (PNG through pillow, events as npz)."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from edmcgs.errors import ReplayFormatError
from edmcgs.geometry import Intrinsics, project, world_to_camera
from edmcgs.sensor.files.recording import read_recording, write_recording
from edmcgs.synth.loaders import load_dnerf, load_ed3dgs

W, H = 8, 6
ANGLE = 0.8


def _blender_c2w(eye_z: float) -> list:
    """A Blender camera on the +z axis looking down -z at the origin (identity rotation)."""
    m = np.eye(4)
    m[2, 3] = eye_z
    return m.tolist()


def _png(path, value: int, alpha: bool = False):
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.full((H, W, 4 if alpha else 3), value, np.uint8)
    if alpha:
        img[..., 3] = 255
        img[0, 0, 3] = 0  # one transparent pixel
    Image.fromarray(img).save(path)


def _events_npz(path, t_ns, x, y, p):
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, x=np.asarray(x, np.int16), y=np.asarray(y, np.int16), t=np.asarray(t_ns, np.int64),
             p=np.asarray(p, np.int8))


@pytest.fixture
def dnerf(tmp_path):
    for split, times in (("train", [0.0, 0.5, 1.0]), ("test", [0.25, 0.75])):
        frames = []
        for i, t in enumerate(times):
            _png(tmp_path / split / f"r_{i:03d}.png", 40 + 60 * i, alpha=True)
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": t,
                           "transform_matrix": _blender_c2w(4.0 + t)})
        data = {"camera_angle_x": ANGLE, "frames": frames}
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps(data))
    # events over 2 s on the event clock, out of order, one outside the 8x6 image
    _events_npz(tmp_path / "events" / "events.npz", t_ns=[2_000_000_000, 0, 999_999_999, 1_500_000_000],
                x=[1, 2, 8, 3], y=[1, 2, 3, 5], p=[1, -1, 1, -1])
    return tmp_path


def test_dnerf_layout(dnerf, tmp_path):
    rec = load_dnerf(dnerf)
    assert (rec.width, rec.height) == (W, H)
    assert list(rec.events.t) == [0, 1_500_000, 2_000_000]  # ns -> µs, sorted
    assert rec.metadata["event_stats"]["out_of_bounds"] == 1
    # time in [0, 1] spans the events' clock
    assert list(rec.anchors.t_us) == [0, 1_000_000, 2_000_000]
    assert list(rec.held_out.t_us) == [500_000, 1_500_000]
    assert list(rec.trajectory_t_us) == [0, 500_000, 1_000_000, 1_500_000, 2_000_000]
    # RGBA over white; RGB channels kept
    assert rec.anchors.images.shape == (3, H, W, 3)
    assert list(rec.anchors.images[1, 0, 0]) == [255, 255, 255] and rec.anchors.images[1, 1, 1, 0] == 100
    fx = 0.5 * W / math.tan(0.5 * ANGLE)
    np.testing.assert_allclose(rec.intrinsics, [fx, fx, (W - 1) / 2, (H - 1) / 2])
    # OpenCV poses: the camera looks down world -z, image up is world +y
    c2w = rec.anchors.poses[0]
    np.testing.assert_allclose(c2w[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], [0, -1, 0], atol=1e-12)
    k = Intrinsics(*rec.intrinsics, W, H)
    uv, depth = project(np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0]]), world_to_camera(c2w), k)
    np.testing.assert_allclose(uv[0], [k.cx, k.cy]) and np.testing.assert_allclose(depth, [4.0, 4.0])
    assert uv[1, 1] < k.cy
    # an explicit span, and the file round trip
    rec = load_dnerf(dnerf, span_us=(10, 1010), background=(0, 0, 0))
    assert list(rec.anchors.t_us) == [10, 510, 1010] and list(rec.anchors.images[1, 0, 0]) == [0, 0, 0]
    back = read_recording(write_recording(tmp_path / "d.h5", rec))
    assert back.events == rec.events and back.metadata["layout"] == "d-nerf"


def test_dnerf_errors(dnerf):
    (dnerf / "events" / "events.npz").unlink()
    with pytest.raises(ReplayFormatError, match=r"events\.npz is missing"):
        load_dnerf(dnerf)
    data = json.loads((dnerf / "transforms_train.json").read_text())
    data["frames"][1]["time"] = 1.5
    (dnerf / "transforms_train.json").write_text(json.dumps(data))
    _events_npz(dnerf / "events" / "events.npz", [0, 5000], [0, 1], [0, 1], [1, 1])
    with pytest.raises(ReplayFormatError, match=r"'time' must lie in \[0, 1\]"):
        load_dnerf(dnerf)
    _events_npz(dnerf / "events" / "events.npz", [0, 0], [0, 1], [0, 1], [1, 1])
    with pytest.raises(ReplayFormatError, match="pass span_us"):
        load_dnerf(dnerf)
    data["frames"][1]["time"] = 0.5
    data["frames"][1]["transform_matrix"][0][0] = float("nan")  # json writes NaN, Python reads it back
    (dnerf / "transforms_train.json").write_text(json.dumps(data))
    with pytest.raises(ReplayFormatError, match=r"frames\[1\]\.transform_matrix has a non-finite"):
        load_dnerf(dnerf, span_us=(0, 100))
    (dnerf / "transforms_train.json").write_text("{not json")
    with pytest.raises(ReplayFormatError, match="not readable JSON"):
        load_dnerf(dnerf)


@pytest.fixture
def ed3dgs(tmp_path):
    """11 frames at 10 fps, one events file per frame interval."""
    frames = []
    for i in range(11):
        _png(tmp_path / "rgb" / f"{i:04d}.png", 10 * i)
        path = f"./rgb/{i:04d}" + (".png" if i % 2 else "")  # with and without the extension
        frames.append({"file_path": path, "time": 0.1 * i, "transform_matrix": _blender_c2w(3.0)})
        if i < 10:
            t = int(0.1 * i * 1e9) + np.array([1000, 50_000_000], np.int64)
            _events_npz(tmp_path / "events" / f"{i:04d}.npz", t, [i % W, 0], [0, i % H], [1, -1])
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": ANGLE, "frames": frames}))
    return tmp_path


def test_ed3dgs_layout(ed3dgs):
    rec = load_ed3dgs(ed3dgs, anchor_fps=5.0)
    assert list(rec.anchors.t_us) == [0, 200_000, 400_000, 600_000, 800_000, 1_000_000]
    assert list(rec.held_out.t_us) == [100_000, 300_000, 500_000, 700_000, 900_000]
    assert rec.held_out.images[0, 0, 0, 0] == 10 and rec.anchors.images[1, 0, 0, 0] == 20
    assert len(rec.events) == 20 and np.all(np.diff(rec.events.t) >= 0)
    assert rec.events.t[0] == 1 and rec.events.t[-1] == 950_000
    assert rec.metadata["anchor_stride"] == 2 and rec.metadata["event_files"] == 10
    assert len(rec.trajectory_t_us) == 11
    np.testing.assert_allclose(rec.anchors.poses[0][:3, 2], [0, 0, -1], atol=1e-12)
    # every anchor at 10 fps, or fewer held-out frames
    assert len(load_ed3dgs(ed3dgs, anchor_fps=10.0).anchors) == 11
    sparse = load_ed3dgs(ed3dgs, anchor_fps=2.5, held_out_per_interval=1)
    assert list(sparse.anchors.t_us) == [0, 400_000, 800_000]
    assert list(sparse.held_out.t_us) == [100_000, 500_000, 900_000]
    assert load_ed3dgs(ed3dgs, held_out_per_interval=0).held_out is None


def test_ed3dgs_errors(ed3dgs):
    for f in (ed3dgs / "events").glob("*.npz"):
        f.unlink()
    with pytest.raises(ReplayFormatError, match=r"no \.npz event files"):
        load_ed3dgs(ed3dgs)
    _events_npz(ed3dgs / "events" / "0000.npz", [0], [0], [0], [1])
    np.savez(ed3dgs / "events" / "0001.npz", x=[0], y=[0], p=[1])
    with pytest.raises(ReplayFormatError, match="lacks event columns"):
        load_ed3dgs(ed3dgs)
    (ed3dgs / "events" / "0001.npz").unlink()
    (ed3dgs / "rgb" / "0004.png").unlink()
    with pytest.raises(ReplayFormatError, match=r"0004\.png is missing"):
        load_ed3dgs(ed3dgs)
