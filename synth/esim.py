"""ESIM-style event simulator: per-pixel log-luminance threshold crossings between frame samples.

Each pixel keeps a reference level. Between two samples its log luminance L = log(I + eps) is taken
to move linearly; every time it crosses the reference +- C an event fires at the linearly
interpolated instant and the reference moves by C, so a change spanning k thresholds fires k events
(the event generation model: C * sum(p) tracks L(t_b) - L(t_a)). An event attributed to the step
(t0, t1] gets a timestamp in (t0, t1] (rounded up to the microsecond), so a window that ends on a
sample sees exactly the crossings up to that sample.

Frames come either as a sequence (``simulate_frames``) or from a render callback
(``simulate_render``), which bisects a step wherever the image changes by more than a fraction of
C, the adaptive sampling of ESIM.

Speed: three numba passes over pixel rows (one thread, or parallel over rows): log luminance, a count
pass, then an emit pass that writes each row's events at its prefix-sum offset; a stable counting sort
by time merges the rows.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numba as nb
import numpy as np

from edmcgs.errors import InvalidInputError
from edmcgs.luminance import LOG_EPS, LUMA
from edmcgs.sensor.events import Events

_R, _G, _B = LUMA  # numba reads module-level numbers as constants
_NEVER = np.iinfo(np.int64).min // 4  # "no event yet": far enough back for any refractory period


@dataclass(frozen=True)
class SimulatorConfig:
    """Settings of the event simulator (all stored in a recording's metadata)."""

    contrast_threshold: float = 0.2
    """C: the log-luminance change that fires one event (before mismatch), for both polarities."""
    threshold_sigma: float = 0.0
    """Standard deviation, in log units, of the per-pixel threshold mismatch: each pixel draws its own
    C+ and C- once from N(C, sigma), floored at ``min_threshold``."""
    min_threshold: float = 0.01
    """Floor of a pixel's drawn threshold, so that a wide mismatch never gives a zero or negative C."""
    refractory_us: int = 0
    """After an event a pixel is blind for this long: crossings inside it fire nothing, but the
    reference still follows them (the change is lost, as in a pixel held in reset)."""
    noise_rate_hz: float = 0.0
    """Background activity per pixel, events per second: Poisson in time, uniform over pixels, random
    polarity, independent of the signal (it does not move the reference)."""
    hot_pixel_fraction: float = 0.0
    """Fraction of the pixels that are hot: ``round(fraction * H * W)`` distinct pixels, drawn once at
    the first reset, each firing at ``hot_pixel_rate_hz`` on top of everything else."""
    hot_pixel_rate_hz: float = 0.0
    """Events per second of each hot pixel: Poisson in time, random polarity, independent of the signal
    and of the refractory period (like the background activity, a leak that never moves the reference)."""
    eps: float = LOG_EPS
    """L = log(I + eps) with I the luminance in [0, 1]; keeps black pixels finite."""
    seed: int = 0
    """Seed of the threshold mismatch and of the noise: a seed gives the same events every run."""

    def __post_init__(self) -> None:
        checks = {
            "contrast_threshold": math.isfinite(self.contrast_threshold) and self.contrast_threshold > 0,
            "threshold_sigma": math.isfinite(self.threshold_sigma) and self.threshold_sigma >= 0,
            "min_threshold": math.isfinite(self.min_threshold) and self.min_threshold > 0,
            "refractory_us": int(self.refractory_us) == self.refractory_us and self.refractory_us >= 0,
            "noise_rate_hz": math.isfinite(self.noise_rate_hz) and self.noise_rate_hz >= 0,
            "hot_pixel_fraction": (math.isfinite(self.hot_pixel_fraction)
                                   and 0 <= self.hot_pixel_fraction <= 1),
            "hot_pixel_rate_hz": math.isfinite(self.hot_pixel_rate_hz) and self.hot_pixel_rate_hz >= 0,
            "eps": math.isfinite(self.eps) and self.eps > 0,
            "seed": int(self.seed) == self.seed and self.seed >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise InvalidInputError(f"SimulatorConfig.{name}={getattr(self, name)!r} is out of range")

    def to_metadata(self) -> dict:
        """The settings as a JSON-able dict."""
        return asdict(self)


# ---------------------------------------------------------------------------------------------------
# kernels


@nb.njit(cache=True, inline="always")
def _log_row(img, y, scale, eps, out):  # pragma: no cover - compiled
    """Row y of img [H, W, C] (C = 1 or 3, any real dtype) -> out[y] float64; returns the non-finite count."""
    bad = 0
    for x in range(img.shape[1]):
        if img.shape[2] == 3:
            v = (_R * img[y, x, 0] + _G * img[y, x, 1] + _B * img[y, x, 2]) * scale
        else:
            v = img[y, x, 0] * scale
        if not np.isfinite(v):
            bad += 1
            v = 0.0
        elif v < 0.0:
            v = 0.0
        out[y, x] = np.log(v + eps)
    return bad


@nb.njit(cache=True, inline="always")
def _walk(l0, l1, ref, cp, cn, last, t0, dt, refractory, out_t, out_p, k, emit):  # pragma: no cover
    """Crossings of one pixel while L goes linearly l0 -> l1 over (t0, t0 + dt].

    Invariant on entry and exit: ref - cn < l0 < ref + cp. Returns (ref, last, k): the new reference,
    the last event time and the number of events (written at out_*[k...] when ``emit``).
    """
    if l1 >= ref + cp:
        level = ref + cp
        while level <= l1:
            frac = (level - l0) / (l1 - l0)
            te = t0 + min(dt, max(1, math.ceil(frac * dt)))
            if te - last >= refractory:
                if emit:
                    out_t[k] = te
                    out_p[k] = 1
                k += 1
                last = te
            ref = level
            level = ref + cp
    elif l1 <= ref - cn:
        level = ref - cn
        while level >= l1:
            frac = (l0 - level) / (l0 - l1)
            te = t0 + min(dt, max(1, math.ceil(frac * dt)))
            if te - last >= refractory:
                if emit:
                    out_t[k] = te
                    out_p[k] = -1
                k += 1
                last = te
            ref = level
            level = ref - cn
    return ref, last, k


@nb.njit(cache=True, inline="always")
def _count_row(y, l0, l1, ref, cp, cn, last, t0, dt, refractory):  # pragma: no cover - compiled
    """Events row y would fire for the step l0 -> l1 (the state is not touched)."""
    dummy_t = np.empty(0, np.int64)
    dummy_p = np.empty(0, np.int8)
    n = 0
    for x in range(l0.shape[1]):
        _, _, n = _walk(l0[y, x], l1[y, x], ref[y, x], cp[y, x], cn[y, x], last[y, x],
                        t0, dt, refractory, dummy_t, dummy_p, n, False)
    return n


@nb.njit(cache=True, inline="always")
def _emit_row(y, l0, l1, ref, cp, cn, last, t0, dt, refractory, k,
              out_t, out_x, out_y, out_p):  # pragma: no cover - compiled
    """Write row y's events from index k on, and advance its state (ref, last, l0 <- l1)."""
    for x in range(l0.shape[1]):
        k0 = k
        ref[y, x], last[y, x], k = _walk(l0[y, x], l1[y, x], ref[y, x], cp[y, x], cn[y, x],
                                         last[y, x], t0, dt, refractory, out_t, out_p, k, True)
        for i in range(k0, k):
            out_x[i] = x
            out_y[i] = y
        l0[y, x] = l1[y, x]


# Each pass exists twice: one thread, or rows spread over numba's threads. Rows are independent
# (counts first, then each row writes at its prefix-sum offset), so both give identical events.
# A parallel region costs a scheduler timeslice whenever a core is taken by another process, so on a
# shared 2-core machine the serial passes are the faster ones (see bench.simulate).

@nb.njit(cache=True)
def _log_serial(img, scale, eps, out):  # pragma: no cover - compiled
    bad = 0
    for y in range(img.shape[0]):
        bad += _log_row(img, y, scale, eps, out)
    return bad


@nb.njit(parallel=True, cache=True)
def _log_parallel(img, scale, eps, out):  # pragma: no cover - compiled
    bad = 0
    for y in nb.prange(img.shape[0]):
        bad += _log_row(img, y, scale, eps, out)
    return bad


@nb.njit(cache=True)
def _count_serial(l0, l1, ref, cp, cn, last, t0, dt, refractory):  # pragma: no cover - compiled
    counts = np.zeros(l0.shape[0], np.int64)
    for y in range(l0.shape[0]):
        counts[y] = _count_row(y, l0, l1, ref, cp, cn, last, t0, dt, refractory)
    return counts


@nb.njit(parallel=True, cache=True)
def _count_parallel(l0, l1, ref, cp, cn, last, t0, dt, refractory):  # pragma: no cover - compiled
    counts = np.zeros(l0.shape[0], np.int64)
    for y in nb.prange(l0.shape[0]):
        counts[y] = _count_row(y, l0, l1, ref, cp, cn, last, t0, dt, refractory)
    return counts


@nb.njit(cache=True)
def _emit_serial(l0, l1, ref, cp, cn, last, t0, dt, refractory, offsets,
                 out_t, out_x, out_y, out_p):  # pragma: no cover - compiled
    for y in range(l0.shape[0]):
        _emit_row(y, l0, l1, ref, cp, cn, last, t0, dt, refractory, offsets[y], out_t, out_x, out_y, out_p)


@nb.njit(parallel=True, cache=True)
def _emit_parallel(l0, l1, ref, cp, cn, last, t0, dt, refractory, offsets,
                   out_t, out_x, out_y, out_p):  # pragma: no cover - compiled
    for y in nb.prange(l0.shape[0]):
        _emit_row(y, l0, l1, ref, cp, cn, last, t0, dt, refractory, offsets[y], out_t, out_x, out_y, out_p)


_PASSES = {False: (_log_serial, _count_serial, _emit_serial),
           True: (_log_parallel, _count_parallel, _emit_parallel)}


@nb.njit(cache=True)
def _time_order(t, t0, dt):  # pragma: no cover - compiled
    """Stable order of t (all in (t0, t0 + dt]) by a counting sort on t - t0: O(n + dt)."""
    counts = np.zeros(dt + 2, np.int64)
    for i in range(len(t)):
        counts[t[i] - t0 + 1] += 1
    for j in range(1, dt + 2):
        counts[j] += counts[j - 1]
    order = np.empty(len(t), np.int64)
    for i in range(len(t)):
        j = t[i] - t0
        order[counts[j]] = i
        counts[j] += 1
    return order


@nb.njit(cache=True)
def _max_abs_diff(a, b):  # pragma: no cover - compiled
    m = 0.0
    for y in range(a.shape[0]):
        for x in range(a.shape[1]):
            d = abs(a[y, x] - b[y, x])
            if d > m:
                m = d
    return m


# ---------------------------------------------------------------------------------------------------
# public API


def _as_hwc(image: np.ndarray, name: str) -> tuple[np.ndarray, float]:
    """Validate an image and return it as [H, W, C] with the scale that maps it to [0, 1]."""
    if not isinstance(image, np.ndarray):
        image = np.asarray(image)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 3) or image.shape[0] == 0 or image.shape[1] == 0:
        raise InvalidInputError(f"{name} must be [H, W], [H, W, 1] or [H, W, 3], got shape {image.shape}")
    if image.dtype == np.uint8:
        return image, 1.0 / 255.0
    if image.dtype == np.uint16:
        return image, 1.0 / 65535.0
    if image.dtype.kind != "f":
        raise InvalidInputError(f"{name} must be uint8, uint16 or float in [0, 1], got {image.dtype}")
    return image, 1.0


def luminance(image: np.ndarray) -> np.ndarray:
    """Luminance in [0, 1] (Rec.601 weights for RGB; grey as is).

    image: [H, W], [H, W, 1] or [H, W, 3], uint8/uint16 (full scale = 1) or float in [0, 1].
    Returns float64 [H, W].
    """
    hwc, scale = _as_hwc(image, "image")
    hwc = hwc.astype(np.float64) * scale
    if hwc.shape[2] == 3:
        return hwc @ np.asarray(LUMA)
    return hwc[:, :, 0]


def log_luminance(image: np.ndarray, eps: float = 1e-3, *, parallel: bool = False) -> np.ndarray:
    """L = log(max(luminance, 0) + eps): float64 [H, W]. Raises InvalidInputError on NaN/Inf input.

    parallel: spread the rows over numba's threads (see ``EventSimulator``).
    """
    hwc, scale = _as_hwc(image, "image")
    if not (math.isfinite(eps) and eps > 0):
        raise InvalidInputError(f"eps must be a positive finite number, got {eps!r}")
    out = np.empty(hwc.shape[:2], np.float64)
    if _PASSES[bool(parallel)][0](np.ascontiguousarray(hwc), scale, float(eps), out):
        raise InvalidInputError("image holds NaN or Inf values")
    return out


class EventSimulator:
    """Stateful simulator: ``reset`` with the first frame, then ``step`` with each later one.

    State per pixel: the reference level, the last log luminance, its thresholds C+ and C- and the
    time of its last event (for the refractory period).

    parallel: run the passes over pixel rows on numba's threads. The events are identical either way;
    serial (the default) is faster unless the cores are otherwise idle, and leaves them to the renderer.
    """

    def __init__(self, config: SimulatorConfig | None = None, *, parallel: bool = False) -> None:
        self.config = config or SimulatorConfig()
        self._log_pass, self._count_pass, self._emit_pass = _PASSES[bool(parallel)]
        self.parallel = bool(parallel)
        # a third stream for the hot pixels: spawn(3)[:2] == spawn(2), so the other draws do not change
        seeds = np.random.SeedSequence(self.config.seed).spawn(3)
        self._mismatch_rng = np.random.default_rng(seeds[0])
        self._noise_rng = np.random.default_rng(seeds[1])
        self._hot_rng = np.random.default_rng(seeds[2])
        self._hot = np.zeros(0, np.int64)
        self._t_us: int | None = None
        self._l: np.ndarray | None = None

    @property
    def t_us(self) -> int | None:
        """Time of the last sample (None before ``reset``)."""
        return self._t_us

    @property
    def shape(self) -> tuple[int, int] | None:
        """(H, W) of the frames, once reset."""
        return None if self._l is None else self._l.shape

    @property
    def last_log_luminance(self) -> np.ndarray:
        """L of the last sample, float64 [H, W] (read-only view)."""
        if self._l is None:
            raise InvalidInputError("the simulator has no frame yet: call reset(t_us, image) first")
        view = self._l.view()
        view.flags.writeable = False
        return view

    @property
    def thresholds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel (C+, C-), float64 [H, W] each."""
        if self._l is None:
            raise InvalidInputError("the simulator has no frame yet: call reset(t_us, image) first")
        return self._cp, self._cn

    @property
    def hot_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(y, x) of the hot pixels, int64 [K] each, sorted by y * W + x."""
        if self._l is None:
            raise InvalidInputError("the simulator has no frame yet: call reset(t_us, image) first")
        w = self._l.shape[1]
        return self._hot // w, self._hot % w

    def reset(self, t_us: int, image: np.ndarray) -> None:
        """Start at ``t_us`` with every reference set to this frame's L (the first frame fires nothing).

        The thresholds are drawn here on the first reset only (a pixel keeps its mismatch).
        """
        self.reset_log(t_us, log_luminance(image, self.config.eps, parallel=self.parallel))

    def reset_log(self, t_us: int, log_lum: np.ndarray) -> None:
        """``reset`` from an L map already computed (float64 [H, W])."""
        t_us = _check_time(t_us)
        log_lum = _check_log(log_lum, None)
        h, w = log_lum.shape
        if self._l is None or self._l.shape != (h, w):
            c = self.config.contrast_threshold
            if self.config.threshold_sigma > 0:
                draw = self._mismatch_rng.normal(c, self.config.threshold_sigma, size=(2, h, w))
                draw = np.maximum(draw, self.config.min_threshold)
            else:
                draw = np.full((2, h, w), c)
            self._cp, self._cn = np.ascontiguousarray(draw[0]), np.ascontiguousarray(draw[1])
            n_hot = round(self.config.hot_pixel_fraction * h * w)
            self._hot = np.sort(self._hot_rng.choice(h * w, size=n_hot, replace=False)) if n_hot else \
                np.zeros(0, np.int64)
        self._l = log_lum.copy()
        self._ref = log_lum.copy()
        self._last = np.full((h, w), _NEVER, np.int64)
        self._t_us = t_us

    def step(self, t_us: int, image: np.ndarray) -> Events:
        """Advance to ``t_us`` (> the last sample) with this frame; returns the events in (t_last, t_us]."""
        return self.step_log(t_us, log_luminance(image, self.config.eps, parallel=self.parallel))

    def step_log(self, t_us: int, log_lum: np.ndarray) -> Events:
        """``step`` from an L map already computed (float64 [H, W])."""
        if self._t_us is None:
            raise InvalidInputError("the simulator has no frame yet: call reset(t_us, image) first")
        t_us = _check_time(t_us)
        if t_us <= self._t_us:
            raise InvalidInputError(f"t_us={t_us} must be after the last sample at {self._t_us}")
        l1 = _check_log(log_lum, self._l.shape)
        t0, dt = self._t_us, t_us - self._t_us
        args = (self._l, l1, self._ref, self._cp, self._cn, self._last, t0, dt, self.config.refractory_us)
        counts = self._count_pass(*args)
        offsets = np.zeros(len(counts), np.int64)
        np.cumsum(counts[:-1], out=offsets[1:])
        n = int(counts.sum())
        t = np.empty(n, np.int64)
        x = np.empty(n, np.uint16)
        y = np.empty(n, np.uint16)
        p = np.empty(n, np.int8)
        self._emit_pass(*args, offsets, t, x, y, p)
        self._t_us = t_us
        if self.config.noise_rate_hz > 0:
            t, x, y, p = self._add_noise(t0, dt, t, x, y, p)
        if len(self._hot) and self.config.hot_pixel_rate_hz > 0:
            t, x, y, p = self._add_hot(t0, dt, t, x, y, p)
        # rows come out one after the other: merge them by time (stable, so ties keep (y, x) order)
        order = _time_order(t, t0, dt) if dt <= 8 * n + 4096 else np.argsort(t, kind="stable")
        return Events(t=t[order], x=x[order], y=y[order], p=p[order])

    def _add_hot(self, t0, dt, t, x, y, p):
        rng, w = self._hot_rng, self._l.shape[1]
        counts = rng.poisson(self.config.hot_pixel_rate_hz * dt * 1e-6, size=len(self._hot))
        idx = np.repeat(self._hot, counts)
        n = len(idx)
        th = t0 + rng.integers(1, dt + 1, size=n, dtype=np.int64)
        ph = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
        return (np.concatenate([t, th]), np.concatenate([x, (idx % w).astype(np.uint16)]),
                np.concatenate([y, (idx // w).astype(np.uint16)]), np.concatenate([p, ph]))

    def _add_noise(self, t0, dt, t, x, y, p):
        h, w = self._l.shape
        rng = self._noise_rng
        n = int(rng.poisson(self.config.noise_rate_hz * h * w * dt * 1e-6))
        tn = t0 + rng.integers(1, dt + 1, size=n, dtype=np.int64)
        xn = rng.integers(0, w, size=n).astype(np.uint16)
        yn = rng.integers(0, h, size=n).astype(np.uint16)
        pn = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
        return (np.concatenate([t, tn]), np.concatenate([x, xn]), np.concatenate([y, yn]),
                np.concatenate([p, pn]))


def _check_time(t_us) -> int:
    if isinstance(t_us, bool) or not isinstance(t_us, int | np.integer):
        raise InvalidInputError(f"t_us must be an integer number of microseconds, got {t_us!r}")
    return int(t_us)


def _check_log(log_lum: np.ndarray, shape: tuple[int, int] | None) -> np.ndarray:
    log_lum = np.ascontiguousarray(log_lum, dtype=np.float64)
    if log_lum.ndim != 2 or (shape is not None and log_lum.shape != shape):
        want = "[H, W]" if shape is None else f"{shape}"
        raise InvalidInputError(f"log_lum must be {want}, got shape {log_lum.shape}")
    if not np.isfinite(log_lum).all():
        raise InvalidInputError("log_lum holds NaN or Inf values")
    return log_lum


def simulate_frames(t_us: np.ndarray, frames, config: SimulatorConfig | None = None) -> Events:
    """Events from a frame sequence.

    t_us: int64 [F], strictly increasing. frames: [F, H, W(, C)] array or a sequence of F images
    (uint8 or float in [0, 1]). The first frame sets the references.
    """
    t_us = np.asarray(t_us)
    if t_us.ndim != 1 or t_us.dtype.kind not in "iu" or len(t_us) == 0:
        raise InvalidInputError(f"t_us must be a non-empty 1-D integer array, got {t_us.dtype} {t_us.shape}")
    if len(frames) != len(t_us):
        raise InvalidInputError(f"frames has {len(frames)} images but t_us has {len(t_us)} times")
    if np.any(np.diff(t_us) <= 0):
        raise InvalidInputError("t_us must be strictly increasing")
    sim = EventSimulator(config)
    sim.reset(int(t_us[0]), frames[0])
    return Events.concat([sim.step(int(t), f) for t, f in zip(t_us[1:], frames[1:], strict=True)])


@dataclass(frozen=True)
class AdaptiveSampling:
    """How ``simulate_render`` chooses its sample times."""

    dt_max_us: int = 2000
    """Longest step between two renders."""
    dt_min_us: int = 100
    """Shortest step: bisection stops here even if the image still changes faster."""
    max_delta: float = 1.0
    """A step is bisected while some pixel's |L(t1) - L(t0)| exceeds max_delta * C."""

    def __post_init__(self) -> None:
        if not (1 <= self.dt_min_us <= self.dt_max_us):
            raise InvalidInputError(f"need 1 <= dt_min_us <= dt_max_us, got dt_min_us={self.dt_min_us}, "
                                    f"dt_max_us={self.dt_max_us}")
        if not (math.isfinite(self.max_delta) and self.max_delta > 0):
            raise InvalidInputError(f"max_delta must be positive, got {self.max_delta!r}")


def simulate_render(render: Callable[[int], np.ndarray], t_start_us: int, t_end_us: int,
                    config: SimulatorConfig | None = None, sampling: AdaptiveSampling | None = None,
                    progress: Callable[[int], object] | None = None) -> tuple[Events, np.ndarray]:
    """Events over [t_start_us, t_end_us] from a render callback, with adaptive time steps.

    render(t_us) -> image ([H, W(, C)], uint8 or float in [0, 1]). A step is halved while the largest
    per-pixel log-luminance change over it exceeds ``sampling.max_delta * C`` (and it is longer than
    ``dt_min_us``); renders made while bisecting are kept for the steps that follow, so none is wasted.
    progress(dt_us) is called after each accepted step (e.g. a tqdm's ``update``).

    Returns (events, sample_t_us): the events and the int64 times at which the image was sampled.
    """
    config = config or SimulatorConfig()
    sampling = sampling or AdaptiveSampling()
    t_start_us, t_end_us = _check_time(t_start_us), _check_time(t_end_us)
    if t_end_us <= t_start_us:
        raise InvalidInputError(f"t_end_us={t_end_us} must be after t_start_us={t_start_us}")
    limit = sampling.max_delta * config.contrast_threshold
    sim = EventSimulator(config)
    sim.reset(t_start_us, render(t_start_us))
    samples, chunks = [t_start_us], []
    pending: list[tuple[int, np.ndarray]] = []  # later samples already rendered, nearest last
    t = t_start_us
    while t < t_end_us:
        if pending:
            t1, l1 = pending.pop()
        else:
            t1 = min(t + sampling.dt_max_us, t_end_us)
            l1 = log_luminance(render(t1), config.eps)
        while t1 - t > sampling.dt_min_us and _max_abs_diff(sim.last_log_luminance, l1) > limit:
            pending.append((t1, l1))
            t1 = t + (t1 - t) // 2
            l1 = log_luminance(render(t1), config.eps)
        chunks.append(sim.step_log(t1, l1))
        samples.append(t1)
        if progress is not None:
            progress(t1 - t)
        t = t1
    return Events.concat(chunks), np.asarray(samples, np.int64)
