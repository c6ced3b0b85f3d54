"""Calibrate a camera from a folder of frames or a video (and the frame reading that undistorting shares).

``calibrate_path(path)`` reads the frames (a folder of images, sorted by name with numbers in
their natural order, or a video through PyAV, the ``video`` extra, or OpenCV:
:mod:`lensdist_torch.core.video`), brings each to the analysis size as
it is read (a long video stays small), and runs
:func:`~lensdist_torch.calibration.direct.calibrate_sequence`; it returns a strict-JSON-ready
dict (None for unknown numbers, never NaN) with the coefficients of eq. 4 in the frames' own
pixels, Delta_avg and Delta_max with their 95 % intervals, the class, and OpenCV's camera
matrix and distortion coefficients (:mod:`~lensdist_torch.geometry.opencv_model`).
Undistorting the frames: :mod:`lensdist_torch.workflows.undistort`. ``lensdist_torch.cli.calibrate``
registers ``lensdist calibrate`` and ``lensdist undistort``. ``synthetic_sequence`` renders the
test sequences of a panning camera.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
import torch.nn.functional as F

from lensdist_torch.calibration.controllers.answer_lens import answer_lens, radial_lens_opencv, scale_lens
from lensdist_torch.calibration.controllers.multiview_path import MIN_FRAMES, combine, multiview_path
from lensdist_torch.calibration.controllers.verify import verdict, verify_undistortion
from lensdist_torch.calibration.direct import (
    NO_TEXTURE,
    TOO_LITTLE_MOTION,
    CalibrationConfig,
    analysis_scale,
    calibrate_sequence,
    to_analysis,
)
from lensdist_torch.calibration.direct_fits import unregistered
from lensdist_torch.config import LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.frames import frames_of_one_size
from lensdist_torch.core.images import load_scene
from lensdist_torch.core.threads import torch_threads
from lensdist_torch.data.realism import degrade, draw_realism
from lensdist_torch.data.relief import draw_height_field, relief_samples
from lensdist_torch.geometry.distortion import distortion_center, distortion_grid
from lensdist_torch.geometry.opencv_model import opencv_export

METHODS = ("auto", "multiview", "direct")
#: A class is verified on this many pairs, registered again after undistorting: fewer error blocks, or no class.
VERIFY_PAIRS = 6
#: Where the OpenCV camera's fx = fy comes from (the answer's ``focal_source``): COLMAP's bundle
#: adjustment (the multi-view camera), the caller's ``focal``, or the half diagonal (a convention).
FOCAL_SOURCES = ("colmap", "given", "half diagonal")

__all__ = ["METHODS", "FOCAL_SOURCES", "calibrate_path", "synthetic_sequence", "tilted_offsets", "MAX_TILT_DEG"]

# ------------------------------------------------------------------ calibration
def _finite(value):
    """NaN / inf -> None, recursively; tensors and tuples -> lists (strict JSON)."""
    if isinstance(value, torch.Tensor):
        value = value.tolist()
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _opencv(k2: float, k4: float, size: tuple[int, int], focal: float | None, model: str) -> dict | None:
    return opencv_export(k2, k4, *size, focal=focal, model=model)


def calibrate_path(
    path: str | Path,
    *,
    config: CalibrationConfig | None = None,
    settings: LensdistConfig | None = None,
    max_frames: int | None = 300,
    focal: float | None = None,
    quiet: bool = True,
    device: torch.device | str | None = None,
    method: str = "auto",
) -> dict:
    """Calibrate the camera of a folder of frames or a video (module docstring).

    Args:
        path: a folder of images (one camera, one size, in recording order by name) or a video.
        config: :class:`~lensdist_torch.config.CalibrationConfig`, the ``[calibration]`` every path reads
            (its coverage); ``settings.calibration`` when None.
        settings: the library's :class:`~lensdist_torch.config.LensdistConfig`.
        max_frames: read at most this many frames (None: all).
        focal: OpenCV's fx = fy in pixels; the half diagonal when None.
        quiet: no progress bars.
        device: where the registration and the self-calibration run (default: the CPU); the
            frames are read and brought to the analysis size on the CPU.
        method: "direct" (the photometric self-calibration of pairs), "multiview" (bundle
            adjustment on COLMAP's tracks, needs pycolmap, beside the homography model's lens) or
            "auto" (the direct path's lens held on the tracks too, every candidate weighed on the same
            held-out frames: :func:`~lensdist_torch.calibration.controllers.multiview_path.combine`; the
            direct path alone where pycolmap is missing). In "auto" the direct path fits its batches of
            pairs beside COLMAP where it leaves a core idle (its matching, its mapping once the homography
            model is done) and where the models wait for it, on the torch threads ``multiview.num_threads``
            leaves (at least one; the count is restored after). Frames that moved too little for the direct path
            (its ``too little motion`` reason) get that answer from every method, before any mapping.

    Returns:
        A dict for ``json.dumps(..., allow_nan=False)``: path, frames, image_size [H, W],
        analysis_size, scale, k2_user, k4_user, delta_avg_user_px, delta_avg_user_interval,
        delta_max_user_px, delta_max_user_interval, confidence, class, reason, pairs_used,
        pairs_rejected, pairs_refitted (pairs fitted again from their own registration),
        pairs_unregistered (pairs whose fit did not register them, ``direct_fits.MAX_MISFIT``; among the rejected),
        relief_effect_px and relief_z (the direct path's: how far its plane + parallax and planar answers part, and
        in how many stds), opencv and opencv_rational (camera_matrix, dist_coeffs and their errors), focal_source
        (where OpenCV's fx = fy comes from: one of ``FOCAL_SOURCES``), method (whose lens answered:
        "direct", "multiview", "planar"; :func:`~lensdist_torch.calibration.controllers.multiview_path.combine`),
        direct, multiview and planar (each path's own numbers; planar: the homography model of the multi-view
        path).

    Example:
        >>> import tempfile
        >>> from lensdist_torch.core.png import encode_png, to_uint8
        >>> from lensdist_torch.workflows.undistort import undistort_path
        >>> tmp = tempfile.TemporaryDirectory()
        >>> folder = Path(tmp.name)
        >>> for i, frame in enumerate(synthetic_sequence(10, 1e-5, 0.0, size=(120, 160))[0]):
        ...     _ = (folder / f"frame_{i}.png").write_bytes(encode_png(to_uint8(frame)))
        >>> res = calibrate_path(folder, method="direct")  # the photometric path alone: COLMAP with 2 threads varies
        >>> res["frames"], res["class"], round(res["k2_user"] * 1e5, 1)
        (10, '2', 1.0)
        >>> out = undistort_path(folder, folder / "undistorted", k2=res["k2_user"], k4=res["k4_user"])
        >>> out["frames"], (folder / "undistorted" / "masks" / "frame_9.png").is_file()
        (10, True)
        >>> tmp.cleanup()
    """
    from tqdm import tqdm

    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if focal is not None and (isinstance(focal, bool) or not isinstance(focal, (int, float)) or not math.isfinite(focal)
                              or focal <= 0):  # checked before the run, not by the OpenCV export at its end
        raise ValueError(f"focal must be a positive number of pixels or None, got {focal!r}")
    st = or_defaults(settings, LensdistConfig, "settings")
    cfg = st.calibration if config is None else or_defaults(config, CalibrationConfig)
    st, frames, scale = dataclasses.replace(st, calibration=cfg), [], 1.0  # one [calibration] for every path
    for _, img in frames_of_one_size(path, grey=True, max_frames=max_frames, quiet=quiet, desc="reading"):
        scale = scale if frames else analysis_scale(*img.shape[-2:], cfg)
        frames.append(to_analysis(img, scale))
        size = tuple(img.shape[-2:])
    if len(frames) < 2:
        raise ValueError(f"path {path} must hold at least 2 frames of one camera, got {len(frames)}")
    n, frames = len(frames), torch.cat(frames)  # one copy of the frames, shared by the direct path and the verifier
    beside = method == "auto" and n >= MIN_FRAMES  # the direct path beside COLMAP's threads
    threads = torch.get_num_threads()
    with tqdm(disable=quiet, desc="pairs", unit="pair", leave=False) as bar, ThreadPoolExecutor(1) as pool, \
            torch_threads(max(1, threads - st.multiview.num_threads) if beside else threads):
        paired, stopped = threading.Event(), threading.Event()  # it has pairs to fit (or answered); stop it
        idle = threading.Event()  # COLMAP leaves a core idle, or waits for the direct path: it may fit a batch
        if not beside:
            idle.set()

        def progress(done: int, total: int) -> None:
            paired.set()
            bar.total = total
            bar.update(done - bar.n)
            idle.wait()  # before and between batches, while COLMAP takes every core (or has not begun)
            if stopped.is_set():  # the caller failed or was interrupted: the direct path ends at its next batch
                raise _Stopped

        def direct_result() -> tuple:  # the direct path's answer, its batches free to run meanwhile
            idle.set()
            return direct.result()

        def direct_path() -> tuple:
            cal = calibrate_sequence(frames.to(device or "cpu"), cfg, st, frame_size=size, progress=progress)
            return cal, _direct_answer(cal, cfg, path, size, focal)

        direct = pool.submit(direct_path)
        direct.add_done_callback(lambda _: paired.set())
        try:
            if not beside:
                direct.result()
            paired.wait()  # frames that moved too little answer before any mapping: no mapping can see more
            mv = None
            early = direct.result()[0] if direct.done() else None  # done already: not beside, or no pairs to fit
            if method != "direct" and n >= MIN_FRAMES and early is not None and _unmappable(early):
                mv = {"ok": False, "reason": early.reason}
            elif method != "direct":  # "auto": the direct path fits its pairs where COLMAP leaves a core idle
                mv = multiview_path(path, size, config=st.multiview, settings=st, max_frames=max_frames,
                                    quiet=quiet, direct=(lambda: direct_result()[1]) if beside else None,
                                    idle=idle if beside else None)
                if method == "multiview" and not mv["ok"]:
                    raise ValueError(mv["reason"])
            cal, out = direct_result()
        except BaseException:
            stopped.set()
            idle.set()
            raise
    return _finite(_verified(_with_focal(combine(out, mv), focal, size), frames, cal, cfg, st))


class _Stopped(Exception):
    """Ends the direct path running beside the multi-view one where that one failed or was interrupted."""


def _direct_answer(cal, cfg: CalibrationConfig, path: str | Path, size: tuple[int, int], focal: float | None) -> dict:
    """The direct path's answer (``calibrate_path``'s dict before the paths combine)."""
    out = {k: getattr(cal, k) for k in ("frames", "image_size", "analysis_size", "scale", "k2_user", "k4_user",
                                        "delta_avg_user_px", "delta_avg_user_interval", "delta_max_user_px",
                                        "delta_max_user_interval", "relief_effect_px", "relief_z")}
    out.update({"path": str(path), "confidence": cfg.confidence, "class": cal.class_label, "reason": cal.reason or None,
                "pairs_used": cal.pairs_used, "pairs_rejected": cal.pairs_rejected,
                "pairs_refitted": int(cal.pair_refitted.sum()) if cal.pair_refitted is not None else 0,
                "pairs_unregistered": int(unregistered(cal.pair_misfit).sum()),
                "opencv": _opencv(cal.k2_user, cal.k4_user, size, focal, "standard"),
                "opencv_rational": _opencv(cal.k2_user, cal.k4_user, size, focal, "rational")})
    return out


def _unmappable(cal) -> bool:
    """Whether the direct path found the frames moved too little, or have nothing to match (no pair at all)."""
    return not len(cal.pairs) and cal.reason.startswith((TOO_LITTLE_MOTION, NO_TEXTURE))


def _with_focal(res: dict, focal: float | None, size: tuple[int, int]) -> dict:
    """``focal_source`` (one of ``FOCAL_SOURCES``) added; the homography model's OpenCV camera fitted at a given focal.

    Eq. 4 and the homography model's lens have no focal length: their OpenCV camera takes
    ``focal`` where given, else the half diagonal, a convention. The multi-view camera's focal is
    COLMAP's estimate from the bundle adjustment, whatever ``focal`` says.
    """
    if res.get("method") == "multiview":
        res["focal_source"] = FOCAL_SOURCES[0]
        return res
    res["focal_source"] = FOCAL_SOURCES[1] if focal is not None else FOCAL_SOURCES[2]
    lens = answer_lens(res)
    if focal is not None and lens is not None and lens["kind"] == "radial":
        for key, model in (("opencv", "standard"), ("opencv_rational", "rational")):
            res[key] = radial_lens_opencv(lens, *size, focal=focal, model=model)
    return res


def _verified(res: dict, frames: torch.Tensor, cal, cfg: CalibrationConfig, st: LensdistConfig) -> dict:
    """The answer, its class withheld where undistorting with it does not lower the registration errors.

    Adds ``verification`` (:func:`~lensdist_torch.calibration.controllers.verify.verify_undistortion`'s dict
    with a ``verdict``: "lowered" (more pairs registered after the correction, or the same and a
    lower share of error blocks), "not lowered" (the class is withheld: no lower share, or fewer
    pairs registered) or "not measurable" (no pair registered both times: far-apart views; the
    class stands, unverified); None where there is no distortion class to verify).
    """
    res["verification"] = None
    if VERIFY_PAIRS == 0 or res["class"] in (None, "R") or res.get("k2_user") is None:
        return res
    pairs = cal.pairs[cal.pair_used] if bool(cal.pair_used.any()) else cal.pairs
    if len(pairs) == 0:  # the direct path chose none (the multi-view path answered): far-apart frames
        n = len(frames)
        pairs = torch.stack([torch.arange(n - n // 2), torch.arange(n // 2, n)], 1)
    s = res["scale"]  # user px per analysis px; the answer's own lens where eq. 4 only approximates it
    check = verify_undistortion(frames, pairs, res["k2_user"] * s**2, res["k4_user"] * s**4, settings=st,
                                max_pairs=VERIFY_PAIRS,
                                lens=scale_lens(answer_lens(res), 1 / s))
    before, after = check["error_share_before"], check["error_share_after"]
    check["verdict"] = verdict(check)
    shares = f"{check['registered_before']} pairs registered before, {check['registered_after']} after"
    if before is not None and after is not None:  # pairs registered both times: their shares
        shares += f"; of their blocks {100 * before:.1f} % before, {100 * after:.1f} % after"
    res["verification"] = check
    if check["verdict"] == "not lowered":
        res.update({"class": None, "reason": "undistorting the frames with the estimate does not lower their "
                    f"registration errors (the paper's metric over {check['pairs']} pairs: {shares})"})
    return res


# ------------------------------------------------------------------ synthetic sequences
#: The largest tilt of :func:`synthetic_sequence`'s oblique views: every ray of a 90-degree view still meets the ground.
MAX_TILT_DEG = 30.0


def tilted_offsets(rel: torch.Tensor, focal: float, pitch: float, roll: float) -> torch.Tensor:
    """Where a tilted pinhole's rays meet the ground, as offsets from the point below it, in an upright one's pixels.

    ``rel`` (..., 2): ideal pixel offsets (x, y) from the principal point of a camera ``focal`` px
    from its image; the camera is turned by ``pitch`` (about its x axis) then ``roll`` (about its y
    axis), radians. An upright camera (0, 0) gives ``rel`` back; a ray (x, y, f) turned to (a, b, c)
    meets the ground f (a, b) / c from the nadir, at the scale of the upright view.

    Example:
        >>> import math, torch
        >>> o = tilted_offsets(torch.zeros(1, 2, dtype=torch.float64), 100.0, math.radians(10), 0.0)
        >>> [round(v, 3) for v in o[0].tolist()]  # the principal ray tilted by 10 degrees: f tan 10 along y
        [0.0, -17.633]
    """
    rays = torch.cat([rel, torch.full_like(rel[..., :1], focal)], -1)
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    about_x = rel.new_tensor([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    about_y = rel.new_tensor([[cr, 0.0, sr], [0.0, 1.0, 0.0], [-sr, 0.0, cr]])
    d = rays @ (about_y @ about_x).T
    if bool((d[..., 2] <= 0).any()):
        raise ValueError(f"pitch and roll must leave every ray pointing at the ground, got {pitch} and {roll} rad")
    return focal * d[..., :2] / d[..., 2:]


def synthetic_sequence(
    n_frames: int = 20,
    k2: float = 0.0,
    k4: float = 0.0,
    *,
    size: tuple[int, int] = (320, 424),
    scene: str = "gravel",
    step_px: tuple[float, float] = (5.0, 10.0),
    jitter_px: float = 1.0,
    rotation_deg: float = 0.2,
    seed: int = 0,
    realistic: bool = False,
    config: LensdistConfig | None = None,
    relief: float = 0.0,
    altitude: float = 0.0,
    tilt_deg: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera panning down an embedded scene, every frame distorted by one (k2, k4).

    Frame n views the scene about c_n = (x0 + jitter, y0 + sum of steps) with a small rotation:
    the ideal frame is I_n(p) = S(c_n + z Rot_n (p - p0)), the distorted one I_n(p(p_d)) (eq. 4),
    one ``grid_sample`` each. Steps ~ U[step_px], horizontal jitter ~ U[-jitter_px, jitter_px],
    rotation ~ U[-rotation_deg, rotation_deg]; the zoom z (scene px per frame px) is the largest
    that keeps every sample inside the scene.

    With ``realistic`` each distorted frame also gets what a video frame has, drawn as the first
    view of the realistic pair protocol (:func:`~lensdist_torch.data.realism.degrade`, ranges from
    ``config.protocol``, default :class:`LensdistConfig`): its own gain, offset, gamma and
    illumination ramp, sensor noise, 8-bit JPEG and, in ``occluder_rate`` of the frames, a patch
    (a moving object: it is at another place or absent in the other frames). The ideal frames
    stay clean.

    With ``relief`` > 0 the scene is not a plane: a height field of 4 Gaussian hills and hollows
    whose largest height is ``relief`` times the camera's height (drawn from ``seed``), seen as
    a pinhole camera looking straight down sees it (:mod:`lensdist_torch.data.relief`): parallax
    in proportion to each frame's baseline, none for the rotation. ``altitude`` > 0 changes the
    camera's height per frame: the view's scale ~ U[1 - altitude, 1], the heights' fractions
    divided by it (a radial parallax).

    ``tilt_deg`` > 0 gives oblique views: each frame's optical axis tilted from the vertical by a
    pitch and a roll ~ U[-tilt_deg, tilt_deg] each (a pinhole of focal length the frame's width),
    so that the frames' axes are no longer parallel. A pixel's ray then meets the flat ground where
    a homography says, and a point of height rho lies on it at 1 - rho of the way from the camera
    (:func:`~lensdist_torch.data.relief.relief_samples`, the ground point below the camera as
    its nadir). 0 draws nothing and renders what it always did.

    Returns:
        distorted, ideal: (N, 1, H, W) float32 (ideal: the same path with k2 = k4 = 0).

    Example:
        >>> distorted, ideal = synthetic_sequence(4, 1e-6, 0.0, size=(64, 80))
        >>> tuple(distorted.shape), tuple(ideal.shape)
        ((4, 1, 64, 80), (4, 1, 64, 80))
    """
    g = torch.Generator().manual_seed(seed)
    h, w = size
    src = load_scene(scene).double()
    hs, ws = src.shape[-2:]
    c = torch.tensor(distortion_center(h, w), dtype=torch.float64)
    rel = torch.stack([distortion_grid([k2], [k4], h, w, dtype=torch.float64)[0],
                       distortion_grid([0.0], [0.0], h, w, dtype=torch.float64)[0]]) - c
    u = torch.rand(3, n_frames, generator=g, dtype=torch.float64)
    ty = torch.cat([torch.zeros(1, dtype=torch.float64), (step_px[0] + (step_px[1] - step_px[0]) * u[0, 1:]).cumsum(0)])
    tx, th = jitter_px * (2 * u[1] - 1), torch.deg2rad(rotation_deg * (2 * u[2] - 1))
    scale = (
        1 - altitude * torch.rand(n_frames, generator=g, dtype=torch.float64)
        if altitude > 0
        else torch.ones(n_frames, dtype=torch.float64)
    )
    field = draw_height_field(g, (0.0, ws - 1.0, 0.0, hs - 1.0), relief) if relief > 0 else None
    if not (math.isfinite(tilt_deg) and 0 <= tilt_deg <= MAX_TILT_DEG):
        raise ValueError(f"tilt_deg must be in [0, {MAX_TILT_DEG}] degrees, got {tilt_deg}")
    rels = [rel] * n_frames
    if tilt_deg > 0:  # drawn last: the other draws stay those of an upright camera
        tilts = torch.deg2rad(tilt_deg * (2 * torch.rand(2, n_frames, generator=g, dtype=torch.float64) - 1))
        rels = [tilted_offsets(rel, float(w), float(tilts[0, i]), float(tilts[1, i])) for i in range(n_frames)]
    big = torch.stack([r.abs().amax(dim=(0, 1, 2)) for r in rels]).amax(0)
    ext = big + math.sin(math.radians(abs(rotation_deg))) * big.flip(0) + 2  # half extents, any rotation drawn
    ext = ext * (1 + relief / (1 - altitude))  # a hollow moves samples away from the nadir
    z = min((ws - 1) / (2 * float(ext[0]) + 2 * jitter_px), (hs - 1) / (2 * float(ext[1]) + float(ty[-1])))
    out = []
    for i in range(n_frames):
        cos, sin = math.cos(float(th[i])), math.sin(float(th[i]))
        ri = rels[i] * float(scale[i])  # exactly rel at a constant altitude
        x = (ws - 1) / 2 + z * (tx[i] + cos * ri[..., 0] - sin * ri[..., 1])
        y = z * (float(ext[1]) + ty[i] + sin * ri[..., 0] + cos * ri[..., 1])
        nadir = ((ws - 1) / 2 + z * float(tx[i]), z * (float(ext[1]) + float(ty[i])))
        # heights are fractions of the camera's height: a lower camera sees the same hills larger
        x, y = relief_samples(x, y, nadir, field, altitude=float(scale[i]))
        out.append(F.grid_sample(src.expand(2, -1, -1, -1), torch.stack([x / (ws - 1), y / (hs - 1)], -1) * 2 - 1,
                                 align_corners=True).float())
    frames = torch.stack(out, 1)  # (2, N, 1, H, W)
    distorted = frames[0].contiguous()
    if realistic:
        cfg = or_defaults(config, LensdistConfig)
        cfg = dataclasses.replace(cfg, image=dataclasses.replace(cfg.image, height=h, width=w))  # the patches' frame
        real = draw_realism(cfg, [1_000_003 * seed + i for i in range(n_frames)])
        distorted = degrade(distorted, distorted, real)[0]
    return distorted, frames[1].contiguous()
