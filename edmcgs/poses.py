"""Camera poses from a recording's own frames: structure from motion over every APS / RGB frame (COLMAP,
through pycolmap, on the CPU), for ``edmcgs poses`` and ``--poses auto``.

Small grey event-camera frames defeat COLMAP's defaults (few features, tiny baselines between video
frames, parts of the scene that move), so the stages are set for video: SIFT at a low peak threshold on
the twice-upsampled image (COLMAP's first octave -1), sequential matching at quadratic jumps (every frame
against the frames 1, 2, 4, 8, ... after it), tight RANSAC and reprojection bounds (a moving object's
matches are outliers of the camera's motion, not a second motion the mapper averages in; a looser bound
is tried when too few frames register with the tight one), an initial pair that needs only a few degrees
of parallax, and a last bundle adjustment with a robust loss. The camera is the one given (a DV
calibration or ``--intrinsics``, held fixed), else one pinhole focal length with a radial term estimated
by the bundle adjustment and returned.

A long run of frames is mapped on keyframes (``_keyframes``: the frames a few percent of the image
apart), not on every frame: the mapper's cost grows much faster than the frames do when they are a pixel
apart (street3d's 251 frames at 25 Hz took 246 s, its 49 keyframes 4 s).
Every other frame is then localized against the keyframes' points through its verified matches (PnP),
its inlier observations joined to their tracks, before the last bundle adjustment refines them all.

Conventions of the result: OpenCV camera-to-world poses (x right, y down, z forward), the world the
first registered frame's camera, the scale such that the median depth of the reconstructed points
seen from the registered frames is 1 (the model's ``init_depth``, its scene depth when the cameras'
axes do not meet). The reconstructed points come with the poses, in the same frame, each in the mean
colour of the frames' pixels it was seen at (where the model's static set starts: ``static_set``).
A camera whose frames match with (almost) no image motion is static; one whose matched frames are
all related by homographies that are rotations (it turns about its centre: no parallax to map with,
e.g. a pan) gets rotations alone, from those homographies, chained through the earliest frame each
frame matched (its focal length, when not given, the one that makes them closest
to rotations); a recording where fewer than ``min_registered`` of the frames register in one model is
refused, naming the count. A recording's IMU refines the poses (``edmcgs.inertial``): the rotations it
settles on are held while the model's positions and points are bundle-adjusted again, before its
accelerometer fixes the positions.
pycolmap is imported when poses are estimated, never at import time.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from edmcgs.errors import InvalidInputError, PoseEstimationError
from edmcgs.geometry import Intrinsics, nearest_rotation

MIN_REGISTERED = 0.8
"""Fewest frames, as a fraction of all, that must register in one model."""
STATIC_PX = 1.0
"""A camera is static when no matched pair of frames shows a median image motion above this (pixels)."""
OVERLAP = 20
"""Each frame is matched against the frames 2^0 .. 2^(OVERLAP - 1) after it (COLMAP's quadratic overlap)."""
KEYFRAME_MOTION = 0.03
"""Largest median image motion between successive keyframes, a fraction of the frames' larger side."""
MIN_KEYFRAMES = 100
"""Fewest keyframes a run of frames keeps: a run under twice this maps every frame (a figure that fills
the frame, jumpingjack's orbit, needs every frame's tracks: mapped on 75 of its 101 frames, 5 of 11 runs
ended 9 to 15 % of the path off, against none of 6 mapping all)."""
KEYFRAME_GAP = 16
"""Most frames between successive keyframes."""
PEAK_THRESHOLD = 0.002
"""SIFT's peak threshold (COLMAP's default 0.0067 finds ~100 features on a 173x130 frame)."""
MAX_ERROR_PX = 1.0
"""RANSAC inlier bound of two-view geometry (pixels at the frames' resolution)."""
REPROJ_PX = (0.35, 1.5)
"""Largest reprojection error an observation may keep in the model (pixels), tried in turn: the tight
bound first (sharp frames: a moving part's tracks drift by more and are dropped: jumpingjack's ATE 14 ->
2 %), the loose one when too few frames register with it (noisy or blurred frames)."""
ROBUST_PX = 0.5
"""Scale of the Cauchy loss of the final bundle adjustment (pixels)."""
INIT_TRI_DEG = 4.0
"""Parallax the initial pair of frames needs (COLMAP's 16 degrees: video frames are a few apart)."""
MIN_INLIERS = 15
"""Fewest verified inlier matches that make two frames a pair."""
MIN_POSE_INLIERS = 30
"""Fewest 2D-3D inliers that localize a frame (the mapper's ``abs_pose_min_num_inliers``)."""
MAX_NON_ROTATION = 0.02
"""Largest median max |M^T M - I| of M = K^-1 H K over pairs for a camera that only turns."""
STAGES = ("features", "matching", "motion", "mapping")


@dataclass(frozen=True)
class PoseEstimate:
    """What structure from motion made of a run of frames."""

    frames: int
    """Frames given."""
    registered: int
    """Frames registered in the kept (largest) model."""
    t_us: np.ndarray
    """int64 [R]: the registered frames' times (static: the first frame's time alone)."""
    c2w: np.ndarray
    """float64 [R, 4, 4]: their OpenCV camera-to-world poses (static: the identity)."""
    intrinsics: Intrinsics | None
    """The camera: the one given, or the one estimated (None: a static camera and none given)."""
    estimated_intrinsics: bool
    """Whether ``intrinsics`` were estimated here (then ``distortion`` is their radial term)."""
    distortion: float
    """COLMAP's SIMPLE_RADIAL k of an estimated camera (0 when given: a pinhole is assumed)."""
    static: bool
    """No image motion between the frames: a static camera."""
    models: int
    """Separate models the mapper made (1 when every registered frame joined one)."""
    points: int
    """3D points of the kept model."""
    motion_px: float
    """Largest median image motion of a matched pair of frames (pixels; what decided ``static``)."""
    seconds: float
    """Wall time of the estimate."""
    rotation_only: bool = False
    """The camera turned about its centre (no parallax): rotations from the frames' homographies, no
    translation (``points`` 0)."""
    point_xyz: np.ndarray | None = None
    """float64 [points, 3]: the kept model's 3D points in the poses' frame (None: no points, a static or
    turning camera)."""
    point_colors: np.ndarray | None = None
    """uint8 [points, C] (C: the frames' channels): each point's mean colour over the pixels that saw it."""
    imu: str | None = None
    """What the IMU did: how the fused poses fit (``edmcgs.inertial``), or why it was left out; None
    when the recording had none, or the camera was static or only turned."""
    frames_c2w: np.ndarray | None = None
    """float64 [R, 4, 4]: the frames' own poses before the IMU refined them (in their own world and units);
    None when the IMU did not."""
    keyframes: int = 0
    """Frames the mapper ran on (the rest were localized against their points; 0: no mapping)."""

    def summary(self) -> str:
        """One line: what registered, the camera, the time."""
        if self.static:
            return (f"a static camera: the frames move by at most {self.motion_px:.2f} px "
                    f"({self.frames} frames, {self.seconds:.1f} s)")
        camera = "the camera given"
        if self.estimated_intrinsics and self.intrinsics is not None:
            k = self.intrinsics
            camera = f"estimated camera fx = fy = {k.fx:.1f}, cx = {k.cx:.1f}, cy = {k.cy:.1f} px"
            if not self.rotation_only:
                camera += f" (radial distortion k = {self.distortion:+.3f} left out of the pinhole model)"
        if self.rotation_only:
            return (f"a camera that turns about its centre (no parallax): {self.registered} of {self.frames} "
                    f"frames rotated by their homographies, {camera}, {self.seconds:.1f} s")
        models = "" if self.models == 1 else f", the largest of {self.models} models"
        imu = "" if self.imu is None else f"; {self.imu}"
        return (f"{self.registered} of {self.frames} frames registered ({self.keyframes} keyframes mapped"
                f"{models}), {self.points} points, "
                f"{camera}, {self.seconds:.1f} s{imu}")


def estimate_poses(t_us, images, intrinsics: Intrinsics | None = None, *, imu: np.ndarray | None = None,
                   min_registered: float = MIN_REGISTERED, progress: bool = True, threads: int = -1,
                   seed: int = 0) -> PoseEstimate:
    """Poses of the frames ``images`` (uint8 [F, H, W, C], C 1 or 3) taken at ``t_us`` (int64 [F],
    strictly increasing), by structure from motion, refined by ``imu`` (``IMU_DTYPE`` samples on the
    frames' clock) when given and usable (``with_imu``).

    ``intrinsics``: the camera (held fixed), or None to estimate it. Raises ``PoseEstimationError`` when
    fewer than ``min_registered`` of the frames register in one model, or no two frames match.
    """
    return _estimate(t_us, images, intrinsics, imu, min_registered=min_registered, progress=progress,
                     threads=threads, seed=seed)


def with_imu(estimate: PoseEstimate, imu: np.ndarray,
             adjust: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None) -> PoseEstimate:
    """``estimate``'s poses refined by the IMU (``edmcgs.inertial.fuse_imu``), the world moved to the
    first frame's refined camera (its points with it); unchanged, with the reason in ``imu``, when the
    IMU cannot refine them. A static or turning camera is left as it is. ``adjust``: given the fused
    rotations, the frames' positions and the points estimated again with them held (``estimate``'s world
    and units); None keeps the frames' own."""
    from edmcgs.inertial import ImuUnusable, fuse_imu

    if estimate.static or estimate.rotation_only:
        return estimate
    start = time.perf_counter()
    adjusted: dict[str, np.ndarray] = {}

    def positions(rotations: np.ndarray) -> np.ndarray:
        adjusted["positions"], adjusted["points"] = adjust(rotations)
        return adjusted["positions"]

    try:
        fit = fuse_imu(estimate.t_us, estimate.c2w, imu, adjust=None if adjust is None else positions)
    except ImuUnusable as exc:
        return replace(estimate, imu=f"IMU left out: {exc}")
    to_first = np.linalg.inv(fit.c2w[0])
    xyz = adjusted.get("points", estimate.point_xyz)
    if xyz is not None:
        xyz = xyz @ to_first[:3, :3].T + to_first[:3, 3]
    return replace(estimate, c2w=to_first @ fit.c2w, point_xyz=xyz, imu=fit.summary(),
                   frames_c2w=estimate.c2w, seconds=estimate.seconds + time.perf_counter() - start)


def _estimate(t_us, images, intrinsics: Intrinsics | None, imu: np.ndarray | None, *, min_registered: float,
              progress: bool, threads: int, seed: int) -> PoseEstimate:
    t_us, images = _checked(t_us, images, intrinsics)
    if not 0 < min_registered <= 1:
        raise InvalidInputError(f"min_registered must be in (0, 1], got {min_registered}")
    from tqdm import tqdm

    start = time.perf_counter()
    pycolmap = _pycolmap()
    n, height, width = images.shape[:3]
    with tempfile.TemporaryDirectory(prefix="edmcgs-poses-") as tmp, \
            tqdm(total=len(STAGES), desc="poses", unit="stage", disable=not progress) as bar:
        root = Path(tmp)
        folder, database, output = root / "frames", root / "frames.db", root / "sfm"
        folder.mkdir()
        output.mkdir()
        bar.set_postfix_str(STAGES[0])
        names = _write_frames(images, folder)
        _extract(pycolmap, database, folder, names, intrinsics, width, height, threads)
        bar.update()
        bar.set_postfix_str(STAGES[1])
        _match(pycolmap, database, threads, seed)
        bar.update()
        bar.set_postfix_str(STAGES[2])
        matched = _verified_pairs(pycolmap, database)
        pairs = matched.pairs
        motion_px = _image_motion(pairs)
        bar.update()
        if motion_px is None:
            raise PoseEstimationError(f"no two of the {n} frames match: structure from motion found nothing "
                                      "to build on (too dark, too blurred or too little texture?)")
        if motion_px <= STATIC_PX:
            bar.update()
            return PoseEstimate(
                frames=n, registered=n, t_us=t_us[:1], c2w=np.eye(4)[None],
                intrinsics=intrinsics,
                estimated_intrinsics=False, distortion=0.0, static=True, models=0, points=0,
                motion_px=motion_px, seconds=time.perf_counter() - start)
        turned = _rotations(pairs, n, intrinsics, width, height)
        if turned is not None and len(turned[0]) >= min_registered * n:  # no parallax to map with
            bar.update()
            index, c2w, camera = turned
            return PoseEstimate(
                frames=n, registered=len(index), t_us=t_us[index], c2w=c2w, intrinsics=camera,
                estimated_intrinsics=intrinsics is None, distortion=0.0, static=False, models=1, points=0,
                motion_px=motion_px, seconds=time.perf_counter() - start, rotation_only=True)
        bar.set_postfix_str(STAGES[3])
        keyframes = [names[i] for i in _keyframes(pairs, n, KEYFRAME_MOTION * max(width, height))]
        for attempt, bound in enumerate(REPROJ_PX):
            options = _options(pycolmap, bound, keyframes, fixed=intrinsics is not None, threads=threads,
                               seed=seed)
            models = _map(pycolmap, database, folder, output / str(attempt), options)
            best = models[0] if models else None
            if best is not None:
                _localize(pycolmap, best, matched, 2 * bound, seed)
                if best.num_reg_images() >= min_registered * n:
                    break
        if best is not None and best.num_reg_images() >= min_registered * n:
            _complete(pycolmap, database, best, options, fixed=intrinsics is not None)
        bar.update()
    registered = 0 if best is None else best.num_reg_images()
    if best is None:
        raise PoseEstimationError(f"0 of {n} frames registered: structure from motion found no initial pair "
                                  "of frames with enough parallax")
    if registered < min_registered * n:
        split = f" (the largest of {len(models)} separate models)" if len(models) > 1 else ""
        raise PoseEstimationError(f"only {registered} of {n} frames registered in one model{split}; poses "
                                  f"need {min_registered:.0%} (give --poses TRAJ.txt, or --intrinsics if "
                                  "the camera is known)")
    world = _World.of(best)
    index, c2w, xyz, colors = _poses(best, world, images)
    camera = best.cameras[next(iter(best.cameras))]
    estimated, k = _camera(camera, intrinsics, width, height)
    estimate = PoseEstimate(
        frames=n, registered=registered, t_us=t_us[index], c2w=c2w, intrinsics=estimated,
        estimated_intrinsics=intrinsics is None, distortion=k, static=False, models=len(models),
        points=len(xyz), motion_px=motion_px, seconds=time.perf_counter() - start, point_xyz=xyz,
        point_colors=colors, keyframes=len(keyframes))
    if imu is None:
        return estimate

    def held(rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        _hold_rotations(pycolmap, best, world, rotations, fixed=intrinsics is not None)
        _, adjusted, points, _ = _poses(best, world, images, colors=False)
        return adjusted[:, :3, 3], points

    return with_imu(estimate, imu, adjust=held)


def _checked(t_us, images, intrinsics) -> tuple[np.ndarray, np.ndarray]:
    t_us, images = np.asarray(t_us), np.asarray(images)
    if t_us.ndim != 1 or t_us.dtype.kind not in "iu":
        raise InvalidInputError(f"t_us must be 1-D integer microseconds, got {t_us.dtype} {t_us.shape}")
    if images.ndim == 3:
        images = images[..., None]
    if images.ndim != 4 or images.shape[-1] not in (1, 3) or images.dtype != np.uint8:
        raise InvalidInputError(f"images must be uint8 [F, H, W, C] with C 1 or 3, got {images.dtype} "
                                f"{images.shape}")
    if len(images) != len(t_us):
        raise InvalidInputError(f"{len(t_us)} times but {len(images)} frames")
    if len(t_us) < 3:
        raise PoseEstimationError(f"structure from motion needs at least 3 frames, the recording has "
                                  f"{len(t_us)}")
    if np.any(np.diff(t_us) <= 0):
        raise InvalidInputError("frame times must be strictly increasing")
    if intrinsics is not None and (intrinsics.width, intrinsics.height) != images.shape[2:0:-1]:
        raise InvalidInputError(f"the camera is {intrinsics.width}x{intrinsics.height}, the frames "
                                f"{images.shape[2]}x{images.shape[1]}")
    return t_us.astype(np.int64), images


def _pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # a dependency: only a broken install lacks it
        raise PoseEstimationError(f"estimating poses needs pycolmap (pip install pycolmap): {exc}") from exc
    pycolmap.logging.minloglevel = 2  # its INFO and WARNING lines would bury the progress bar
    pycolmap.logging.stderrthreshold = 2
    return pycolmap


def _write_frames(images: np.ndarray, folder: Path) -> list[str]:
    """The frames as grey PNGs (SIFT sees grey), named in time order."""
    from PIL import Image

    luma = images[..., 0] if images.shape[-1] == 1 else np.rint(
        images.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.uint8)
    names = []
    for i, grey in enumerate(luma):
        names.append(f"{i:06d}.png")
        Image.fromarray(grey).save(folder / names[-1])
    return names


def _extract(pycolmap, database: Path, folder: Path, names: list[str], intrinsics: Intrinsics | None,
             width: int, height: int, threads: int) -> None:
    reader = pycolmap.ImageReaderOptions()
    if intrinsics is None:
        reader.camera_model = "SIMPLE_RADIAL"
    else:  # COLMAP puts pixel centres at +0.5; ours at integers
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(repr(v) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx + 0.5,
                                                           intrinsics.cy + 0.5))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.peak_threshold = PEAK_THRESHOLD
    extraction.sift.first_octave = -1  # (COLMAP's default) detect on the twice-upsampled frame too
    extraction.max_image_size = max(width, height)
    pycolmap.extract_features(database, folder, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction)


def _match(pycolmap, database: Path, threads: int, seed: int) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = OVERLAP
    pairing.quadratic_overlap = True
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = MAX_ERROR_PX
    verification.ransac.random_seed = seed
    verification.detect_watermark = False  # a still scene shared by both frames is no watermark here
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                              verification_options=verification)


@dataclass(frozen=True)
class _Pair:
    """Two frames the matcher verified (``a`` before ``b``): their inlier matches (keypoint indices
    [M, 2], a's then b's), the matched keypoints (COLMAP's pixels, centres at +0.5) and the homography it
    fitted (``b ~ H a``)."""

    a: int
    b: int
    matches: np.ndarray
    points_a: np.ndarray
    points_b: np.ndarray
    H: np.ndarray

    @cached_property
    def motion_px(self) -> float:
        """The median displacement of the inlier matches (pixels)."""
        return float(np.median(np.linalg.norm(self.points_b - self.points_a, axis=1)))


@dataclass(frozen=True)
class _Matched:
    """What the matcher verified: the pairs, and per frame its keypoints and database image id."""

    pairs: list[_Pair]
    keypoints: dict[int, np.ndarray]
    image_ids: dict[int, int]


def _verified_pairs(pycolmap, database: Path) -> _Matched:
    """Every pair of frames with at least ``MIN_INLIERS`` verified inlier matches."""
    with pycolmap.Database.open(database) as db:
        index = {image.image_id: int(Path(image.name).stem) for image in db.read_all_images()}
        keypoints = {index[i]: np.asarray(db.read_keypoints(i))[:, :2].astype(np.float64) for i in index}
        pairs = []
        for pair_id, geometry in zip(*db.read_two_view_geometries(), strict=True):
            matches = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
            if len(matches) < MIN_INLIERS:
                continue
            first, second = (index[i] for i in pycolmap.pair_id_to_image_pair(pair_id))
            H = np.asarray(geometry.H, dtype=np.float64)
            if first > second:
                first, second, matches, H = second, first, matches[:, ::-1], np.linalg.inv(H)
            pairs.append(_Pair(first, second, matches, keypoints[first][matches[:, 0]],
                               keypoints[second][matches[:, 1]], H))
    return _Matched(pairs, keypoints, {frame: image_id for image_id, frame in index.items()})


def _image_motion(pairs: list[_Pair]) -> float | None:
    """The largest, over verified pairs, of the median displacement of their inlier matches (pixels);
    None when no pair was verified."""
    return max((p.motion_px for p in pairs), default=None)


def _rotations(pairs: list[_Pair], n: int, intrinsics: Intrinsics | None, width: int,
               height: int) -> tuple[np.ndarray, np.ndarray, Intrinsics] | None:
    """A camera that turns about its centre (no parallax: every pair a homography that is a rotation
    conjugated by the camera): (frame indices, c2w [R, 4, 4] with no translation, the camera), the
    rotations chained along the closest earlier frame; None when the homographies are no rotations.
    Without a camera given, its focal length is the one that makes them closest to rotations."""
    explained = [float(np.mean(np.linalg.norm(_transfer(p.H, p.points_a) - p.points_b, axis=1)
                               <= 2 * MAX_ERROR_PX)) for p in pairs]
    if not pairs or np.median(explained) < 0.9:
        return None
    pairs = [p for p, share in zip(pairs, explained, strict=True) if share >= 0.9]
    if intrinsics is None:
        side = max(width, height)
        focal = min(np.geomspace(0.3, 3.0, 121) * side, key=lambda f: np.median(_non_rotation(
            pairs, _k(f, f, width / 2, height / 2))))
        intrinsics = Intrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)
    K = _k(intrinsics.fx, intrinsics.fy, intrinsics.cx + 0.5, intrinsics.cy + 0.5)
    residual = _non_rotation(pairs, K)
    if np.median(residual) > MAX_NON_ROTATION:
        return None
    pairs = [p for p, r in zip(pairs, residual, strict=True) if r <= MAX_NON_ROTATION]
    rotation = {0: np.eye(3)}  # world-to-camera rotations, the world the first frame's camera
    for b in range(1, n):
        earlier = [p for p in pairs if p.b == b and p.a in rotation]
        if earlier:
            p = min(earlier, key=lambda p: p.a)  # the longest baseline: the fewest links to frame 0
            rotation[b] = nearest_rotation(_conjugated(p.H, K)) @ rotation[p.a]
    index = np.array(sorted(rotation), dtype=np.int64)
    c2w = np.tile(np.eye(4), (len(index), 1, 1))
    c2w[:, :3, :3] = [rotation[i].T for i in index]
    return index, c2w, intrinsics


def _k(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _transfer(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    moved = np.c_[points, np.ones(len(points))] @ H.T
    return moved[:, :2] / np.where(np.abs(moved[:, 2:]) < 1e-12, 1e-12, moved[:, 2:])


def _conjugated(H: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """K^-1 H K scaled to determinant 1 (a homography's scale and sign are arbitrary); None if singular."""
    m = np.linalg.solve(K, H @ K)
    det = np.linalg.det(m)
    return None if not np.isfinite(det) or abs(det) < 1e-12 else m / np.cbrt(det)


def _non_rotation(pairs: list[_Pair], K: np.ndarray) -> np.ndarray:
    """Per pair, how far K^-1 H K (scaled to determinant 1) is from a rotation M: max |M^T M - I|."""
    out = np.full(len(pairs), np.inf)
    for i, p in enumerate(pairs):
        m = _conjugated(p.H, K)
        if m is not None:
            out[i] = float(np.abs(m.T @ m - np.eye(3)).max())
    return out
def _keyframes(pairs: list[_Pair], n: int, motion_px: float) -> list[int]:
    """The frames the mapper runs on, in time order: from the first, each the farthest verified successor
    of the last, at most ``KEYFRAME_GAP`` frames on (fewer when the run would keep fewer than
    ``MIN_KEYFRAMES``), whose matches moved by at most ``motion_px`` (median); the next frame when none
    did."""
    gap = max(1, min(KEYFRAME_GAP, n // MIN_KEYFRAMES))
    moved = {(p.a, p.b): p.motion_px for p in pairs}
    keys = [0]
    while keys[-1] < n - 1:
        k = keys[-1]
        reach = [j for j in range(k + 2, min(n, k + gap + 1)) if moved.get((k, j), np.inf) <= motion_px]
        keys.append(max(reach, default=k + 1))
    return keys


def _options(pycolmap, reproj_px: float, keyframes: list[str], *, fixed: bool, threads: int, seed: int):
    """The mapper's options: the ``keyframes`` (image names) mapped at ``reproj_px``."""
    options = pycolmap.IncrementalPipelineOptions()
    options.image_names = keyframes
    options.num_threads = threads
    options.random_seed = seed
    options.extract_colors = False
    options.min_model_size = 3
    if fixed:
        options.ba_refine_focal_length = False
        options.ba_refine_extra_params = False
    options.ba_refine_principal_point = False
    mapper = options.mapper
    mapper.init_min_tri_angle = INIT_TRI_DEG
    mapper.init_min_num_inliers = 30
    mapper.init_max_error = MAX_ERROR_PX
    mapper.abs_pose_min_num_inliers = 30
    mapper.abs_pose_max_error = 2 * reproj_px
    mapper.filter_max_reproj_error = reproj_px
    mapper.filter_min_tri_angle = 1.0
    mapper.max_reg_trials = 5
    options.triangulation.min_angle = 1.0
    options.triangulation.merge_max_reproj_error = reproj_px
    options.triangulation.complete_max_reproj_error = reproj_px
    return options


def _map(pycolmap, database: Path, folder: Path, output: Path, options) -> list:
    """The mapper's models (largest first) of ``options``' keyframes."""
    output.mkdir()
    try:
        models = pycolmap.incremental_mapping(database, folder, output, options).values()
    except RuntimeError as exc:
        raise PoseEstimationError(f"structure from motion failed: {exc}") from exc
    return sorted(models, key=lambda m: -m.num_reg_images())


def _complete(pycolmap, database: Path, model, options, *, fixed: bool) -> None:
    """``model`` with its localized frames' own tracks triangulated (the keyframes' points alone are a
    sparse cloud of the scene), adjusted whole with the robust loss, and the points the mapper's filter
    rejects after it dropped."""
    mapped = set(options.image_names)
    with pycolmap.Database.open(database) as db:
        cache = pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions())
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(model)
    try:
        for image in list(model.images.values()):
            if image.has_pose and image.name not in mapped:
                mapper.triangulate_image(options.triangulation, image.image_id)
        _adjust(pycolmap, model, fixed=fixed)
        mapper.filter_points(options.mapper)
    except RuntimeError as exc:
        raise PoseEstimationError(f"structure from motion failed: {exc}") from exc
    finally:
        mapper.end_reconstruction(False)


def _localize(pycolmap, model, matched: _Matched, max_error_px: float, seed: int) -> None:
    """Register in ``model`` every frame it lacks that its registered frames' points locate: in passes,
    each frame's verified matches to the registered frames' keypoints with a 3D point give its 2D-3D
    correspondences, absolute pose (LO-RANSAC at ``max_error_px``, then refined) its pose, and its inliers
    join the points' tracks. A pass's frames give the next pass's their points, until none is added."""
    camera_id = next(iter(model.cameras))
    camera = model.cameras[camera_id]
    point_ids, xyz = _points(model)
    order = np.argsort(point_ids)
    sorted_ids = np.asarray(point_ids, dtype=np.int64)[order]
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = max_error_px
    options.ransac.random_seed = seed
    seen: dict[int, np.ndarray] = {}  # per registered frame: each keypoint's 3D point id, -1 for none
    for image in model.images.values():
        if image.has_pose:
            owner = np.full(image.num_points2D(), -1, dtype=np.int64)
            for i in image.get_observation_point2D_idxs():
                owner[i] = image.points2D[i].point3D_id
            seen[int(Path(image.name).stem)] = owner
    partners: dict[int, list[tuple[int, np.ndarray]]] = {}  # frame -> [(other frame, [M, 2]: its, ours)]
    for p in matched.pairs:
        partners.setdefault(p.a, []).append((p.b, p.matches[:, ::-1]))
        partners.setdefault(p.b, []).append((p.a, p.matches))
    while True:
        found = {}
        for frame, links in partners.items():
            if frame in seen or model.exists_image(matched.image_ids[frame]):
                continue
            ours, theirs = [], []
            for other, m in links:
                if other in seen:
                    point = seen[other][m[:, 0]]
                    ours.append(m[point >= 0, 1])
                    theirs.append(point[point >= 0])
            if not ours:
                continue
            keypoint, first = np.unique(np.concatenate(ours), return_index=True)
            point = np.concatenate(theirs)[first]
            if len(point) < MIN_POSE_INLIERS:
                continue
            pose = pycolmap.estimate_and_refine_absolute_pose(
                matched.keypoints[frame][keypoint], xyz[order[np.searchsorted(sorted_ids, point)]], camera,
                options)
            inliers = None if pose is None else np.asarray(pose["inlier_mask"], dtype=bool)
            if inliers is not None and inliers.sum() >= MIN_POSE_INLIERS:
                found[frame] = (pose["cam_from_world"], keypoint[inliers], point[inliers])
        if not found:
            return
        for frame, (cam_from_world, keypoint, point) in found.items():
            image_id = matched.image_ids[frame]
            model.add_image_with_trivial_frame(pycolmap.Image(
                name=f"{frame:06d}.png", keypoints=matched.keypoints[frame], camera_id=camera_id,
                image_id=image_id), cam_from_world)
            for i, point_id in zip(keypoint.tolist(), point.tolist(), strict=True):
                model.add_observation(point_id, pycolmap.TrackElement(image_id, i))
            seen[frame] = np.full(len(matched.keypoints[frame]), -1, dtype=np.int64)
            seen[frame][keypoint] = point


def _adjust(pycolmap, model, *, fixed: bool, held_rotations: bool = False) -> None:
    """A last bundle adjustment of ``model`` with a robust loss: a few matches on a moving part or a
    repeated texture otherwise pull whole frames centimetres off (the mapper's own adjustments use a
    squared loss). ``held_rotations``: the cameras' rotations held as they are, their positions and the
    points adjusted."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_extra_params = not fixed
    options.refine_principal_point = False
    options.constant_rig_from_world_rotation = held_rotations
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = ROBUST_PX
    config = pycolmap.BundleAdjustmentConfig()
    for image_id, image in model.images.items():
        if image.has_pose:
            config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    pycolmap.create_default_bundle_adjuster(options, config, model).solve()


def _registered(model) -> list:
    """The model's registered images, in time order."""
    return [image for _, image in sorted((int(Path(im.name).stem), im) for im in model.images.values()
                                         if im.has_pose)]


def _w2c(images: list) -> np.ndarray:
    """float64 [R, 4, 4]: the images' world-to-camera transforms (COLMAP's)."""
    w2c = np.tile(np.eye(4), (len(images), 1, 1))
    w2c[:, :3] = [im.cam_from_world().matrix() for im in images]
    return w2c


def _points(model) -> tuple[list[int], np.ndarray]:
    """The model's 3D point ids and positions (COLMAP's world, float64 [P, 3])."""
    ids = list(model.points3D.keys())
    return ids, np.array([model.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)


@dataclass(frozen=True)
class _World:
    """Where a model's poses are expressed: the first registered frame's camera (COLMAP's ``w2c0`` [4, 4]),
    scaled by ``scale`` so that the median depth of the points in front of the registered frames is 1."""

    w2c0: np.ndarray
    scale: float

    @classmethod
    def of(cls, model) -> _World:
        w2c = _w2c(_registered(model))
        _, points = _points(model)
        # at most 256 frames and 16384 points, evenly strided: the same median to a fraction of a percent,
        # where a minute of frames against all its points would take gigabytes
        w2c, points = w2c[::max(1, -(-len(w2c) // 256))], points[::max(1, -(-len(points) // 16384))]
        depths = np.einsum("rj,pj->rp", w2c[:, 2, :3], points) + w2c[:, 2, 3:]  # [R, P]
        depths = depths[depths > 0]
        return cls(w2c[0], 1.0 / float(np.median(depths)) if depths.size else 1.0)


def _poses(model, world: _World, images: np.ndarray,
           colors: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(frame indices [R], c2w [R, 4, 4]) of the registered frames, in ``world``; and the points in it
    (float64 [P, 3]) with their colours in ``images`` (uint8 [P, C]; None unless ``colors``)."""
    registered = _registered(model)
    index = np.array([int(Path(im.name).stem) for im in registered], dtype=np.int64)
    c2w = world.w2c0 @ np.linalg.inv(_w2c(registered))
    c2w[:, :3, 3] *= world.scale
    ids, points = _points(model)
    xyz = world.scale * (points @ world.w2c0[:3, :3].T + world.w2c0[:3, 3])
    by_id = {im.image_id: im for im in registered}
    return index, c2w, xyz, _colors(model, ids, by_id, images) if colors else None


def _hold_rotations(pycolmap, model, world: _World, rotations: np.ndarray, *, fixed: bool) -> None:
    """Turn the registered cameras of ``model`` to ``rotations`` (c2w [R, 3, 3] in ``world``, time order)
    about their centres, then adjust their positions and the points with the rotations held."""
    for image, rotation in zip(_registered(model), rotations, strict=True):
        cam_from_world = (world.w2c0[:3, :3].T @ rotation).T
        centre = image.projection_center()
        model.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(cam_from_world), -cam_from_world @ centre)
    _adjust(pycolmap, model, fixed=fixed, held_rotations=True)


def _colors(model, ids: list[int], images_by_id: dict, images: np.ndarray) -> np.ndarray:
    """uint8 [P, C]: each point's mean over the frames' pixels its track observes (COLMAP's keypoints have
    pixel centres at +0.5; the frames are ours, in any channels)."""
    frame, u, v, owner = [], [], [], []
    for k, point_id in enumerate(ids):
        for element in model.points3D[point_id].track.elements:
            image = images_by_id.get(element.image_id)
            if image is None:
                continue
            x, y = image.points2D[element.point2D_idx].xy
            frame.append(int(Path(image.name).stem))
            u.append(x - 0.5)
            v.append(y - 0.5)
            owner.append(k)
    h, w, c = images.shape[1:]
    colors = np.zeros((len(ids), c), dtype=np.float64)
    if not owner:
        return colors.astype(np.uint8)
    col = np.clip(np.rint(u), 0, w - 1).astype(np.int64)
    row = np.clip(np.rint(v), 0, h - 1).astype(np.int64)
    owner_arr = np.asarray(owner)
    np.add.at(colors, owner_arr, images[np.asarray(frame), row, col].astype(np.float64))
    counts = np.bincount(owner_arr, minlength=len(ids))[:, None]
    return np.rint(colors / np.maximum(counts, 1)).astype(np.uint8)


def _camera(camera, given: Intrinsics | None, width: int, height: int) -> tuple[Intrinsics, float]:
    """The camera in our convention (pixel centres at integers) and its radial term."""
    if given is not None:
        return given, 0.0
    f, cx, cy, k = (float(v) for v in camera.params)
    return Intrinsics(f, f, cx - 0.5, cy - 0.5, width, height), k
