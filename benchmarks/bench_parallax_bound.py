"""What one pair of a non-planar scene can tell, whatever the estimator (docs/method.md, section 10).

For the realistic protocol's test pairs (distorted ones) the exact correspondences are known: a
pixel p of I2 sees the scene point of I1's pixel distort(V(A undistort(p))), A the centred
motion and V where camera 1 sees the scene points camera 2 sees (the pair's relief,
``data.relief.homography_view_points``, as the renderer; docs/method.md, section 7). This fits
two models to those exact points (every 8th pixel, no image, no noise) by Levenberg-Marquardt in
float64 and reports Delta_avg's error and class:

- planar: (k2, k4) and a homography, the self-calibration's model;
- relief: the same plus n x n Gaussian bumps of relief along the true translation (the plane +
  parallax model of ``SelfCalConfig.parallax``), or with ``--direction epipole`` along each
  point's true line to the epipole (``SelfCalConfig.parallax_epipole``: the translation plus
  the change of height's radial part; ``--only-relief`` fits that model alone).

The planar model's errors here are a bound: no planar estimator does better on these pairs. A
pair "cannot be told by one pair" when the planar model, on its exact points, gives the wrong
class: ``cannot_tell_share`` is their share, what the relief condition's "cannot tell" is
compared with (``--config configs/realistic_relief.toml``).

    python benchmarks/bench_parallax_bound.py --config configs/realistic_relief.toml --n 400 \
        --out docs/results/bench_parallax_bound.json
    python benchmarks/bench_parallax_bound.py --n 400 --direction epipole --only-relief \
        --out docs/results/bench_parallax_bound_epipole.json
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from lensdist_torch.config import load_config
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.data.realism import height_field
from lensdist_torch.data.relief import homography_view_points
from lensdist_torch.data.synthesis import draw_pairs
from lensdist_torch.geometry.distortion import (
    N_CLASSES,
    delta_avg,
    delta_top,
    distort_points,
    distortion_center,
    distortion_class,
    estimated_class,
    undistort_points,
)
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.homography import apply_homography
from lensdist_torch.selfcal.model import relief_basis


def correspondences(cfg, params, i: int, step: int):
    """I2's pixels (N, 2) and their exact matches in I1 (N, 2), both inside the frame, the centre and the centred
    motion."""
    h, w = cfg.image.size
    x0, y0 = distortion_center(h, w)
    c = torch.tensor([x0, y0], dtype=torch.float64)
    ys, xs = torch.meshgrid(
        torch.arange(0, h, step, dtype=torch.float64), torch.arange(0, w, step, dtype=torch.float64), indexing="ij"
    )
    p2 = torch.stack([xs.flatten(), ys.flatten()], -1)
    k2, k4 = params.k2[i : i + 1], params.k4[i : i + 1]
    u = undistort_points(p2[None], k2, k4, (x0, y0))[0] - c  # I2's ideal points, centred
    to_c = torch.eye(3, dtype=torch.float64)
    to_c[:2, 2] = c
    a = torch.linalg.inv(to_c) @ params.M[i] @ to_c  # the centred motion, as the renderer uses it
    qx, qy = homography_view_points(a, u[:, 0], u[:, 1], height_field(params.realism, i, h, w))
    p1 = distort_points(torch.stack([qx, qy], -1)[None] + c, k2, k4, (x0, y0))[0]
    inside = (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    return p2[inside], p1[inside], c, a


def fit(src, dst, c, r, basis, direction, iterations: int = 25, epipole=None):
    """LM fit of [a, b, 8 homography entries, relief coefficients] mapping src -> dst (pixels).

    The relief moves I2's ideal points along ``direction`` (2,), or, with ``epipole`` (t, s) of
    the true centred motion (normalised translation, scale), I1's along t + (s - 1) x per unit |t|.
    """
    nb = 0 if basis is None else basis.shape[1]

    def model(th):
        k2, k4 = (th[0] / r**2).reshape(1), (th[1] / r**4).reshape(1)
        hm = torch.cat([th[2:10], torch.ones(1, dtype=th.dtype)]).reshape(3, 3)
        u = (undistort_points(src[None], k2, k4, tuple(c.tolist()))[0] - c) / r
        if nb and epipole is None:
            u = u + (basis @ th[10:])[:, None] * direction[None]
        x = apply_homography(hm[None], u)[0]
        if nb and epipole is not None:
            t, s = epipole
            x = x + (basis @ th[10:])[:, None] * (t[None] + (s - 1) * x) / t.norm().clamp_min(1e-12)
        return distort_points(x[None] * r + c, k2, k4, tuple(c.tolist()))[0]

    th = torch.zeros(10 + nb, dtype=torch.float64)
    th[2], th[6] = 1.0, 1.0
    th[4], th[7] = ((dst - src).mean(0) / r).unbind()
    cost, lam = float((model(th) - dst).pow(2).sum()), 1e-3
    for _ in range(iterations):
        res = (model(th) - dst).flatten()
        jac = torch.func.jacfwd(lambda t: model(t).flatten())(th)
        jtj = jac.T @ jac
        cand = th - torch.linalg.solve(jtj + lam * torch.diag(torch.diag(jtj).clamp_min(1e-12)), jac.T @ res)
        new = float((model(cand) - dst).pow(2).sum())
        if new < cost:
            done = cost - new < 1e-12 * cost
            th, cost, lam = cand, new, lam / 3
            if done:
                break
        else:
            lam *= 4
    return th


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/realistic_relief.toml")
    ap.add_argument("--n", type=int, default=48, help="test pairs (the first n, all distorted)")
    ap.add_argument("--step", type=int, default=8, help="every step-th pixel of I2")
    ap.add_argument("--bumps", type=int, default=5, help="the relief model's n x n bumps")
    ap.add_argument("--width", type=float, default=0.3, help="their sigma, half-diagonals")
    ap.add_argument("--direction", choices=("translation", "epipole"), default="translation",
                    help="the relief model's: along the true translation, or each point's line to the epipole")
    ap.add_argument("--only-relief", action="store_true", help="fit the relief model alone (no planar bound)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None, help="also write the JSON here")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg = load_config(a.config)
    h, w = cfg.image.size
    r = half_diagonal(h, w)
    params = draw_pairs(cfg, "test", list(range(a.n)), len(cfg.protocol.scenes))
    true = delta_avg(params.k2, params.k4, h, w).double()
    t0 = time.perf_counter()
    est = {"relief": []} if a.only_relief else {"planar": [], "relief": []}
    for i in range(a.n):
        src, dst, c, motion = correspondences(cfg, params, i, a.step)
        t = torch.stack([params.motion[i, 1], params.motion[i, 0]])
        direction = t / t.norm().clamp_min(1e-12)
        un = (src - c) / r
        basis = relief_basis(un[None, :, 0], un[None, :, 1], n=a.bumps, width=a.width, h0=h, w0=w)[0].T.double()
        epipole = None
        if a.direction == "epipole":
            m = motion / motion[2, 2]
            epipole = (m[:2, 2] / r, torch.linalg.det(m[:2, :2]).abs().sqrt())
        for name, b in (("planar", None), ("relief", basis))[1 if a.only_relief else 0:]:
            th = fit(src, dst, c, r, b, direction, epipole=epipole)
            ok = bool(torch.isfinite(th).all() and th[:2].abs().max() <= 2)
            est[name].append(float(delta_avg(th[0:1] / r**2, th[1:2] / r**4, h, w)) if ok else float("nan"))
    out = {
        "config": a.config,
        "pairs": a.n,
        "step": a.step,
        "bumps": a.bumps,
        "width": a.width,
        "direction": a.direction,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    truth = distortion_class(true, delta_top("delta_avg", cfg), N_CLASSES)
    for name, values in est.items():
        e = torch.tensor(values, dtype=torch.float64)
        ok = torch.isfinite(e)
        err = (e - true)[ok]
        right = estimated_class(e[ok], e[ok], metric="delta_avg", config=cfg) == truth[ok]
        out[name] = {"right": float(right.double().mean()), "over_1px": int((err.abs() > 1).sum()),
                     "median_abs_px": float(err.abs().median()), "rmse_px": float(err.pow(2).mean().sqrt()),
                     "diverged": int((~ok).sum())}
    if a.only_relief:  # no planar bound without the planar fits
        out["per_pair"] = {"index": list(range(a.n)), "relief_px": [round(v, 4) for v in est["relief"]],
                           "true_px": [round(float(v), 4) for v in true]}
        return _write(out, a.out)
    wrong = (
        estimated_class(torch.tensor(est["planar"]), torch.tensor(est["planar"]), metric="delta_avg", config=cfg)
        != truth
    )
    out["cannot_tell_share"] = float(wrong.double().mean())  # planar model wrong on exact points (NaN counts)
    out["per_pair"] = {"index": list(range(a.n)), "relief": [round(float(v), 5) for v in params.realism.relief[:, 0]],
                       "planar_px": [round(v, 4) for v in est["planar"]], "true_px": [round(float(v), 4) for v in true]}
    _write(out, a.out)


def _write(out: dict, path) -> None:
    text = json.dumps(out, indent=1)
    print(text)
    if path:
        atomic_write_text(path, text + "\n")


if __name__ == "__main__":
    main()
