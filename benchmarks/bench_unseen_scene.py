"""The shipped checkpoints on scenes they were never fitted on: right, flagged, or confidently wrong.

    python benchmarks/bench_unseen_scene.py [--pairs 40] [--json out.json]

The shipped eigen-space and regression checkpoints were fitted on the embedded gravel and grass
scenes. Unseen scenes are made from them (a strong contrast change, a gamma, a blur) and
synthesised (band-limited noise, a patchwork of random rectangles, a sum of sinusoids); each is
rendered through the pair protocol (``make_pairs``: distorted pairs and class-R pairs with the
protocol's perturbed registration, docs/method.md, section 7) and every pair is analysed by
``analyze_batch`` as ``lensdist analyze`` would. A pair is "right or flagged" when the answer is
the true class or "cannot tell" (out of domain, low confidence, ...); the rest are confident
wrong answers. The test pairs of gravel and grass are the in-domain reference (how often a
pair of the training scenes is flagged). Prints one Markdown table per scene group.
"""

from __future__ import annotations

import argparse
import json
import math

import torch


def _band_noise(g, size=512, lo=4, hi=40):
    f = torch.fft.fft2(torch.randn(size, size, generator=g, dtype=torch.float64))
    fy, fx = torch.fft.fftfreq(size)[:, None] * size, torch.fft.fftfreq(size)[None] * size
    r = (fx**2 + fy**2).sqrt()
    y = torch.fft.ifft2(f * ((r >= lo) & (r <= hi))).real
    return ((y - y.min()) / (y.max() - y.min())).float()[None, None]


def _rectangles(g, size=512, n=300):
    y = torch.full((size, size), 0.5)
    for _ in range(n):
        x0, y0 = torch.randint(0, size, (2,), generator=g).tolist()
        w, h = torch.randint(8, 80, (2,), generator=g).tolist()
        y[y0 : y0 + h, x0 : x0 + w] = torch.rand(1, generator=g)
    return y[None, None]


def _sines(g, size=512, n=12):
    yy, xx = torch.meshgrid(torch.arange(size).double(), torch.arange(size).double(), indexing="ij")
    y = torch.zeros(size, size, dtype=torch.float64)
    for _ in range(n):
        th, fr, ph = (torch.rand(3, generator=g, dtype=torch.float64) * torch.tensor([math.pi, 0.15, 6.283]))
        y += torch.cos((0.02 + fr) * (xx * torch.cos(th) + yy * torch.sin(th)) + ph)
    return ((y - y.min()) / (y.max() - y.min())).float()[None, None]


def unseen_scenes() -> dict[str, torch.Tensor]:
    """(1, 1, 512, 512) scenes unlike the training ones, by name."""
    from kornia.filters import gaussian_blur2d

    from lensdist_torch.core import load_scene

    gravel, grass = load_scene("gravel"), load_scene("grass")
    g = torch.Generator().manual_seed(0)
    return {
        "gravel, contrast x 0.3": 0.5 + 0.3 * (gravel - 0.5),
        "grass, contrast x 0.5": 0.5 + 0.5 * (grass - 0.5),
        "gravel, gamma 2.2": gravel**2.2,
        "grass, blur sigma 2": gaussian_blur2d(grass, (13, 13), (2.0, 2.0)),
        "band-limited noise": _band_noise(g),
        "random rectangles": _rectangles(g),
        "sinusoid sum": _sines(g),
    }


def analyse(scenes: list, config, indices: list[int], batch_size: int = 8) -> dict:
    """{method: [(truth class, answer or None), ...]} over the protocol's test pairs ``indices``."""
    from lensdist_torch.data import make_pairs
    from lensdist_torch.geometry import CLASS_LABELS
    from lensdist_torch.workflows import analyze_batch, prepare_batch

    out = {"eigenspace": [], "regression": [], "selfcal": []}
    for s in range(0, len(indices), batch_size):
        batch = make_pairs(
            scenes, config=config, set_name="test", indices=indices[s : s + batch_size], keep_images=True
        )
        truth = [CLASS_LABELS[int(c)] for c in batch.classes["delta_avg"]]
        r_pairs = batch.params.perturbed
        for sel, hom in ((~r_pairs, None), (r_pairs, batch.H[r_pairs])):
            rows = sel.nonzero().flatten()
            if rows.numel() == 0:
                continue
            prep = prepare_batch(batch.img1[rows], batch.img2[rows], config=config, homography=hom)
            for method in out:
                res = analyze_batch(None, None, method=method, config=config, prepared=prep)
                out[method] += [(truth[i], r.class_label) for i, r in zip(rows.tolist(), res)]
    return out


def summary(pairs: list) -> dict:
    n = len(pairs)
    right = sum(t == a for t, a in pairs)
    flagged = sum(a is None for _, a in pairs)
    return {"pairs": n, "right": 100.0 * right / n, "flagged": 100.0 * flagged / n,
            "right_or_flagged": 100.0 * (right + flagged) / n, "confident_wrong": n - right - flagged}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", type=int, default=40, help="test pairs per scene (a fifth of them class R)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.data.shards import load_scenes

    cfg = LensdistConfig()
    n_d = args.pairs - args.pairs // 5
    idx = list(range(n_d)) + list(
        range(cfg.protocol.n_test_distorted, cfg.protocol.n_test_distorted + args.pairs - n_d)
    )
    rows = {}
    rows["gravel + grass (training scenes)"] = analyse(load_scenes(cfg)[0], cfg, idx)
    for name, scene in unseen_scenes().items():
        rows[name] = analyse([scene], cfg, idx)
    table = {name: {m: summary(v) for m, v in res.items()} for name, res in rows.items()}
    unseen = {
        m: summary([x for name, res in rows.items() if "training" not in name for x in res[m]]) for m in rows[name]
    }
    table["all unseen scenes"] = unseen
    print(
        f"{args.pairs} protocol test pairs per scene ({args.pairs - n_d} class R), "
        "shipped checkpoints, default [analysis]"
    )
    print("| scene | method | right | flagged (cannot tell) | right or flagged | confident wrong |")
    print("|---|---|---|---|---|---|")
    for name, per in table.items():
        for m, f in per.items():
            print(f"| {name} | {m} | {f['right']:.0f} % | {f['flagged']:.0f} % | {f['right_or_flagged']:.0f} % | "
                  f"{f['confident_wrong']} of {f['pairs']} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(table, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
