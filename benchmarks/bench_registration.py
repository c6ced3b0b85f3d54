"""Speed and accuracy of lensdist_torch.registration at the analysis size (320 x 424).

Measures, for 1 and 2 intra-op threads and batches of 1, 8 and 32 pairs:

* pairs/s of ``estimate_homography`` (wall clock, best of ``--repeat``) and its CPU time per
  pair (process time: on a shared machine the wall clock also counts other people's work);
* median / max corner error against the true homography and the number of converged pairs,
  on undistorted SPEC 7 pairs of the embedded scenes;
* an end-to-end generation step (render a distorted SPEC 6/7 pair, register it, warp img2,
  count the registration-error pixels per block) in pairs/s.

Usage: python benchmarks/bench_registration.py [--pairs 64] [--threads 1 2] [--batches 1 8 32]

On a shared machine, run it also as ``OMP_WAIT_POLICY=PASSIVE python benchmarks/...``: with the
default (spinning) OpenMP wait policy, a 2-thread pool whose second thread is descheduled by
someone else's work spins at every parallel region, and every op-heavy torch code (not only
this module) slows down ~20 x.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import torch
import torch.nn.functional as F

from lensdist_torch.core import load_scene
from lensdist_torch.geometry import corner_error
from lensdist_torch.metric import registration_error_counts
from lensdist_torch.registration import estimate_homography, warp_to_reference

H0, W0 = 320, 424


def _t(x: float, y: float) -> torch.Tensor:
    return torch.tensor([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]], dtype=torch.float64)


def draw(n: int, seed: int, distort: bool):
    """Per pair, from its own generator (SPEC 7): A (M = T(p0) A T(-p0), I2 -> I1), zoom and
    offset of the camera on the scene, and (if ``distort``) SPEC 6's k2, k4."""
    out = []
    for i in range(n):
        g = torch.Generator().manual_seed(seed * 100_003 + i)
        r = torch.rand(10, generator=g, dtype=torch.float64).tolist()
        th, s = math.radians(2 * r[2] - 1), 0.98 + 0.04 * r[3]
        a = [[s * math.cos(th), -s * math.sin(th), 8 * r[1] - 4], [s * math.sin(th), s * math.cos(th), 40 * r[0]],
             [4e-5 * r[4] - 2e-5, 4e-5 * r[5] - 2e-5, 1.0]]  # SPEC 7's A
        a = torch.tensor(a, dtype=torch.float64)
        k2, k4 = (2.5e-6 * r[6], 2.5e-11 * r[7]) if distort else (0.0, 0.0)
        fc = 1 + k2 * 265.0**2 + k4 * 265.0**4  # radial stretch at the corners
        z = min(1.0, 235 / (1.03 * (W0 - 1) / 2 * fc + 10))  # every sample stays inside the scene
        out.append((a, z, 40 * r[8] - 20, 40 * r[9] - 20, k2, k4))
    return out


def render(scene: torch.Tensor, params) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched: I1(p_d) = S(P p(p_d)), I2(p_d) = S(P M p(p_d)), one grid_sample per image."""
    b, side = len(params), scene.shape[-1] - 1
    a = torch.stack([q[0] for q in params])
    k2, k4 = (torch.tensor([q[i] for q in params], dtype=torch.float32)[:, None, None] for i in (4, 5))
    x = torch.arange(W0, dtype=torch.float32) - (W0 - 1) / 2  # centred pixel coordinates
    y = torch.arange(H0, dtype=torch.float32)[:, None] - (H0 - 1) / 2
    f = 1 + k2 * (x * x + y * y) + k4 * (x * x + y * y) ** 2
    xi, yi = f * x, f * y  # ideal points p(p_d), centred (b, h, w)
    place = [[[q[1], 0, side / 2 + q[2]], [0, q[1], side / 2 + q[3]], [0, 0, 1]] for q in params]
    place = torch.tensor(place, dtype=torch.float64)  # P, from centred image coordinates
    norm = torch.tensor([[2 / side, 0, -1], [0, 2 / side, -1], [0, 0, 1]], dtype=torch.float64)
    imgs = []
    for q in (place, place @ a):  # centred: T(-p0) M T(p0) = A
        g = (norm @ q).float()
        num = [g[:, i, 0, None, None] * xi + g[:, i, 1, None, None] * yi + g[:, i, 2, None, None] for i in range(3)]
        grid = torch.stack([num[0] / num[2], num[1] / num[2]], -1)
        imgs.append(F.grid_sample(scene.expand(b, -1, -1, -1), grid, mode="bilinear", align_corners=True))
    m = _t((W0 - 1) / 2, (H0 - 1) / 2) @ a @ _t(-(W0 - 1) / 2, -(H0 - 1) / 2)
    h_true = torch.linalg.inv(m)
    return imgs[0], imgs[1], h_true / h_true[:, 2:, 2:]


def timed(fn, repeat: int, *args):
    """Best wall and CPU (process) seconds of ``repeat`` runs of fn(*args), and its last result."""
    wall, cpu, out = math.inf, math.inf, None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn(*args)
        wall, cpu = min(wall, time.perf_counter() - t0), min(cpu, time.process_time() - c0)
    return wall, cpu, out


def register_all(chunks):
    return [estimate_homography(a, b) for a, b in chunks]


def end_to_end(scene: torch.Tensor, params, parts: dict[str, float]) -> None:
    """Render, register, warp and count block errors, 32 pairs at a time; CPU time per stage."""
    for i in range(0, len(params), 32):
        c = time.process_time()
        a, b, _ = render(scene, params[i : i + 32])
        c, parts["render"] = time.process_time(), parts["render"] + time.process_time() - c
        h, _ = estimate_homography(a, b)
        c, parts["register"] = time.process_time(), parts["register"] + time.process_time() - c
        w, v = warp_to_reference(b, h)
        c, parts["warp"] = time.process_time(), parts["warp"] + time.process_time() - c
        registration_error_counts(a, w, v)
        parts["metric"] += time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} at start, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')}")
    scenes = {name: load_scene(name) for name in ("gravel", "grass")}
    n = args.pairs
    data = [render(scenes[name], draw(n // 2, seed, distort=False)) for seed, name in enumerate(scenes)]
    img1, img2, h_true = (torch.cat(x) for x in zip(*data))

    print(f"\nestimate_homography, {img1.shape[0]} undistorted pairs at {H0} x {W0}")
    print(f"{'threads':>7} {'batch':>5} {'pairs/s':>8} {'cpu ms/pair':>11} {'median err':>10} {'max err':>8} "
          f"{'converged':>9}")
    for threads in args.threads:
        torch.set_num_threads(threads)
        for bs in args.batches:
            chunks = [(img1[i : i + bs], img2[i : i + bs]) for i in range(0, img1.shape[0], bs)]
            wall, cpu, res = timed(register_all, args.repeat, chunks)
            h = torch.cat([r[0] for r in res])
            conv = int(torch.cat([r[1].converged for r in res]).sum())
            err = corner_error(h, h_true, H0, W0)
            print(f"{threads:>7} {bs:>5} {img1.shape[0] / wall:>8.1f} {1e3 * cpu / img1.shape[0]:>11.2f} "
                  f"{float(err.median()):>10.4f} {float(err.max()):>8.4f} {conv:>5}/{img1.shape[0]}")

    print(f"\nend to end: render a distorted pair + register + warp + block error counts, batch 32, {n} pairs")
    print(f"{'threads':>7} {'pairs/s':>8} {'cpu ms/pair':>11} {'render':>7} {'register':>8} {'warp':>6} {'metric':>6}"
          "  (cpu ms/pair)")
    params = draw(n, 99, distort=True)
    for threads in args.threads:
        torch.set_num_threads(threads)
        parts = {"render": 0.0, "register": 0.0, "warp": 0.0, "metric": 0.0}
        wall, cpu, _ = timed(end_to_end, args.repeat, scenes["gravel"], params, parts)
        per = {k: 1e3 * v / (n * args.repeat) for k, v in parts.items()}
        print(f"{threads:>7} {n / wall:>8.1f} {1e3 * cpu / n:>11.2f} {per['render']:>7.2f} {per['register']:>8.2f} "
              f"{per['warp']:>6.2f} {per['metric']:>6.2f}")
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end (2-thread numbers suffer most from a busy machine)")


if __name__ == "__main__":
    main()
