"""The ``lensdist calibrate`` and ``lensdist undistort`` commands, a user's camera (parsers and printing).

Like ``commands.py`` it imports torch only inside the commands, so ``lensdist --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from statistics import NormalDist

from lensdist_torch.cli import support as argtypes

__all__ = ["add_calibrate_commands"]


def _straightness(pl: dict) -> str:
    """How straight the homography model's lens map makes lines, where the jackknife could tell."""
    b, share = pl.get("bending_halfwidth_px"), pl.get("matched_fraction")
    if not isinstance(b, float) or b != b or not isinstance(share, float):
        return ""
    return (
        f"; it straightens lines to +-{b:.2f} px (95 %, RMS over the {100 * share:.0f} % of the frame "
        "its matches reach)"
    )


def _guided(pl: dict) -> str:
    """What guided matching did for the homography model, where it ran."""
    g = pl.get("guided")
    if not isinstance(g, dict):
        return ""
    first = g["first_fit"]
    if not g.get("used"):
        return f"; guided matching found no answer ({g.get('reason')}): the first fit's"
    return (
        f"; on guided matches ({g['matches']} in {g['pairs_matched']} of {g['pairs_verified']} verified pairs; "
        "the first "
        f"fit on the verified matches: {first['pairs']} pairs, Delta_avg {first['delta_avg_user_px']:.2f} px)"
    )


def _refined(pl: dict) -> str:
    """What the sub-pixel refinement of its matches did for the homography model, where it ran."""
    r = pl.get("refined")
    if not isinstance(r, dict):
        return ""
    if not r.get("used"):
        return f"; its matches refined found no answer ({r.get('reason')}): the fit before"
    before = r["before"]
    return (f"; on sub-pixel matches ({r['kept']} of {r['matches']} kept, moved {r['median_shift_px']:.2f} px median; "
            f"before: {before['pairs']} pairs, RMS {before['reprojection_px']:.2f} px, Delta_avg "
            f"{before['delta_avg_user_px']:.2f} px)")


def _paths(res: dict) -> None:
    """Each path's own numbers, after the answer: the frames, the direct and multi-view paths, the homography model."""
    (h, w) = res["image_size"]
    unregistered = f" ({res['pairs_unregistered']} not registered)" if res.get("pairs_unregistered") else ""
    print(
        f"{res['frames']} frames of {w} x {h}; direct path: {res['pairs_used']} pairs used, "
        f"{res['pairs_rejected']} rejected"
        + unregistered
    )
    mv = res.get("multiview")
    if mv is not None and "model" not in mv:
        print(f"multi-view path: no answer ({mv['reason']})")
    elif mv is not None:
        weight = (mv.get("models") or {}).get(mv["model"], {}).get("weight")
        by = "" if weight is None else f" (weight {weight:.2f} on held-out frames)"
        iv = mv["delta_avg_user_interval"]
        best = f"camera model {mv['model']}" if mv["model"] not in _HELD else f"{_HELD[mv['model']]} held on its tracks"
        print(
            f"multi-view path: {mv['registered']} frames registered, {mv['points3D']} tracks, {best}"
            f"{by}, reprojection RMS {mv['reprojection_px']:.2f} px, Delta_avg {mv['delta_avg_user_px']:.2f} px"
            + ("" if iv is None or None in iv else f" [{iv[0]:.2f}, {iv[1]:.2f}]")
        )
    pl = res.get("planar")
    if pl is not None and "terms" not in pl:
        print(f"homography model: no answer ({pl['reason']})")
    elif pl is not None:
        print(
            f"homography model: {pl['pairs']} pairs, {pl['inliers']} of {pl['matches']} matches on one homography per "
            f"pair, {pl['terms']} radial terms about ({pl['centre'][0]:.1f}, {pl['centre'][1]:.1f}) (by BIC), RMS "
            f"{pl['reprojection_px']:.2f} px, Delta_avg {pl['delta_avg_user_px']:.2f} px "
            f"({pl['class'] or 'cannot tell: ' + str(pl['reason'])})" + _straightness(pl) + _guided(pl) + _refined(pl)
        )


#: Another path's lens held on COLMAP's tracks (``multiview_path.HELD_PATHS``), as the multi-view line names it.
_HELD = {"direct": "the direct path's lens", "planar": "the homography model's lens"}
#: Which path an answer's ``method`` names, in words.
_FROM = {"direct": "the direct path (eq. 4)", "multiview": "the multi-view path (COLMAP)",
         "planar": "the homography model"}
#: What the OpenCV camera's fx = fy is, per ``focal_source``.
_FOCAL = {"colmap": "COLMAP's estimate from the bundle adjustment",
          "given": "yours (--focal)",
          "half diagonal": "the half diagonal, a convention (the lens model has no focal length; --focal F sets yours)"}


def _focal_spread(res: dict) -> str:
    """", +-X px (95 %)" of COLMAP's focal length from its posterior, or why there is none.

    "" for the other sources, and for another path's camera weighed at COLMAP's focal (its row has
    no ``focal_std_px``: the focal is not that camera's own estimate).
    """
    row = ((res.get("multiview") or {}).get("models") or {}).get(res.get("camera_model"), {})
    if res.get("focal_source") != "colmap" or "focal_std_px" not in row:
        return ""
    std = row["focal_std_px"]  # None in the JSON where the posterior has no bound
    if std is None or not math.isfinite(std):
        return ", not determined by the tracks: a value to check, not to use"
    level = res.get("confidence") or 0.95
    return f", +-{NormalDist().inv_cdf(0.5 + level / 2) * std:.1f} px ({100 * level:.0f} %)"


def _kind(res: dict) -> str:
    """", barrel" / ", pincushion" / ", mustache" of the answer's eq. 4, or ""."""
    from lensdist_torch.geometry.distortion import distortion_type
    from lensdist_torch.geometry.frame import half_diagonal

    r = half_diagonal(*res["image_size"])
    kind = distortion_type(res["k2_user"] * r**2, res["k4_user"] * r**4)
    return f", {kind}" if kind else ""


def _print_calibration(res: dict, out: str | Path | None = None, *, debug: bool = False) -> None:
    """The answer (class, Delta, OpenCV's camera, the next command); eq. 4 and each path's numbers with ``debug``.

    An answer without an estimate prints each path's numbers always: they say why there is none.
    """
    (h, w), (lo, hi), (mlo, mhi) = res["image_size"], res["delta_avg_user_interval"], res["delta_max_user_interval"]
    if res["k2_user"] is None:
        print(f"no estimate: {res['reason']}")
        _paths(res)
        return
    print(
        f"distortion class: {(res['class'] + _kind(res)) if res['class'] else 'cannot tell (' + res['reason'] + ')'}  "
        "(1 = small ... 4 = very strong, R = none visible)"
    )
    # where it cannot tell, the numbers are the estimate that could not be trusted, and say so
    tag = "" if res["class"] is not None else "estimate, not an answer: "
    for name, d, a, b in (("avg", res["delta_avg_user_px"], lo, hi), ("max", res["delta_max_user_px"], mlo, mhi)):
        bound = (
            ""
            if a is None
            else (
                f" (95 % interval {a:.2f} to {b:.2f})"
                if b is not None
                else f" (95 % interval from {a:.2f}, no upper bound: a model the tracks do not determine)"
            )
        )
        print(f"{tag}Delta_{name} = {d:.2f} px" + bound + f" over your {w} x {h} frames")
    print(f"from {_FROM.get(res.get('method'), res.get('method'))}"
          + (f", lens model {res['camera_model']}" if res.get("camera_model") else "") + (
        "" if res.get("eq4_fit_error_px") is None else
        f"; Delta over the {100 * res['invertible_fraction']:.1f} % of pixels where its lens inverts"))
    from lensdist_torch.calibration.controllers.answer_lens import opencv_to_use
    from lensdist_torch.geometry.opencv_model import FOLLOWS_PX

    standard, use = res["opencv"] or res.get("opencv_rational"), opencv_to_use(res)
    shown = [standard] if use is standard else [standard, use]  # the 5 coefficients cannot follow: the 8 beside
    for cv in shown:
        k, n = cv["camera_matrix"], len(cv["dist_coeffs"])
        forward = cv.get("forward_error_mean_px")
        print(
            f"{tag}OpenCV ({n} coefficients): fx = {k[0][0]:.2f}, fy = {k[1][1]:.2f}, "
            f"cx = {k[0][2]:.2f}, cy = {k[1][2]:.2f}, "
            f"dist_coeffs = [{', '.join(f'{v:.6g}' for v in cv['dist_coeffs'])}] (undistortPoints error "
            f"{cv['fit_error_mean_px']:.3f} px mean, {cv['fit_error_max_px']:.3f} px max"
            + ("" if forward is None else f"; cv2.undistort's map {forward:.3f} px mean")
            + ")"
        )
    if res.get("focal_source") in _FOCAL:
        print(f"fx, fy: {_FOCAL[res['focal_source']]}{_focal_spread(res)}")
    if len(shown) == 2:
        print(f"OpenCV's 5 coefficients do not follow this lens (over {FOLLOWS_PX:g} px mean): use the 8 rational ones "
              "(cv2.CALIB_RATIONAL_MODEL's order); `lensdist undistort --from` applies the answer's own lens")
    if res["class"] is not None and res["class"] != "R":
        src = res.get("path", "PATH")
        cal = Path(out) / "calibration.json" if out else None
        print(
            "next: "
            + (
                f"lensdist undistort {src} --from {cal} --out {Path(out) / 'undistorted'}"
                if cal
                else f"lensdist calibrate {src} --out DIR, then lensdist undistort {src} --from DIR/calibration.json "
                "--out DIR/undistorted"
            )
        )
    if not debug:
        print("eq. 4's k2, k4 and each path's numbers: with --debug, or in the JSON (--json, --out)")
        return
    print(
        f"{tag}eq. 4 about the frame centre, in your pixels: k2 = {res['k2_user']:.4e}, k4 = {res['k4_user']:.4e}"
        + (
            ""
            if res.get("eq4_fit_error_px") is None
            else f" (follows the answer's lens to {res['eq4_fit_error_px']:.2f} px RMS)"
        )
    )
    print("each path:")
    _paths(res)


def _archive_mode(args: argparse.Namespace) -> bool:
    """Several inputs, a glob, a manifest or an archive option: the archive run; one PATH alone: as ever."""
    return (
        len(args.paths) != 1
        or args.manifest is not None
        or args.shard is not None
        or args.engine is not None
        or args.ray_address is not None
        or (any(c in args.paths[0] for c in "*?[") and not Path(args.paths[0]).exists())
    )


def _print_archive(run) -> None:
    """The archive run in words: its counts, each failed input's reason, each camera's pooled answer, its files."""
    share = "" if run.selected == run.inputs else f" ({run.selected} in this share)"
    print(f"{run.inputs} inputs{share}: {run.computed} calibrated, {run.reused} reused from an earlier run; "
          f"{len(run.rows)} rows in the table, {run.failed} without an answer")
    for row in run.rows:
        if not row.ok:
            print(f"  failed: {row.path}: {row.reason}")
    for cam in run.cameras:
        name = f"camera {cam.camera} ({cam.size})" if cam.camera else f"frames of {cam.size}"
        if cam.delta_avg_px is None:
            print(f"{name}: {cam.inputs} inputs, none answered")
            continue
        off = "none" if not cam.disagreeing else ", ".join(cam.disagreeing)
        print(
            f"{name}: {cam.inputs} inputs, {cam.answered} answered: Delta_avg {cam.delta_avg_px:.2f} px pooled over "
            f"{cam.pooled} (95 % interval {cam.delta_avg_low_px:.2f} to {cam.delta_avg_high_px:.2f}); "
            f"disagreeing: {off}"
        )
    print("written: " + ", ".join(run.files) + f", {Path(run.out) / 'answers'}/")


def _cmd_archive(args: argparse.Namespace) -> int:
    """``lensdist calibrate PATH... | --manifest FILE --out DIR [--shard I/N] [--engine local|ray]``: 0 if it ran."""
    from lensdist_torch.calibration.controllers import archive

    if args.engine == "ray":
        archive.require_ray()  # one line naming the extra, before any work
    if not args.out:
        raise ValueError("--out DIR is needed with several inputs, a glob or --manifest (answers, rows, answers.csv)")
    from lensdist_torch.core.outputs import check_output_dir

    check_output_dir(args.out, "--out", {"path": args.paths, "--manifest": args.manifest, "--config": args.config})
    inputs = archive.archive_inputs(args.paths, manifest=args.manifest)
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.analyze import resolve_device

    settings = None if args.config is None else load_config(args.config)
    run = archive.run_archive(inputs, args.out, method=args.method, max_frames=args.max_frames, focal=args.focal,
                              device=resolve_device(args.device), settings=settings, shard=args.shard or (0, 1),
                              engine=args.engine or "local", ray_address=args.ray_address, quiet=argtypes.no_bars(args))
    if args.json:
        argtypes.print_json({"inputs": run.inputs, "selected": run.selected, "computed": run.computed,
                             "reused": run.reused, "failed": run.failed, "rows": [r.columns() for r in run.rows],
                             "cameras": [c.columns() for c in run.cameras], "files": list(run.files)})
    else:
        _print_archive(run)
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    """``lensdist calibrate PATH [--json] [--out DIR] [--config TOML] [--quiet]``, or an archive (several inputs)."""
    if not args.paths and args.manifest is None:
        raise ValueError("the following arguments are required: path (or --manifest FILE)")
    if _archive_mode(args):
        return _cmd_archive(args)
    args.path = args.paths[0]
    argtypes.existing(args.path, "path")  # before the imports below: a missing input's error at once
    from lensdist_torch.core.outputs import check_output_dir

    if args.out:
        check_output_dir(args.out, "--out", {"path": args.path, "--config": args.config}, writes=["calibration.json"])
    from lensdist_torch.calibration.controllers.calibrate import calibrate_path
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.analyze import resolve_device

    settings = None if args.config is None else load_config(args.config)  # checked before any frame is read
    res = calibrate_path(args.path, config=None if settings is None else settings.calibration, settings=settings,
                         max_frames=args.max_frames, focal=args.focal, quiet=argtypes.no_bars(args),
                         device=resolve_device(args.device), method=args.method)
    from lensdist_torch.calibration.controllers.answer_file import answer_text, write_answer

    if args.out:
        write_answer(res, args.out)
    if args.json:
        print(answer_text(res))
    else:
        _print_calibration(res, args.out, debug=getattr(args, "debug", False))
        if args.out:
            print(f"written: {Path(args.out) / 'calibration.json'}")
    return 0


def _cmd_undistort(args: argparse.Namespace) -> int:
    """``lensdist undistort PATH (--k2 K2 --k4 K4 | --from CALIBRATION.json) --out DIR [--alpha A] [--overwrite]``."""
    argtypes.existing(args.path, "path")  # before the imports below: a missing input's error at once
    argtypes.existing(args.from_json, "calibration file")
    from lensdist_torch.workflows.analyze import resolve_device
    from lensdist_torch.workflows.undistort import undistort_path

    res = undistort_path(args.path, args.out, k2=args.k2, k4=args.k4, from_json=args.from_json,
                         max_frames=args.max_frames, quiet=argtypes.no_bars(args), device=resolve_device(args.device),
                         overwrite=args.overwrite, alpha=args.alpha)
    if args.json:
        print(json.dumps(res, indent=2, allow_nan=False))
        return 0
    view = "the input's scale" if res["alpha"] is None else f"alpha {res['alpha']:g}"
    lens = res.get("lens")
    if lens is None:
        applied = f"k2 = {res['k2']:.4e}, k4 = {res['k4']:.4e}"
    elif lens["kind"] == "radial":
        applied = (
            f"the homography model's lens: {len(lens['coefficients'])} radial terms about ({lens['centre'][0]:.1f}, "
            f"{lens['centre'][1]:.1f})"
        )
    else:
        applied = f"the multi-view path's camera: {len(lens['dist_coeffs'])} OpenCV coefficients"
    k = res["camera"]["new_camera_matrix"]
    print(f"{res['frames']} frames undistorted ({applied}, {view}) into {res['out_dir']} "
          f"as {' and '.join(f'{b}-bit' for b in res['bits'])} PNG, masks in {Path(res['out_dir']) / 'masks'} "
          f"({100 * res['valid_fraction']:.1f} % valid)")
    print(f"new camera matrix: fx = {k[0][0]:.2f}, fy = {k[1][1]:.2f}, cx = {k[0][2]:.2f}, cy = {k[1][2]:.2f} "
          f"(with the OpenCV camera and coefficients in {res['camera_file']})")
    return 0


_CALIBRATE = """\
Estimate the lens distortion of one camera (eq. 4's k2, k4, Delta_avg and Delta_max with 95 %
intervals, the class, OpenCV's camera matrix and coefficients) from a folder of frames or a
video (.mp4, .mov, .avi, .mkv, ...: PyAV from the 'video' extra, or OpenCV where PyAV is
missing). The frames must show one camera moving over a scene; every option is checked before
any frame is read. The text gives the answer, OpenCV's camera and the next command; --debug adds
eq. 4's k2, k4 and each path's numbers (always in the JSON).

Several inputs, a quoted glob or --manifest make an archive run (docs/guide/archive.md): each
input's answer in OUT/answers/NAME-KEY.json (what --json prints for it), one row per input in
OUT/answers.csv (answers.parquet where pyarrow imports), the pooled answer per camera in
OUT/cameras.csv; a rerun skips the inputs already answered, an input that fails is a row with
its reason, and the exit status is 0 once the run completed, failed rows or not."""

_UNDISTORT = """\
Correct every frame of a folder or video with eq. 4 (with --from an answer whose lens eq. 4's
k2_user, k4_user only approximate, that lens: the homography model's, `method` "planar", or the
multi-view path's OpenCV camera, "multiview"): FRAME.EXT becomes OUT/FRAME.png (16-bit PNG
for 16-bit input, else 8-bit), its validity mask OUT/masks/FRAME.png (0 where the sample lies
outside the frame or where eq. 4 folds over), and OUT/undistortion.json the coefficients used,
the output size and the new camera matrix (OpenCV's). --alpha chooses the view as OpenCV's
getOptimalNewCameraMatrix: 0 only valid pixels, 1 every source pixel kept; without it the
frames keep their scale (cv2.undistort's default). Refused, before anything is written: two
inputs with one name stem (frame_01.png and frame_01.jpg), coefficients that fold before the
frame's nearest edge, an OUT that is the input folder or would overwrite an input, and existing
files of the names it writes unless --overwrite."""


def add_calibrate_commands(subparsers, parents: list | None = None) -> None:
    """Register ``calibrate`` and ``undistort`` on the ``lensdist`` parser's subparsers (``parents``: --debug)."""
    p = subparsers.add_parser(
        "calibrate",
        help="the distortion of one camera from a folder of frames or a video",
        description=_CALIBRATE,
        epilog="examples:\n  lensdist calibrate frames/ --out calib/\n"
        "  lensdist calibrate dive.mp4 --json --method direct\n"
        "  lensdist calibrate 'archive/*.mp4' --out archive_answers/\n"
        "  lensdist calibrate --manifest dives.csv --out answers/ --shard 0/8",
        parents=parents or [],
        formatter_class=argtypes.Formatter,
    )
    p.add_argument("paths", nargs="*", metavar="path",
                   help="folder of frames (sorted by name) or a video file; several, or a quoted glob, for an archive")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--out", default=None, help="folder for calibration.json (an archive: answers/, answers.csv, "
                   "cameras.csv)")
    p.add_argument("--manifest", default=None, help="an archive's inputs: one path per line, or CSV with a path and "
                   "an optional camera column (relative paths from the manifest's folder)")
    p.add_argument("--shard", type=argtypes.shard, default=None,
                   help="I/N: this job's share of an archive's inputs, k %% N == I (array jobs; default: all)")
    p.add_argument("--engine", default=None, choices=("local", "ray"),
                   help="an archive's engine: local (one input after another) or ray (a task per input, "
                        'pip install "lensdist_torch[ray]")')
    p.add_argument("--ray-address", default=None, help="the Ray cluster for --engine ray (auto: this machine's; "
                   "default: a local Ray)")
    p.add_argument("--config", default=None, help="TOML config ([calibration], [multiview], [selfcal] "
                   "parallax; the defaults of docs/method.md when omitted)")
    p.add_argument("--max-frames", type=argtypes.positive_int, default=300, help="read at most this many frames")
    p.add_argument(
        "--focal",
        type=argtypes.positive_float,
        default=None,
        help="OpenCV focal length in px (default: the half diagonal)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars (none either where stderr is no terminal)")
    p.add_argument("--device", type=argtypes.device, default="cpu",
                   help="where registration and self-calibration run: cpu, cuda or cuda:N")
    p.add_argument("--method", default="auto", choices=("auto", "multiview", "direct"),
                   help="multiview: bundle adjustment on COLMAP's tracks (pycolmap), with the homography model on its "
                        "matches (a plane or a turning camera); direct: photometric pairs; auto: every path's lens "
                        "weighed on the same held-out frames")
    p.set_defaults(func=_cmd_calibrate)

    p = subparsers.add_parser(
        "undistort", help="correct every frame of a folder or video (PNG + validity masks + the new camera)",
        description=_UNDISTORT, parents=parents or [], formatter_class=argtypes.Formatter,
        epilog="examples:\n  lensdist undistort frames/ --from calib/calibration.json --out corrected/\n"
               "  lensdist undistort dive.mp4 --k2 2e-7 --k4 0 --alpha 1 --out corrected/")
    p.add_argument("path", help="folder of frames or a video file")
    p.add_argument(
        "--k2",
        type=argtypes.finite_float,
        default=None,
        help="eq. 4's k2 in the frames' pixels (0 if only --k4 is given)",
    )
    p.add_argument(
        "--k4",
        type=argtypes.finite_float,
        default=None,
        help="eq. 4's k4 in the frames' pixels (0 if only --k2 is given)",
    )
    p.add_argument("--from", dest="from_json", default=None,
                   help="the JSON of lensdist calibrate (--out or --json) or of lensdist analyze --json")
    p.add_argument("--out", required=True, help="output folder (frames as PNG, masks in out/masks, undistortion.json)")
    p.add_argument("--alpha", type=argtypes.float_in(0.0, 1.0), default=None,
                   help="0: only valid pixels, 1: every source pixel kept, between: interpolated (OpenCV's "
                        "getOptimalNewCameraMatrix); omitted: the frames keep their scale and centre")
    p.add_argument(
        "--json", action="store_true", help="print the result (with undistortion.json's content) as one JSON object"
    )
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing files of the names it writes in --out (never an input)")
    p.add_argument(
        "--max-frames", type=argtypes.positive_int, default=None, help="at most this many frames (default: all)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar (none either where stderr is no terminal)")
    p.add_argument(
        "--device", type=argtypes.device, default="cpu", help="where the frames are resampled: cpu, cuda or cuda:N"
    )
    p.set_defaults(func=_cmd_undistort)
