"""Real footage with a published calibration: lensdist calibrate against the truth and COLMAP, one table.

    python benchmarks/bench_real_calibration.py FRAMES_DIR CALIBRATION.json [--corners CORNERS.json]
        [--out docs/results/bench_real_calibration.json] [--answer ANSWER.json]

FRAMES_DIR: the frames of one camera; CALIBRATION.json: {"primary": {"K": 3 x 3, "dist": OpenCV's
coefficients}} (its chessboard calibration). What runs is the user's path, ``calibrate_path``
(= ``lensdist calibrate``, method auto: the multi-view and the direct answers combined; the
multi-view answer from ``multiview.reconstructions`` mappings, each listed). Beside it:
every COLMAP camera model fitted by bundle adjustment on the same tracks (what COLMAP gives with
that model fixed), the homography model (``multiview.planar_*``: one lens and one homography per
pair on the same matches) and the direct path alone, each over the pixels where the calibration
inverts (the truth's; the direct path, and an answer saved before the models carried their
cameras, over their own). ``--answer`` checks a saved answer (the JSON of ``lensdist calibrate
FRAMES --json``) instead of running it again. The truth is Delta = |p - undistortPoints(p, K,
dist, P=K)| run to convergence, over the pixels where the calibration's model inverts.

With ``--corners`` (per view the chessboard's inner corners, {"image_points": {name: [[x, y], ...]},
"object_points_xy": [[X, Y], ...]}), the check that does not trust any Delta: each answer's OpenCV
camera undistorts every view's corners, one homography per view is fitted to them, and the RMS of
the fit is reported, in the undistorted frame's pixels and in the image's (``homography_rms_image_px``: the unit
of the chessboard calibration's own 0.56 px RMS); the homography
model's own lens map is checked beside its OpenCV export, with its Delta_avg over the pixels
where the calibration's model inverts (its own covers every pixel). How well the board knows the
truth: the chessboard calibration again on the corners, with OpenCV's 5 coefficients and its
rational model (``truth_models``), and every lens's Delta_avg over the pixels some view's board
covers (``on_boards_px``; beyond them the calibration's Delta is an extrapolation). The board is
never shown to the estimators.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from lensdist_torch.calibration.controllers.answer_lens import opencv_to_use
from lensdist_torch.calibration.planar_features import delta_avg_where
from lensdist_torch.config import CalibrationConfig, LensdistConfig
from lensdist_torch.core import atomic_write_text
from lensdist_torch.geometry.opencv_model import (
    grid_points,
    map_grid_step,
    opencv_camera_from_map,
    opencv_delta,
    opencv_ideal_points,
)
from lensdist_torch.geometry.radial_lens import lens_ideal_points


def homography_rms(k, dist, corners: dict, ideal=None, image_px: bool = False) -> list[float]:
    """Per view: RMS (px) of one homography fitted to the corners undistorted by (K, dist), or by ``ideal``.

    ``ideal``: a function from (N, 2) float64 pixels to their ideal pixels (a lens map), in place of (K, dist).
    ``image_px``: the RMS in the image's pixels, the unit of a calibration's reprojection error (the
    chessboard calibration's 0.56 px): each corner's misfit taken back through the map's local
    Jacobian (central differences, 0.01 px), the homography refined to the least squares there
    (Gauss-Newton from the undistorted fit). Without it, in the undistorted frame's pixels, where
    a strong barrel lens magnifies the edges' misfits.
    """
    import cv2

    obj = np.asarray(corners["object_points_xy"], dtype=np.float64)
    board = torch.cat([torch.from_numpy(obj), torch.ones(len(obj), 1, dtype=torch.float64)], 1)
    if ideal is None:
        kt, dt = torch.tensor(k, dtype=torch.float64), torch.tensor(dist, dtype=torch.float64)
        ideal = lambda p: opencv_ideal_points(p, kt, dt)  # noqa: E731
    else:
        ideal = (lambda f: lambda p: (f(p), torch.ones(len(p), dtype=torch.bool)))(ideal)
    out = []
    for pts in corners["image_points"].values():
        p = torch.tensor(pts, dtype=torch.float64).reshape(-1, 2)
        x, ok = ideal(p)
        if not bool(ok.all()):
            out.append(float("inf"))
            continue
        hm, _ = cv2.findHomography(obj, x.numpy(), 0)
        hv = torch.from_numpy(hm / hm[2, 2]).reshape(-1)[:8]
        back = torch.eye(2, dtype=torch.float64).expand(len(p), 2, 2)
        if image_px:  # the map's Jacobian at each corner, inverted: an ideal misfit in the image's pixels
            e = 0.01 * torch.eye(2, dtype=torch.float64)
            jac = torch.stack([(ideal(p + e[i])[0] - ideal(p - e[i])[0]) / 0.02 for i in range(2)], -1)
            back = torch.linalg.inv(jac)

        def residual(hv: torch.Tensor, back=back, x=x) -> torch.Tensor:
            q = board @ torch.cat([hv, hv.new_ones(1)]).reshape(3, 3).T
            return (back @ (q[:, :2] / q[:, 2:] - x)[..., None]).reshape(-1)

        for _ in range(10 if image_px else 0):
            hv = hv - torch.linalg.lstsq(torch.func.jacfwd(residual)(hv), residual(hv)[:, None]).solution[:, 0]
        out.append(float(residual(hv).reshape(-1, 2).pow(2).sum(1).mean().sqrt()))
    return out


def _coverage(res: dict) -> LensdistConfig:
    """The settings at the answer's own coverage (its JSON's ``confidence``)."""
    return LensdistConfig(calibration=CalibrationConfig(confidence=res.get("confidence", 0.95)))


def truth_footprint(truth_k, truth_dist, size: tuple[int, int], step: int) -> torch.Tensor:
    """The ``step``-spaced grid pixels (N, 2) where the truth's model inverts."""
    p = grid_points(*size, step)
    return p[
        opencv_ideal_points(
            p, torch.tensor(truth_k, dtype=torch.float64), torch.tensor(truth_dist, dtype=torch.float64)
        )[1]
    ]


def on_footprint(k, dist, points: torch.Tensor) -> float:
    """Delta_avg (px) of (k, dist) over ``points`` (the truth's footprint) where it inverts too."""
    ideal, ok = opencv_ideal_points(
        points, torch.tensor(k, dtype=torch.float64), torch.tensor(dist, dtype=torch.float64)
    )
    return float((ideal - points).norm(dim=-1)[ok].mean()) if bool(ok.any()) else float("nan")


def inside_boards(points: torch.Tensor, corners: dict) -> torch.Tensor:
    """(N,) bool: the ``points`` (N, 2) inside the convex hull of some view's chessboard corners."""
    import cv2

    p, inside = points.numpy(), np.zeros(len(points), dtype=bool)
    for view in corners["image_points"].values():
        hull = cv2.convexHull(np.asarray(view, dtype=np.float32)).reshape(-1, 2).astype(np.float64)
        edge, to_p = np.roll(hull, -1, axis=0) - hull, p[:, None, :] - hull[None]
        cross = edge[None, :, 0] * to_p[..., 1] - edge[None, :, 1] * to_p[..., 0]
        inside |= (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
    return torch.from_numpy(inside)


def truth_models(corners: dict, size: tuple[int, int], points: dict[str, torch.Tensor]) -> dict:
    """The chessboard calibration again, with OpenCV's 5 coefficients and its rational model, on the corners.

    How well the board itself knows the truth: per model its corners' RMS (px) and Delta_avg over
    each set of ``points`` (the calibration's footprint, the pixels the boards cover).
    """
    import cv2

    obj = np.array([[x, y, 0.0] for x, y in corners["object_points_xy"]], dtype=np.float32)
    views = [np.asarray(v, dtype=np.float32) for v in corners["image_points"].values()]
    out = {}
    for name, flags, n in (("opencv, 5 coefficients", 0, 5), ("opencv, rational", cv2.CALIB_RATIONAL_MODEL, 8)):
        rms, k, dist, _, _ = cv2.calibrateCamera([obj] * len(views), views, (size[1], size[0]), None, None,
                                                 flags=flags)
        k, dist = k.tolist(), dist.ravel()[:n].tolist()
        out[name] = {"rms_px": rms, "camera_matrix": k, "dist_coeffs": dist,
                     **{f"delta_avg_{where}_px": on_footprint(k, dist, pts) for where, pts in points.items()}}
    return out


def main() -> None:
    from lensdist_torch.calibration import calibrate_path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames")
    ap.add_argument("calibration")
    ap.add_argument("--corners", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--answer",
        default=None,
        help="the JSON of `lensdist calibrate FRAMES --json` on these frames "
        "(or this benchmark's report), checked instead of running it again",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cal = json.loads(Path(args.calibration).read_text())["primary"]
    t0 = time.perf_counter()
    res = json.loads(Path(args.answer).read_text()) if args.answer else calibrate_path(args.frames, method="auto")
    res = res["answer"] if "answer" in res and "image_size" not in res else res  # this benchmark's own report, too
    seconds = float("nan") if args.answer else time.perf_counter() - t0
    h, w = res["image_size"]
    truth = opencv_delta(torch.tensor(cal["K"]), torch.tensor(cal["dist"]), h, w, step=2)
    pl = res.get("planar") or {}
    footprint = {step: truth_footprint(cal["K"], cal["dist"], (h, w), step) for step in (2, 4)}
    on_truth = None  # the homography model where the calibration inverts (its interval from its replicates, same rules)
    if pl.get("coefficients"):
        on_truth = delta_avg_where(pl, footprint[2], h, w, settings=_coverage(res))
    own = f"{res['delta_avg_user_px']:.2f} px over its own footprint"
    if res.get("method") == "planar" and on_truth is not None:
        rows = [("lensdist calibrate (answer)", "planar", on_truth[0], on_truth[1], res["class"], own)]
    else:
        rows = [
            (
                "lensdist calibrate (answer)",
                res.get("method"),
                res["delta_avg_user_px"],
                res["delta_avg_user_interval"],
                res["class"],
                (res.get("reason") or "") + " (over its own footprint)",
            )
        ]
    mv = res.get("multiview") or {}
    for model, v in (mv.get("models") or {}).items():
        if (
            "camera_matrix" in v
        ):  # its Delta where the calibration inverts, as the truth's (an answer saved before: its own footprint)
            value = on_footprint(v["camera_matrix"], v["dist_coeffs"], footprint[2])
            note = f"reprojection {v['reprojection_px']:.3f} px; {v['delta_avg_px']:.2f} px where it inverts"
        else:
            value, note = (
                v["delta_avg_px"],
                f"reprojection {v['reprojection_px']:.3f} px; where it inverts, not the truth's pixels",
            )
        if "weight" in v:  # the held-out evidence and the posterior (answers since the models were weighed)
            std = v["delta_avg_std_px"]  # None (JSON's inf): the tracks do not determine it, or it did not converge
            jack = "" if v.get("jackknife_std_px") is None else f", jackknife {v['jackknife_std_px']:.3f} px"
            note += (f"; weight {v['weight']:.3f}, posterior std "
                     f"{'none' if std is None else format(std, '.3f') + ' px'}{jack}, "
                     f"held-out RMS {v['heldout_rms_px']:.3f} px, elpd {v['elpd']:.1f}")
        if "path" in v:  # another path's lens held on the tracks (its own interval, no BIC)
            rows.append((f"lensdist, the {model} path's lens held on the tracks", "held", value, None, None, note))
        else:
            rows.append((f"COLMAP, {model} fixed (same tracks)", f"BIC {v['bic']:.0f}", value, None, None, note))
    if "terms" in pl:
        value, iv = on_truth if on_truth is not None else (pl["delta_avg_user_px"], pl["delta_avg_user_interval"])
        rows.append(("lensdist, homography model", f"{pl['terms']} terms, {pl['pairs']} pairs", value, iv, pl["class"],
                     pl.get("reason") or f"{pl['delta_avg_user_px']:.2f} px over its own footprint"))
    d = res["direct"]
    rows.append(
        (
            "lensdist, direct path alone",
            "pairs",
            d["delta_avg_user_px"],
            d["delta_avg_user_interval"],
            d["class"],
            d.get("reason"),
        )
    )
    report = {"frames": args.frames, "seconds": seconds, "truth": truth, "answer": res, "rows": rows,
              "multiview_reason": mv.get("reason")}
    print(
        f"{res['frames']} frames of {w} x {h}, {seconds:.0f} s; truth Delta_avg {truth['delta_avg_px']:.2f} px "
        f"over the {100 * truth['invertible_fraction']:.1f} % of pixels where the calibration's model inverts"
    )
    if "model" not in mv:
        print(f"multi-view path: no answer ({mv.get('reason')})")
    else:
        print(f"multi-view path: {mv['registered']} of {res['frames']} frames registered, {mv['points3D']} tracks, "
              f"reprojection RMS {mv['reprojection_px']:.2f} px, model {mv['model']}, {mv['delta_avg_user_px']:.2f} px "
              f"[{mv['delta_avg_user_interval'][0]:.2f}, {mv['delta_avg_user_interval'][1]:.2f}], "
              f"class {mv['class'] or 'cannot tell (' + str(mv['reason']) + ')'}")
    for run in mv.get("reconstructions") or []:  # one per mapping seed (multiview.reconstructions)
        if "failed" in run:
            print(f"  reconstruction, seed {run['seed']}: failed ({run['failed']})")
            continue
        iv = run["delta_avg_user_interval"]
        print(f"  reconstruction, seed {run['seed']}: {run['registered']} registered, {run['points3D']} tracks, "
              f"{run['model']} {run['delta_avg_user_px']:.2f} px [{iv[0]:.2f}, {iv[1]:.2f}], covers "
              f"{'yes' if iv[0] <= truth['delta_avg_px'] <= iv[1] else 'no'}, class {run['class'] or 'cannot tell'}")
    print("| estimate | detail | Delta_avg (px) | % of truth | 95 % interval | covers | class | note |")
    print("|---|---|---|---|---|---|---|---|")
    for name, detail, value, iv, cls, note in rows:
        pct = "-" if value is None else f"{100 * value / truth['delta_avg_px']:.0f} %"
        cover = "-" if iv is None or iv[0] is None else ("yes" if iv[0] <= truth["delta_avg_px"] <= iv[1] else "no")
        ivs = "-" if iv is None or iv[0] is None else f"[{iv[0]:.2f}, {iv[1]:.2f}]"
        vs = "-" if value is None else f"{value:.2f}"
        print(f"| {name} | {detail} | {vs} | {pct} | {ivs} | {cover} | {cls or 'cannot tell'} | {note or ''} |")
    if args.corners:
        corners = json.loads(Path(args.corners).read_text())
        checks = {"chessboard calibration (truth)": (cal["K"], cal["dist"])}
        cam = opencv_to_use(res)  # the camera the answer's text tells its user to paste
        if cam is not None:
            checks["lensdist answer"] = (cam["camera_matrix"], cam["dist_coeffs"])
            report["answer_on_truth_footprint_px"] = on_footprint(
                cam["camera_matrix"], cam["dist_coeffs"], footprint[4]
            )
            print(f"the answer's Delta_avg over the pixels where the calibration inverts too: "
                  f"{report['answer_on_truth_footprint_px']:.2f} px")
        if "model" in mv:
            checks["multi-view estimate"] = (mv["camera_matrix"], mv["dist_coeffs"])
            report["multiview_on_truth_footprint_px"] = on_footprint(
                mv["camera_matrix"], mv["dist_coeffs"], footprint[4]
            )
            print(f"the multi-view estimate's Delta_avg there: {report['multiview_on_truth_footprint_px']:.2f} px")
        planar = res.get("planar") or {}
        maps = {}
        if planar.get("coefficients"):  # the homography model's own lens map, beside its OpenCV export
            a, centre = planar["coefficients"], planar["centre"]
            maps["homography model (its lens map)"] = lambda p: lens_ideal_points(p, a, h, w, centre=centre)
            value, iv = on_truth
            report["planar_on_truth_footprint"] = {"delta_avg_px": value, "interval": iv,
                                                   "covers": iv[0] <= truth["delta_avg_px"] <= iv[1]}
            for name, model in (
                ("opencv", "standard"),
                ("opencv_rational", "rational"),
            ):  # its exports, about its centre
                cam = planar.get(name)
                if cam is None:  # an answer saved before the block carried them: the library's same export of its map
                    fit = opencv_camera_from_map(maps["homography model (its lens map)"], h, w, model=model,
                                                 step=map_grid_step(h, w), centre=centre)
                    cam = {"camera_matrix": fit.camera_matrix.tolist(), "dist_coeffs": fit.dist_coeffs.tolist()}
                checks[f"homography model ({name})"] = (cam["camera_matrix"], cam["dist_coeffs"])
            print(
                f"the homography model: {planar['model']} about "
                f"({planar['centre'][0]:.1f}, {planar['centre'][1]:.1f}), "
                f"the calibration's principal point ({cal['K'][0][2]:.1f}, {cal['K'][1][2]:.1f}); "
                f"its bending half-width {planar['bending_halfwidth_px']:.2f} px "
                f"over the {100 * planar['matched_fraction']:.0f} % of the frame its matches reach"
            )
            print(
                f"the homography model's Delta_avg over the pixels where the calibration inverts: {value:.2f} px "
                f"({100 * value / truth['delta_avg_px']:.1f} % of the truth) [{iv[0]:.2f}, {iv[1]:.2f}], covers "
                f"{'yes' if report['planar_on_truth_footprint']['covers'] else 'no'} "
                f"({planar['delta_avg_user_px']:.2f} px over its own footprint, every pixel)"
            )
        boards = footprint[4][inside_boards(footprint[4], corners)]
        report["boards_share"] = len(boards) / len(footprint[4])
        report["truth_models"] = truth_models(corners, (h, w), {"footprint": footprint[4], "boards": boards})
        report["on_boards_px"] = {"chessboard calibration (truth)": on_footprint(cal["K"], cal["dist"], boards)} | {
            n: on_footprint(k, dist, boards) for n, (k, dist) in checks.items()}
        if on_truth is not None:
            value, iv = delta_avg_where(pl, boards, h, w, settings=_coverage(res))
            report["planar_on_boards"] = {"delta_avg_px": value, "interval": iv}
        print(f"over the pixels the boards cover ({100 * report['boards_share']:.0f} % of the calibration's "
              "footprint):")
        for name, t in report["truth_models"].items():
            print(f"  the chessboard again, {name}: corners RMS {t['rms_px']:.3f} px, Delta_avg "
                  f"{t['delta_avg_boards_px']:.2f} px there ({t['delta_avg_footprint_px']:.2f} over the footprint)")
        for name, value in report["on_boards_px"].items():
            print(f"  {name}: {value:.2f} px")
        if "planar_on_boards" in report:
            value, iv = report["planar_on_boards"]["delta_avg_px"], report["planar_on_boards"]["interval"]
            print(f"  the homography model's lens map: {value:.2f} px [{iv[0]:.2f}, {iv[1]:.2f}]")
        report["homography_rms"], report["homography_rms_image_px"] = {}, {}
        for name, (k, dist, ideal) in (
            {n: (*v, None) for n, v in checks.items()} | {n: (None, None, f) for n, f in maps.items()}
        ).items():
            for key, unit, image_px in (
                ("homography_rms", "undistorted px", False),
                ("homography_rms_image_px", "image px", True),
            ):
                rms = homography_rms(k, dist, corners, ideal, image_px=image_px)
                report[key][name] = rms
                finite = [v for v in rms if np.isfinite(v)]
                print(f"corners on one homography per view ({unit}), {name}: median {np.median(finite):.2f} px, worst "
                      f"{max(rms):.2f} px, within 1 px {100 * np.mean(np.array(rms) <= 1):.0f} % of {len(rms)} views")
    if args.out:
        strict = json.loads(json.dumps(report, default=str).replace("NaN", "null").replace("Infinity", "null"))
        atomic_write_text(Path(args.out), json.dumps(strict, indent=1, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
