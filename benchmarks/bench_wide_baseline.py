"""Success, accuracy and cost of the registration fallback for far-apart pairs (docs/method.md, section 10).

The grid: planar pairs of an embedded scene at the analysis size (320 x 424), img1 the centre of the
512 x 512 scene and img2 = img1 seen through a known homography about the image centre (rendered with
``kornia.geometry.warp_perspective``, zeros outside the scene), for every rotation x zoom x
perspective (default 5 x 4 x 2 = 40 pairs). Printed:

* per cell, whether ``estimate_homography`` alone and ``estimate_homography_robust`` register the
  pair, and the corner error of the latter (mean distance of img1's corners mapped by the estimate
  and by the truth, px);
* the success rates, the corner errors (median, 90th percentile, max) of the registered pairs;
* the cost: the fast path per pair (the whole grid as one batch) against the fallback per pair
  (SIFT + matching + RANSAC, then the refinement), in process time (CPU seconds: on a shared
  machine the wall clock also counts other people's work) and wall clock;
* with ``--keypoints 500 1000 2000``, the same for each cap on the keypoints (``wide_baseline.MAX_KEYPOINTS``
  set for the run).

Usage: python benchmarks/bench_wide_baseline.py [--scene gravel] [--keypoints 2000] [--threads 1]
"""

from __future__ import annotations

import argparse
import math
import time

import torch
from kornia.geometry import warp_perspective

from lensdist_torch.core import load_scene
from lensdist_torch.geometry import corner_error
from lensdist_torch.registration import estimate_homography, wide_baseline
from lensdist_torch.registration.wide_baseline import estimate_homography_robust, feature_homography

H0, W0 = 320, 424


def _shift(x: float, y: float) -> torch.Tensor:
    return torch.tensor([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]], dtype=torch.float64)


def true_h(deg: float, scale: float, persp: tuple[float, float]) -> torch.Tensor:
    """img1 -> img2: rotation, zoom and perspective row (h31, h32) about the image centre."""
    c, s = scale * math.cos(math.radians(deg)), scale * math.sin(math.radians(deg))
    a = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [persp[0], persp[1], 1.0]], dtype=torch.float64)
    h = _shift((W0 - 1) / 2, (H0 - 1) / 2) @ a @ _shift(-(W0 - 1) / 2, -(H0 - 1) / 2)
    return h / h[2, 2]


def render(hs: torch.Tensor, scene: str) -> tuple[torch.Tensor, torch.Tensor]:
    """img1 the scene's centre, img2(H p) = img1(p), as (N, 1, 320, 424) float32."""
    s = load_scene(scene).double()
    c = (s.shape[-1] - 1) / 2
    a1 = _shift(c, c) @ _shift(-(W0 - 1) / 2, -(H0 - 1) / 2)  # img1 pixel -> scene pixel
    warp = torch.stack([torch.linalg.inv(a1 @ torch.linalg.inv(h)) for h in hs])
    img1 = warp_perspective(s, torch.linalg.inv(a1)[None], (H0, W0), align_corners=True).float()
    img2 = warp_perspective(s.expand(len(hs), -1, -1, -1), warp, (H0, W0), align_corners=True).float()
    return img1.expand(len(hs), -1, -1, -1).contiguous(), img2


def _clocks() -> tuple[float, float]:
    return time.process_time(), time.perf_counter()


def run(args: argparse.Namespace, keypoints: int) -> None:
    cells = [(d, s, p) for p in args.perspectives for s in args.scales for d in args.rotations]
    persp = [(p + 0.0, -p / 2 + 0.0) for _, _, p in cells]  # + 0.0: no -0
    hs = torch.stack([true_h(d, s, q) for (d, s, _), q in zip(cells, persp)])
    img1, img2 = render(hs, args.scene)
    wide_baseline.MAX_KEYPOINTS = keypoints  # the cap under test, a constant of the method
    estimate_homography(img1[:2], img2[:2])  # warm-up
    feature_homography(img1[:1], img2[:1])

    c0, w0 = _clocks()
    _, fast = estimate_homography(img1, img2)
    c1, w1 = _clocks()
    t_feat = [0.0, 0.0]
    t_all = [0.0, 0.0]
    hr, conv = [], []
    for i in range(len(cells)):  # one pair at a time, to time the fallback per pair
        a, b = img1[i : i + 1], img2[i : i + 1]
        s0 = _clocks()
        feature_homography(a, b)
        s1 = _clocks()
        h, info = estimate_homography_robust(a, b)
        s2 = _clocks()
        for k in (0, 1):
            t_feat[k] += s1[k] - s0[k]
            t_all[k] += s2[k] - s1[k]
        hr.append(h)
        conv.append(bool(info.converged[0]))
    err = corner_error(torch.cat(hr), hs, H0, W0)

    print(f"\n== {args.scene}, max_keypoints={keypoints}, {torch.get_num_threads()} thread(s) ==")
    print(f"{'h31':>7} {'h32':>8} {'zoom':>5} {'rot':>6}  {'fast':>5} {'robust':>6} {'corner err px':>13}")
    for (d, s, _), q, f, r, e in zip(cells, persp, fast.converged.tolist(), conv, err.tolist()):
        print(f"{q[0]:7.0e} {q[1]:8.0e} {s:5.2f} {d:6.2f}  {str(f):>5} {str(r):>6} {e if r else math.nan:13.4f}")
    ok = torch.tensor(conv)
    e = err[ok]
    n, nf = len(cells), int(fast.converged.sum())
    print(
        f"fast path alone: {nf}/{n} registered; robust: {int(ok.sum())}/{n} ({100 * float(ok.double().mean()):.0f} %)"
    )
    if e.numel():
        q = torch.quantile(e, torch.tensor([0.5, 0.9], dtype=e.dtype)).tolist()
        print(
            f"corner error of the registered pairs: median {q[0]:.4f} px, p90 {q[1]:.4f} px, "
            f"max {float(e.max()):.4f} px"
        )
    print(
        f"fast path:            {1e3 * (c1 - c0) / n:8.1f} ms CPU {1e3 * (w1 - w0) / n:8.1f} ms wall per pair "
        f"(batch of {n})"
    )
    print(f"features (SIFT+RANSAC): {t_feat[0] / n:6.2f} s CPU   {t_feat[1] / n:6.2f} s wall per pair")
    nfb = max(n - nf, 1)  # the robust call per pair: fast path, then the fallback where it failed
    print(f"robust, per fallback pair: {t_all[0] / nfb:6.2f} s CPU {t_all[1] / nfb:6.2f} s wall")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="gravel")
    p.add_argument("--keypoints", type=int, nargs="+", default=[wide_baseline.MAX_KEYPOINTS])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rotations", type=float, nargs="+", default=[0.0, 11.25, 22.5, 33.75, 45.0])
    p.add_argument("--scales", type=float, nargs="+", default=[0.6, 0.9, 1.25, 1.6])
    p.add_argument("--perspectives", type=float, nargs="+", default=[0.0, 1e-3],
                   help="h31 of each perspective (h32 = -h31 / 2), pixel units about the centre")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    for k in args.keypoints:
        run(args, k)


if __name__ == "__main__":
    main()
