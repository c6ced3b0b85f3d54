"""Can the homography model's lens follow a real lens? Its family fitted to a calibration's own map.

    python benchmarks/bench_lens_family.py CALIBRATION.json CORNERS.json [--answer BENCH.json]
        [--out docs/results/bench_lens_family_gopro.json]

The homography model (docs/method.md, section 12) maps a pixel p to c + (p - c)(1 + a_1 r^2 +
... + a_n r^(2n)), r = |p - c| / R. Here its coefficients are fitted by linear least squares to
the calibration's own undistortion map (``undistortPoints(p, K, dist, P=K)`` over the pixels
where it inverts), with the distortion centre c held at one place per row: the calibration's
principal point, the frame centre, and (``--answer``: the JSON that
``bench_real_calibration.py --out`` wrote) where lensdist's homography model put it. Each
fitted map then undistorts every view's chessboard corners, one homography per view is fitted to
them and the RMS of the fit is reported, the check of ``bench_real_calibration.py``, in the
undistorted frame's pixels and (``image_*``) in the image's. The board is only used for that check.

What it separates: the error of the lens family (the map at the calibration's centre: the best
the family can do) from the error of the estimate's centre (the same family about the centre
the estimator found). The calibration's own figures come first, for scale.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from bench_real_calibration import homography_rms

from lensdist_torch.core import atomic_write_text
from lensdist_torch.geometry.distortion import distortion_center
from lensdist_torch.geometry.opencv_model import grid_points, opencv_ideal_points
from lensdist_torch.geometry.radial_lens import lens_ideal_points


def fit_family(points: torch.Tensor, ideal: torch.Tensor, centre, terms: int, size: tuple[int, int]) -> list[float]:
    """a_1 .. a_n of the lens about ``centre`` closest (least squares, px) to the map points -> ideal.

    The lens map is linear in its coefficients: the column of a_k is what the lens with a_k = 1
    alone (:func:`lens_ideal_points`) adds to the points.
    """
    unit = torch.eye(terms, dtype=points.dtype)
    columns = torch.stack(
        [(lens_ideal_points(points, unit[k], *size, centre=centre) - points).reshape(-1) for k in range(terms)], 1
    )
    return torch.linalg.lstsq(columns, (ideal - points).reshape(-1, 1)).solution[:, 0].tolist()


def summary(rms: list[float], image: list[float] | None = None) -> dict:
    """Median, worst and share within 1 px of per-view RMS (undistorted px), and with ``image`` the same in the
    image's px."""
    out = {}
    for prefix, values in (("", rms), ("image_", image)):
        if values is not None:
            r = np.asarray(values, dtype=np.float64)
            out.update({f"{prefix}median_px": float(np.median(r)), f"{prefix}worst_px": float(r.max()),
                        f"{prefix}within_1px": float((r <= 1).mean())})
    return out


def checked(corners: dict, **lens) -> dict:
    """:func:`summary` of the corner check in both units, ``lens`` as :func:`homography_rms` takes it."""
    return summary(*(homography_rms(corners=corners, image_px=px, **lens) for px in (False, True)))


def said(s: dict) -> str:
    return (
        f"corners median {s['median_px']:.3f} px, worst {s['worst_px']:.2f} px, "
        f"within 1 px {100 * s['within_1px']:.0f} % of views; "
        f"in the image's px {s['image_median_px']:.3f}, {s['image_worst_px']:.2f}, {100 * s['image_within_1px']:.0f} %"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibration")
    ap.add_argument("corners")
    ap.add_argument("--answer", help="bench_real_calibration.py's JSON: its homography model's centre is one more row")
    ap.add_argument("--terms", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--step", type=int, default=8, help="the map's grid step in pixels")
    ap.add_argument("--out")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cal = json.loads(Path(args.calibration).read_text())["primary"]
    corners = json.loads(Path(args.corners).read_text())
    w, h = cal["image_size"]
    k, dist = torch.tensor(cal["K"], dtype=torch.float64), torch.tensor(cal["dist"], dtype=torch.float64)
    p = grid_points(h, w, args.step)
    ideal, ok = opencv_ideal_points(p, k, dist)
    p, ideal = p[ok], ideal[ok]
    centres = {"the calibration's principal point": [float(k[0, 2]), float(k[1, 2])],
               "the frame centre": list(distortion_center(h, w))}
    if args.answer:
        planar = json.loads(Path(args.answer).read_text())["answer"]["planar"]
        centres[f"lensdist's ({planar['model']})"] = planar["centre"]
    truth_a, truth_c = (
        [0.3, 0.1, 0.05],
        [w / 2 + 7.0, h / 2 - 5.0],
    )  # self-check: the family's own map is fitted exactly
    back = fit_family(p, lens_ideal_points(p, truth_a, h, w, centre=truth_c), truth_c, 3, (h, w))
    if max(abs(x - y) for x, y in zip(back, truth_a)) > 1e-9:
        raise SystemExit(f"self-check failed: {truth_a} fitted as {back}")
    report = {"calibration": checked(corners, k=cal["K"], dist=cal["dist"]), "rows": []}
    print(f"the calibration's own model: {said(report['calibration'])}")
    for where, centre in centres.items():
        for n in args.terms:
            a = fit_family(p, ideal, centre, n, (h, w))
            fitted = lens_ideal_points(p, a, h, w, centre=centre)
            map_rms = float((fitted - ideal).norm(dim=-1).pow(2).mean().sqrt())
            s = checked(
                corners,
                k=None,
                dist=None,
                ideal=lambda x, a=a, centre=centre: lens_ideal_points(x, a, h, w, centre=centre),
            )
            report["rows"].append(
                {"centre": where, "centre_px": centre, "terms": n, "coefficients": a, "map_rms_px": map_rms, **s}
            )
            print(f"{n} terms about {where} ({centre[0]:.1f}, {centre[1]:.1f}): map RMS {map_rms:.2f} px; {said(s)}")
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
