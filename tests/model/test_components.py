"""Invariants of the model's parts: skinning, control points, event branch, losses, config."""

import math

import pytest
import torch

from edmcgs.errors import InvalidInputError
from edmcgs.geometry import quat_multiply, quat_normalize, quat_to_rotmat
from edmcgs.model.config import EdmcgsConfig, preset
from edmcgs.model.eval.ssim import ssim
from edmcgs.model.motion.control_points import ControlPoints
from edmcgs.model.motion.deformation import DeformationField
from edmcgs.model.motion.encoding import encoded_size, positional_encoding
from edmcgs.model.motion.event_branch import (
    EventEncoder,
    EventTransition,
    sample_global,
    sample_local,
    saturate,
)
from edmcgs.model.motion.neighbors import farthest_point_sampling, knn
from edmcgs.model.motion.skinning import identity_rotations, lbs, skinning_weights
from edmcgs.model.train.losses import (
    event_loss,
    laplacian_smoothness,
    log_luminance,
    photometric_loss,
    tli_loss,
)


def _random_rotations(m, gen):
    return quat_normalize(torch.randn(m, 4, generator=gen))


def test_positional_encoding_shape():
    x = torch.rand(5, 3)
    assert positional_encoding(x, 4).shape == (5, encoded_size(3, 4)) == (5, 27)
    assert torch.equal(positional_encoding(x, 0), x)


def test_knn_matches_brute_force_and_excludes_self():
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(300, 3, generator=gen)
    d2, idx = knn(pts, pts, 4, exclude_self=True, chunk=64)
    full = torch.cdist(pts, pts).square().fill_diagonal_(float("inf"))
    ref_d, ref_i = torch.topk(full, 4, largest=False)
    assert torch.equal(idx, ref_i)
    assert torch.allclose(d2, ref_d, atol=1e-6)


def test_knn_exact_far_from_the_origin_with_more_neighbours_than_points():
    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(5, 4, generator=gen) + torch.tensor([0.0, 0.0, 0.0, 1e6])
    queries = torch.rand(70, 4, generator=gen) + torch.tensor([0.0, 0.0, 0.0, 1e6])
    d2, idx = knn(queries, pts, 8, exact=True, chunk=16)
    diff = (queries[:, None].double() - pts[None].double()).square().sum(-1)
    ref_d, ref_i = torch.topk(diff, 5, largest=False)
    assert idx.shape == (70, 5) and torch.equal(idx, ref_i)
    assert torch.allclose(d2.double(), ref_d, atol=1e-5)
    empty_d, empty_i = knn(queries[:0], pts, 2)
    assert empty_d.shape == (0, 2) and empty_i.dtype == torch.long


def test_farthest_point_sampling_spreads_out():
    gen = torch.Generator().manual_seed(0)
    cluster = torch.rand(500, 3, generator=gen) * 0.01
    outliers = torch.tensor([[5.0, 0, 0], [0, 5.0, 0], [0, 0, 5.0]])
    pts = torch.cat([cluster, outliers])
    idx = farthest_point_sampling(pts, 4)
    assert len(set(idx.tolist())) == 4
    assert {500, 501, 502} <= set(idx.tolist())


def test_skinning_weights_sum_to_one_even_far_away():
    gen = torch.Generator().manual_seed(1)
    control = torch.rand(16, 3, generator=gen)
    means = torch.cat([torch.rand(50, 3, generator=gen), torch.full((2, 3), 1e4)])
    idx = knn(means, control, 3)[1]
    w = skinning_weights(means, control, torch.full((16,), math.log(1e-3)), idx)
    assert torch.isfinite(w).all()
    assert torch.allclose(w.sum(1), torch.ones(52), atol=1e-6)
    assert (w >= 0).all()


def test_lbs_identity_returns_rest_state():
    gen = torch.Generator().manual_seed(2)
    control = torch.rand(16, 3, generator=gen)
    means = torch.rand(100, 3, generator=gen)
    quats = quat_normalize(torch.randn(100, 4, generator=gen))
    idx = knn(means, control, 3)[1]
    w = skinning_weights(means, control, torch.full((16,), math.log(0.2)), idx)
    m_t, q_t = lbs(means, quats, control, identity_rotations(16), torch.zeros(16, 3), idx, w)
    assert torch.allclose(m_t, means, atol=1e-6)
    assert torch.allclose(q_t, quats, atol=1e-6)


def test_lbs_common_rigid_transform_moves_everything_rigidly():
    gen = torch.Generator().manual_seed(3)
    control = torch.rand(16, 3, generator=gen)
    means = torch.rand(100, 3, generator=gen)
    idx = knn(means, control, 3)[1]
    w = skinning_weights(means, control, torch.full((16,), math.log(0.2)), idx)
    q = _random_rotations(1, gen)
    R = quat_to_rotmat(q)[0]
    shift = torch.tensor([0.3, -0.2, 0.5])
    # control point k rotated about the origin: R (x - p_k) + p_k + T_k with T_k = R p_k - p_k + shift
    trans = control @ R.T - control + shift
    m_t, _ = lbs(means, quat_normalize(torch.randn(100, 4, generator=gen)), control, q.expand(16, 4),
                   trans, idx, w)
    assert torch.allclose(m_t, means @ R.T + shift, atol=1e-5)


def test_control_points_sample_and_bind():
    gen = torch.Generator().manual_seed(4)
    means = torch.rand(400, 3, generator=gen)
    cp = ControlPoints.sample(means, 32, skin_k=3, graph_k=10, radius=0.1)
    assert cp.positions.shape == (32, 3) and cp.graph.shape == (32, 10) and cp.bind.shape == (400, 3)
    assert not (cp.graph == torch.arange(32)[:, None]).any()
    assert torch.allclose(cp.weights(means).sum(1), torch.ones(400), atol=1e-6)
    assert torch.allclose(cp.log_radius.exp(), torch.full((32,), 0.1))


def test_event_encoder_shapes_and_zero_in_zero_out():
    enc = EventEncoder(limit=6.9)
    out = enc(torch.randn(1, 1, 260, 346))
    assert out.shape == (1, 32, 65, 87)
    assert torch.equal(enc(torch.zeros(1, 1, 260, 346)), torch.zeros(1, 32, 65, 87))


def test_pooled_event_encoder_widens_its_field_and_keeps_zero_exact():
    torch.manual_seed(0)
    full, pooled = EventEncoder(limit=6.9), EventEncoder(limit=6.9, pool=4)
    pooled.load_state_dict(full.state_dict())  # pooling adds no parameter
    assert pooled(torch.randn(1, 1, 130, 173)).shape == (1, 32, 9, 11)  # ceil(ceil(130 / 4) / 4) ...
    assert torch.equal(pooled(torch.zeros(1, 1, 130, 173)), torch.zeros(1, 32, 9, 11))
    one = torch.zeros(1, 1, 128, 128)
    one[0, 0, 64, 64] = 0.2  # a single event
    # event-camera pixels whose output cell sees it: Phi's 23-px field is 4x wider once pooled
    reach = {enc.pool: int(enc(one)[0].abs().sum(0).gt(0).sum()) * (4 * enc.pool) ** 2
             for enc in (full, pooled)}
    assert reach[4] > 4 * reach[1]
    burst = torch.full((1, 1, 64, 64), 0.2 * 1e7)
    assert torch.equal(pooled(burst), pooled(burst.clamp(max=6.9)))  # bounded in the event count


def test_event_encoder_is_bounded_in_the_event_count():
    enc = EventEncoder(limit=6.9)
    burst = torch.zeros(1, 1, 40, 40)
    burst[0, 0, 10:30, 10:30] = 0.2 * 1e7  # C times a 10^7-event burst per pixel
    physical = burst.clamp(max=6.9)
    assert torch.equal(enc(burst), enc(physical))
    small = torch.zeros(1, 1, 40, 40)
    small[0, 0, 20, 20] = 0.4  # inside the physical range: untouched by the saturation
    assert torch.equal(saturate(small, 6.9), small)
    assert torch.isfinite(enc(torch.full((1, 1, 40, 40), 3e38))).all()


def test_time_is_encoded_in_float64():
    # One microsecond of a 24-hour span, far beyond float32's resolution at t ~ 0.7.
    span_us = 24 * 3600 * 10**6
    t0, t1 = 0.7, 0.7 + 1.0 / span_us
    field = DeformationField(width=8, depth=2, pos_freqs=2, time_freqs=12)
    x = torch.zeros(2, 3)
    with torch.no_grad():
        for p in field.parameters():
            p.fill_(0.01)
        enc = {t: positional_encoding(torch.tensor([[t]], dtype=torch.float64), 12) for t in (t0, t1)}
    # The encoding the field feeds its MLP equals the float64 reference rounded once to float32 ...
    ref = enc[t0].float()
    assert torch.equal(field.encode_time(t0, x), ref)
    # ... which a float32 encoding misses by far more than one float32 rounding.
    f32 = positional_encoding(torch.tensor([[t0]], dtype=torch.float32), 12)
    assert (f32 - ref).abs().max() > 1e-5
    assert not torch.equal(enc[t0].float(), enc[t1].float())


@pytest.mark.parametrize("depth", [1, 2, 4])
def test_deformation_field_equals_its_mlp_on_the_concatenated_input(depth):
    # The field splits the layers that read [gamma(x), gamma(t)] by columns and keeps the gamma(x) part
    # between inference calls: the same function as the plain MLP, with and without gradients.
    torch.manual_seed(depth)
    field = DeformationField(width=16, depth=depth, pos_freqs=3, time_freqs=4)
    with torch.no_grad():
        for p in field.parameters():
            p.normal_(0.0, 0.3)
    x = torch.rand(7, 3) * 2 - 1

    def plain(t):
        inp = torch.cat([positional_encoding(x, 3), field.encode_time(t, x).expand(7, -1)], -1)
        h = inp
        for i, layer in enumerate(field.layers):
            h = torch.relu(layer(torch.cat([h, inp], -1) if i == field.skip and i > 0 else h))
        return field.translation(h), field.rotation(h)

    for t in (0.0, 0.3, 0.9):
        want = plain(t)
        with torch.no_grad():
            for _ in range(2):  # the second call reuses the kept gamma(x) terms
                got = field(x, t)
                for g, w in zip(got, want, strict=True):
                    torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-6)
        for g, w in zip(field(x, t), want, strict=True):  # with gradients: rebuilt, differentiable
            torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-6)
    with torch.no_grad():  # an optimizer step (in place) or other points: rebuilt
        field.layers[0].bias.add_(0.5)
        torch.testing.assert_close(field(x, 0.3)[0], plain(0.3)[0], rtol=1e-5, atol=1e-6)
        x = x + 0.1
        torch.testing.assert_close(field(x, 0.3)[0], plain(0.3)[0], rtol=1e-5, atol=1e-6)


def test_event_transition_is_its_difference_of_mlps():
    torch.manual_seed(0)
    g = EventTransition(pos_freqs=2, hidden=16)
    with torch.no_grad():
        for p in g.parameters():
            p.normal_(0.0, 0.3)
    x = torch.rand(5, 3)
    codes = torch.randn(5, 32)
    codes[2] = 0.0

    def mlp(c):
        return g.out(torch.relu(g.hidden(torch.cat([positional_encoding(x, 2), c], -1))))

    want = mlp(codes) - mlp(torch.zeros_like(codes))
    with torch.no_grad():
        for _ in range(2):
            got = g(x, codes)
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
            assert torch.equal(got[2], torch.zeros(3))  # an empty code moves nothing, exactly
    torch.testing.assert_close(g(x, codes), want, rtol=1e-5, atol=1e-6)


def test_ssim_shrinks_its_window_for_tiny_images():
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(8, 9, 3, generator=gen)
    b = torch.rand(8, 9, 3, generator=gen)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-5)
    assert torch.isfinite(ssim(a, b)) and float(ssim(a, b)) < 0.9
    assert torch.isfinite(ssim(a[:1, :1], b[:1, :1]))
    loss = photometric_loss(a.requires_grad_(), b, 0.2)
    loss.backward()
    assert torch.isfinite(a.grad).all()


def test_event_transition_is_exactly_zero_for_zero_codes_after_training():
    gen = torch.Generator().manual_seed(5)
    g = EventTransition(pos_freqs=4, hidden=64)
    with torch.no_grad():  # a "trained" g: nothing zero any more
        for p in g.parameters():
            p.copy_(torch.randn(p.shape, generator=gen))
    x = torch.rand(20, 3, generator=gen)
    codes = torch.randn(20, 32, generator=gen)
    codes[::3] = 0.0
    out = g(x, codes)
    assert torch.equal(out[::3], torch.zeros_like(out[::3]))
    assert (out[1::3].abs().sum(1) > 0).all()


def test_event_transition_starts_at_zero():
    g = EventTransition(pos_freqs=4, hidden=64)
    assert torch.equal(g(torch.rand(8, 3), torch.randn(8, 32)), torch.zeros(8, 3))


def test_sample_local_reads_the_pixel_under_the_point():
    h, w = 16, 20
    feats = torch.zeros(32, h, w)
    feats[:, 5, 7] = torch.arange(32, dtype=torch.float32)
    # a full-resolution map: the pixel centre (7, 5) reads exactly that feature
    uv = torch.tensor([[7.0, 5.0], [0.0, 0.0], [7.0, 5.0]])
    out = sample_local(feats, uv, torch.tensor([True, True, False]), w, h)
    assert torch.allclose(out[0], torch.arange(32, dtype=torch.float32))
    assert torch.equal(out[1], torch.zeros(32)) and torch.equal(out[2], torch.zeros(32))
    # a quarter-resolution map covers the same image: pixel centre (4j + 1.5) sits on map cell j
    quarter = torch.zeros(32, 4, 5)
    quarter[:, 2, 3] = 1.0
    out = sample_local(quarter, torch.tensor([[4 * 3 + 1.5, 4 * 2 + 1.5]]), torch.tensor([True]), 20, 16)
    assert torch.allclose(out, torch.ones(1, 32))
    assert torch.allclose(sample_global(feats, 3), feats.mean((1, 2))[None].expand(3, 32))


def test_deformation_field_starts_at_identity():
    f = DeformationField(width=32, depth=4, pos_freqs=4, time_freqs=3)
    d_mu, d_q = f(torch.rand(10, 3), 0.3)
    assert d_mu.shape == (10, 3) and d_q.shape == (10, 4)
    assert torch.equal(d_mu, torch.zeros(10, 3)) and torch.equal(d_q, torch.zeros(10, 4))


def test_quaternion_product_matches_rotation_product():
    gen = torch.Generator().manual_seed(6)
    a, b = _random_rotations(5, gen), _random_rotations(5, gen)
    product = quat_to_rotmat(a) @ quat_to_rotmat(b)
    assert torch.allclose(quat_to_rotmat(quat_multiply(a, b)), product, atol=1e-5)
    assert torch.equal(quat_normalize(torch.zeros(1, 4)), torch.tensor([[1.0, 0, 0, 0]]))


def test_tli_zero_for_rigid_motion_positive_for_stretch():
    gen = torch.Generator().manual_seed(7)
    pts = torch.rand(64, 3, generator=gen)
    graph = knn(pts, pts, 10, exclude_self=True)[1]
    R = quat_to_rotmat(_random_rotations(1, gen))[0]
    moved = pts @ R.T + torch.tensor([1.0, 2.0, 3.0])
    assert tli_loss(pts, moved, graph) < 1e-10
    stretched = pts * torch.tensor([1.5, 1.0, 1.0])
    assert tli_loss(pts, stretched, graph) > 1e-4


def test_laplacian_smoothness_zero_for_constant_field():
    gen = torch.Generator().manual_seed(8)
    pts = torch.rand(64, 3, generator=gen)
    graph = knn(pts, pts, 10, exclude_self=True)[1]
    assert laplacian_smoothness(torch.ones(64, 3) * 0.3, graph) < 1e-12
    assert laplacian_smoothness(torch.randn(64, 3, generator=gen), graph) > 0.1


def test_the_graph_regularisers_of_a_window_with_no_points_are_zero_not_nan():
    none = torch.zeros(0, 3)
    graph = torch.zeros(0, 10, dtype=torch.long)
    for value in (tli_loss(none, none, graph), laplacian_smoothness(none, graph)):
        assert value.item() == 0.0


def test_photometric_and_ssim():
    gen = torch.Generator().manual_seed(9)
    img = torch.rand(32, 40, 3, generator=gen)
    assert torch.allclose(ssim(img, img), torch.tensor(1.0), atol=1e-5)
    assert photometric_loss(img, img, 0.2) < 1e-5
    assert photometric_loss(img, 1 - img, 0.2) > 0.3


def test_event_loss_zero_when_events_explain_the_change():
    gen = torch.Generator().manual_seed(10)
    a = torch.rand(8, 9, 3, generator=gen) * 0.5 + 0.2
    counts = torch.randint(-3, 4, (8, 9), generator=gen).float()
    # brighten every pixel by exactly `counts` thresholds in log space
    la = log_luminance(a, 1e-3)
    target = torch.exp(la + 0.2 * counts) - 1e-3
    b = a * (target / (a @ torch.tensor([0.299, 0.587, 0.114])))[..., None]
    assert event_loss(a, b, counts, 0.2, 1e-3) < 1e-4
    assert event_loss(a, b, counts, 0.2, 1e-3, levels=3) < 1e-4
    assert event_loss(a, a, counts, 0.2, 1e-3) > 0.1


def test_event_loss_pyramid_averages_pooled_levels():
    gen = torch.Generator().manual_seed(11)
    a, b = torch.rand(8, 8, 1, generator=gen), torch.rand(8, 8, 1, generator=gen)
    counts = torch.randint(-2, 3, (8, 8), generator=gen).float()
    residual = (log_luminance(b, 1e-3) - log_luminance(a, 1e-3) - 0.2 * counts)[None, None]
    pooled = torch.nn.functional.avg_pool2d(residual, 2)
    expected = (residual.abs().mean() + pooled.abs().mean()) / 2
    assert torch.allclose(event_loss(a, b, counts, 0.2, 1e-3, levels=2), expected)
    assert torch.allclose(event_loss(a, b, counts, 0.2, 1e-3), residual.abs().mean())


def test_config_overrides_presets_and_round_trip():
    cfg = preset("demo").with_overrides(["events=false", "iterations=10", "event_warmup=0.1,0.2",
                                         "lambda_tli=0"])
    assert cfg.events is False and cfg.iterations == 10 and cfg.event_warmup == (0.1, 0.2)
    assert not cfg.has_event_branch
    assert EdmcgsConfig.from_dict(cfg.to_dict()) == cfg
    assert preset("paper") == EdmcgsConfig()
    with pytest.raises(InvalidInputError, match="no_such"):
        cfg.with_overrides(["no_such=1"])
    with pytest.raises(InvalidInputError, match="iterations"):
        cfg.with_overrides(["iterations=-3"])
    with pytest.raises(InvalidInputError, match="markov"):
        cfg.with_overrides(["markov=maybe"])
    with pytest.raises(InvalidInputError, match="preset"):
        preset("huge")
