"""Speed of ``lensdist analyze`` on one pair, beside a plain planar fit, before/after.

Renders pairs of the default protocol at 640 x 480 (test pairs ``--pairs``, their lens scaled
by ``--lens-scale`` so that the analysis size sees classes 1-3 rather than beyond class 4) and
writes them as PNG files. Then, in a fresh process per case and round (``--threads`` torch
threads, pinned), times ``analyze_pair(img1_path, img2_path)``, what ``lensdist analyze`` runs
(reading, the analysis size, registration, self-calibration, decision), and
``estimate_homography`` of the same pair at the analysis size (the plain planar fit): seconds
per pair (each pair after one warm-up call) and their ratio, the figure to compare on a shared
machine. With ``--baseline DIR`` the ``lensdist_torch`` package in DIR (``git archive OLD
lensdist_torch | tar -x -C DIR``) runs the same, alternating with the current one (``--rounds``
rounds; the best of each is reported). ``--cli`` also times the command itself (a subprocess:
imports included) on the first pair and on a missing file (the one-line error).

    python benchmarks/bench_analyze_speed.py --threads 2 [--pairs 0 1 2 3] [--baseline DIR]
        [--rounds 3] [--cli] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch


def render(folder: Path, pairs: list[int], lens_scale: float) -> list[tuple[str, str, float]]:
    """The 640 x 480 pairs as PNG files: (img1, img2, true Delta_avg at the analysis size) each."""
    from lensdist_torch.config import LensdistConfig, config_from_dict
    from lensdist_torch.core.png import encode_png, to_uint8
    from lensdist_torch.data.shards import load_scenes
    from lensdist_torch.data.synthesis import draw_pairs, render_pairs
    from lensdist_torch.geometry.distortion import delta_avg

    cfg = config_from_dict({"image": {"height": 480, "width": 640}})
    scenes, _ = load_scenes(cfg)
    p = draw_pairs(cfg, "test", pairs, len(scenes))
    p.k2, p.k4 = p.k2 * lens_scale, p.k4 * lens_scale
    i1, i2 = render_pairs(scenes, p, cfg)
    h, w = LensdistConfig().image.size
    scale = min(640 / w, 480 / h)  # the analysis size's centre crop: user px per analysis px
    truth = delta_avg(p.k2 * scale**2, p.k4 * scale**4, h, w)
    out = []
    for j, k in enumerate(pairs):
        a, b = folder / f"pair{k}_1.png", folder / f"pair{k}_2.png"
        a.write_bytes(encode_png(to_uint8(i1[j])))
        b.write_bytes(encode_png(to_uint8(i2[j])))
        out.append((str(a), str(b), float(truth[j])))
    return out


def _case(args) -> dict:
    """One round in a fresh process: (code, threads, files) -> seconds per pair of both paths."""
    code, threads, files = args
    if code != "current":  # a baseline checkout: its package shadows the installed one
        sys.path.insert(0, code)
    torch.set_num_threads(threads)
    from lensdist_torch.core.images import load_image, resize_to
    from lensdist_torch.registration.direct import estimate_homography
    from lensdist_torch.workflows.analyze import analyze_pair

    analyze_pair(files[0][0], files[0][1])  # warm-up
    t_an, t_h, answers = [], [], []
    for a, b, truth in files:
        t0 = time.perf_counter()
        res = analyze_pair(a, b)
        t_an.append(time.perf_counter() - t0)
        answers.append({"class": res.class_label, "delta_avg": res.delta_avg, "truth_delta_avg": truth,
                        "relief_answer": res.to_json().get("relief_delta_avg") is not None})
        x, y = (resize_to(load_image(f), 320, 424) for f in (a, b))
        estimate_homography(x, y)  # warm-up of this size
        t0 = time.perf_counter()
        estimate_homography(x, y)
        t_h.append(time.perf_counter() - t0)
    return {"analyze_s": t_an, "planar_fit_s": t_h, "answers": answers, "load_average": os.getloadavg()}


def _cli(code: str, files) -> dict:
    """Wall seconds of the command itself (imports included): one pair, and a missing file."""
    env = dict(os.environ, PYTHONPATH=code if code != "current" else "")
    cmd = [sys.executable, "-m", "lensdist_torch.cli", "analyze"]
    out = {}
    for name, args in (("pair", [files[0][0], files[0][1]]), ("missing_file", ["/nonexistent.png", files[0][1]])):
        t0 = time.perf_counter()
        subprocess.run(cmd + args, env=env, capture_output=True, check=False)
        out[name + "_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, nargs="+", default=[0, 1, 2, 3], help="test pair indices")
    ap.add_argument("--lens-scale", type=float, default=0.25, help="the drawn k2, k4 times this")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--baseline", default=None, help="directory holding another lensdist_torch to compare with")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cli", action="store_true", help="also time the command in a subprocess")
    ap.add_argument("--out", default=None, help="write the figures as JSON here too")
    a = ap.parse_args(argv)
    codes = ["current"] + ([a.baseline] if a.baseline else [])
    res: dict = {"threads": a.threads, "pairs": a.pairs, "size": "640 x 480", "load_average_before": os.getloadavg()}
    with tempfile.TemporaryDirectory() as tmp:
        files = render(Path(tmp), a.pairs, a.lens_scale)
        ctx = mp.get_context("spawn")
        best: dict = {}
        for _ in range(a.rounds):
            for code in codes:
                with ctx.Pool(1) as pool:
                    r = pool.apply(_case, ((code, a.threads, files),))
                if a.cli:
                    r["cli"] = _cli(code, files)
                r["ratio"] = sum(r["analyze_s"]) / sum(r["planar_fit_s"])
                key = "current" if code == "current" else "baseline"
                if key not in best or sum(r["analyze_s"]) < sum(best[key]["analyze_s"]):
                    best[key] = r
    for key, r in best.items():
        r["analyze_s_per_pair"] = sum(r["analyze_s"]) / len(r["analyze_s"])
        r["planar_fit_s_per_pair"] = sum(r["planar_fit_s"]) / len(r["planar_fit_s"])
        res[key] = r
    if a.baseline:
        res["analyze_time_ratio_to_baseline"] = best["current"]["analyze_s_per_pair"] / best["baseline"][
            "analyze_s_per_pair"]
    res["load_average_after"] = os.getloadavg()
    text = json.dumps(res, indent=1)
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
