"""The 3DGS PLY export (written with ``plyfile``) read back by ``plyfile``: every column what 3DGS stores for
the same Gaussians, the SH coefficients of the model's own degree in 3DGS's layout."""

import numpy as np
import pytest
import torch
from plyfile import PlyData

from edmcgs.cli import main
from edmcgs.errors import InvalidInputError
from edmcgs.model.checkpoint import load_checkpoint, save_checkpoint
from edmcgs.model.motion.gaussians import GaussianState
from edmcgs.model.ply import ply_bytes, write_ply
from edmcgs.model.render.sh import SH_C0
from harness.server import randomize_event_branch
from tests.support import tiny_scene
from tests.support.models import TINY, build

HEAD = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
TAIL = ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _read(path):
    vertex = PlyData.read(str(path))["vertex"]
    return vertex, list(vertex.data.dtype.names)


def _inria_features(vertex) -> tuple[np.ndarray, np.ndarray]:
    """(features_dc [N, 1, 3], features_rest [N, K - 1, 3]) as Inria 3DGS's ``GaussianModel.load_ply``
    rebuilds them: the f_rest_* columns in the order of their index, reshaped to [N, 3, K - 1] (each
    channel's coefficients together) and transposed."""
    n = len(vertex.data)
    dc = np.stack([np.asarray(vertex[f"f_dc_{c}"]) for c in range(3)], 1)[:, None, :]
    names = sorted((p.name for p in vertex.properties if p.name.startswith("f_rest_")),
                   key=lambda name: int(name.split("_")[-1]))
    rest = np.stack([np.asarray(vertex[name]) for name in names], 1) if names else np.zeros((n, 0))
    return dc, rest.reshape(n, 3, -1).transpose(0, 2, 1)


def _with_sh(model, degree: int, seed: int = 0):
    """``model`` with SH colours of ``degree`` (random coefficients, as after training) in its weights and
    its config (a checkpoint's Gaussians take the config's degree)."""
    n = len(model.gaussians)
    gen = torch.Generator().manual_seed(seed)
    model.gaussians.features = torch.nn.Parameter(0.3 * torch.randn(n, (degree + 1) ** 2, 3, generator=gen))
    model.config = model.config.replace(sh_degree=degree)
    model.meta.config = model.config.to_dict()
    return model


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


@pytest.mark.parametrize("degree", [0, 3])
def test_a_checkpoint_exports_its_own_sh_degree_in_the_3dgs_layout(tmp_path, degree):
    """``edmcgs export-ply`` of a saved checkpoint: (d + 1)^2 - 1 f_rest columns per channel, which a
    3DGS loader turns back into the model's own coefficients (channel-major: R's, then G's, then B's)."""
    model, _ = build(TINY)
    if degree:
        _with_sh(model, degree)
    ckpt = tmp_path / "sh.ckpt"
    save_checkpoint(model, ckpt)
    out = tmp_path / "sh.ply"
    assert main(["export-ply", str(ckpt), "--t", "0.05", "-o", str(out), "-q"]) == 0
    vertex, names = _read(out)
    rest = [f"f_rest_{i}" for i in range(3 * ((degree + 1) ** 2 - 1))]
    assert names == HEAD + rest + TAIL and len(rest) == (45 if degree == 3 else 0)
    assert vertex.properties[0].val_dtype in ("f4", "float32")  # 3DGS's float columns
    state = model.deform(tiny_scene.T0 + 50_000)
    dc, features_rest = _inria_features(vertex)
    if degree == 0:  # plain colours: the DC term that gives them
        np.testing.assert_allclose(0.5 + SH_C0 * dc[:, 0], state.colors.numpy(), atol=1e-5)
        assert features_rest.shape == (len(state), 0, 3)
    else:
        coeffs = state.colors.numpy()  # [N, 16, 3]
        np.testing.assert_allclose(dc[:, 0], coeffs[:, 0], atol=1e-6)
        np.testing.assert_allclose(features_rest, coeffs[:, 1:], atol=1e-6)
        # spelt out for one Gaussian: f_rest_0..14 are R's degree 1..3 coefficients, 15..29 G's, 30..44 B's
        row = vertex.data[7]
        assert [row[f"f_rest_{i}"] for i in range(15)] == pytest.approx(coeffs[7, 1:, 0].tolist(), abs=1e-6)
        assert [row[f"f_rest_{15 + i}"] for i in range(15)] == pytest.approx(coeffs[7, 1:, 1].tolist(),
                                                                               abs=1e-6)
        assert row["f_rest_44"] == pytest.approx(coeffs[7, 15, 2], abs=1e-6)
    loaded = load_checkpoint(ckpt).deform(tiny_scene.T0 + 50_000)
    assert out.read_bytes() == ply_bytes(loaded)  # GET /ply's bytes are the file's


def test_a_failed_write_leaves_no_file(tmp_path, monkeypatch):
    model, _ = build(TINY)
    state = model.deform(tiny_scene.T0 + 50_000)

    def broken(self, stream):
        stream.write(b"ply\n")
        raise OSError("disk full")

    monkeypatch.setattr(PlyData, "write", broken)
    with pytest.raises(OSError, match="disk full"):
        write_ply(state, tmp_path / "scene.ply")
    assert list(tmp_path.iterdir()) == []
