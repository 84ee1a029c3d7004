"""The 3DGS PLY export read back by ``plyfile``: every column what 3DGS stores for the same Gaussians."""

import numpy as np
import pytest
import torch
from plyfile import PlyData

from edmcgs.cli import main
from edmcgs.errors import InvalidInputError
from edmcgs.model.checkpoint import save_checkpoint
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.ply import write_ply
from edmcgs.model.render.sh import SH_C0
from tests.support import tiny_scene
from tests.support.models import TINY, build, randomize_event_branch

HEAD = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _read(path):
    vertex = PlyData.read(str(path))["vertex"]
    return vertex, list(vertex.data.dtype.names)


@pytest.mark.parametrize("channels", [3, 1])
def test_a_state_round_trips_through_the_3dgs_layout(tmp_path, channels):
    model, _ = build(channels=channels)
    state = model.deform(tiny_scene.T0 + 50_000)
    vertex, names = _read(write_ply(state, tmp_path / "scene.ply"))
    assert names == HEAD + TAIL and len(vertex.data) == len(state)  # degree 0: no f_rest
    col = lambda k: np.asarray(vertex[k], np.float64)  # noqa: E731
    np.testing.assert_allclose(np.stack([col("x"), col("y"), col("z")], 1), state.means.numpy(), rtol=1e-6)
    colors = state.colors.numpy()
    for c in range(3):  # 3DGS's colour of the DC term; a grey channel on R, G and B
        np.testing.assert_allclose(0.5 + SH_C0 * col(f"f_dc_{c}"), colors[:, min(c, channels - 1)], atol=1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-col("opacity"))), state.opacities.numpy(), atol=1e-5)
    scales = np.exp(np.stack([col(f"scale_{i}") for i in range(3)], 1))
    np.testing.assert_allclose(scales, state.scales.numpy(), rtol=1e-5)
    quats = np.stack([col(f"rot_{i}") for i in range(4)], 1)
    np.testing.assert_allclose(np.abs((quats * state.quats.numpy()).sum(1)), 1, atol=1e-5)  # same rotation


def test_sh_coefficients_go_channel_major_as_in_3dgs(tmp_path):
    n, k = 5, 4  # degree 1
    coeffs = torch.arange(n * k * 3, dtype=torch.float32).reshape(n, k, 3) / 100
    state = GaussianState(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.ones(n, 3),
                          torch.full((n,), 0.5), coeffs)
    vertex, names = _read(write_ply(state, tmp_path / "sh.ply"))
    rest = [f"f_rest_{i}" for i in range(9)]
    assert names == HEAD + rest + TAIL
    row = vertex.data[2]
    assert [row[f"f_dc_{c}"] for c in range(3)] == pytest.approx(coeffs[2, 0].tolist())
    expected = coeffs[2, 1:].T.reshape(-1).tolist()  # R's three coefficients, then G's, then B's
    assert [row[r] for r in rest] == pytest.approx(expected)


def test_non_finite_or_empty_states_write_nothing(tmp_path):
    state = GaussianState(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.ones(1, 3),
                          torch.full((1,), 0.5), torch.full((1, 3), float("nan")))
    with pytest.raises(InvalidInputError, match="non-finite f_dc_0"):
        write_ply(state, tmp_path / "bad.ply")
    hidden = GaussianState(state.means, state.quats, state.scales, torch.zeros(1), state.colors)
    with pytest.raises(InvalidInputError, match="no Gaussians"):  # opacity 0: another anchor window's
        write_ply(hidden, tmp_path / "hidden.ply")
    empty = GaussianState(*(t[:0] for t in (state.means, state.quats, state.scales, state.opacities,
                                            state.colors)))
    with pytest.raises(InvalidInputError, match="no Gaussians"):
        write_ply(empty, tmp_path / "empty.ply")
    assert list(tmp_path.iterdir()) == []


def test_the_export_ply_command(tmp_path, capsys):
    model, _ = build(TINY)
    randomize_event_branch(model)
    ckpt = tmp_path / "tiny.ckpt"
    save_checkpoint(model, ckpt)
    out = tmp_path / "t.ply"
    assert main(["export-ply", str(ckpt), "--t", "0.05", "-o", str(out)]) == 0
    assert "the event branch sees no events" in capsys.readouterr().out
    assert len(PlyData.read(str(out))["vertex"].data) == len(model.gaussians)
    with pytest.raises(SystemExit):
        main(["export-ply", str(ckpt), "--t", "0.05", "-o", str(out)])
    assert "use --force" in capsys.readouterr().err
    assert main(["export-ply", str(ckpt), "--t", "9", "-o", str(out), "--force"]) == 1
    assert "outside the checkpoint's span" in capsys.readouterr().err
    assert main(["export-ply", str(ckpt), "--t", "0.05", "-o", str(out), "--force", "-q"]) == 0
    assert capsys.readouterr().out == "" and out.stat().st_size > 0


def test_gaussians_of_other_anchor_windows_are_left_out(tmp_path):
    n = 4
    state = GaussianState(torch.arange(n * 3, dtype=torch.float32).reshape(n, 3),
                          torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.ones(n, 3),
                          torch.tensor([0.5, 0.0, 0.9, 0.0]), torch.full((n, 3), 0.5))
    vertex, _ = _read(write_ply(state, tmp_path / "window.ply"))
    assert np.asarray(vertex["x"]).tolist() == [0.0, 6.0]  # the two of zero opacity are not written
