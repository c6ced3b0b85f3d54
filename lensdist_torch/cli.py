"""The ``lensdist`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

__all__ = ["main"]


def _cmd_demo(args: argparse.Namespace) -> int:
    """Two views of the gravel scene, the second misregistered by a known scale error."""
    from kornia.geometry.transform import warp_perspective

    from lensdist_torch.config import load_config
    from lensdist_torch.geometry.distortion import distortion_center
    from lensdist_torch.core.images import load_scene
    from lensdist_torch.metric.quality import registration_quality

    cfg = load_config(args.config)
    h, w = cfg.image.height, cfg.image.width
    scene = load_scene(args.scene)
    y0, x0 = (scene.shape[-2] - h) // 2, (scene.shape[-1] - w) // 2
    img1 = scene[..., y0 : y0 + h, x0 : x0 + w].contiguous()
    # The registration error: a 1 % scale about the image centre (0.01 r px at radius r).
    cx, cy = distortion_center(h, w)
    s = 1.0 + args.scale_error
    err = torch.tensor([[[s, 0.0, (1 - s) * cx], [0.0, s, (1 - s) * cy], [0.0, 0.0, 1.0]]])
    img2 = warp_perspective(img1, err, (h, w), align_corners=True)
    valid = warp_perspective(torch.ones_like(img1), err, (h, w), align_corners=True) > 0.999
    res = registration_quality(img1, img2, valid.float(), cfg.quality)
    qmap = res.registration_map
    hb, wb = qmap.shape[-2:]
    yy, xx = torch.meshgrid(torch.arange(hb), torch.arange(wb), indexing="ij")
    r = torch.sqrt((yy - (hb - 1) / 2) ** 2 + (xx - (wb - 1) / 2) ** 2)
    inner, outer = qmap[0, 0][r < r.max() / 3], qmap[0, 0][r > 2 * r.max() / 3]
    summary = {
        "scene": args.scene,
        "size": [h, w],
        "scale_error": args.scale_error,
        "max_offset_px": args.scale_error * float(torch.hypot(torch.tensor(cx), torch.tensor(cy))),
        "blocks": hb * wb,
        "blocks_with_errors": int((qmap > 0).sum()),
        "mean_error_ratio": float(qmap.mean()),
        "quality_index": float(res.quality_index[0]),
        "mean_error_ratio_centre_third": float(inner.mean()),
        "mean_error_ratio_outer_third": float(outer.mean()),
        "visual_error_blocks": int((res.visual_map > 0).sum()),
    }
    print(json.dumps(summary, indent=2))
    print(
        f"A {100 * args.scale_error:.1f} % scale error moves pixels by up to {summary['max_offset_px']:.1f} px: "
        f"{summary['blocks_with_errors']} of {summary['blocks']} blocks show registration errors, "
        f"{summary['mean_error_ratio_outer_third']:.3f} mean ratio in the outer third vs "
        f"{summary['mean_error_ratio_centre_third']:.3f} in the centre."
    )
    from lensdist_torch.workflows.figures import have_matplotlib, save_demo_figure

    if have_matplotlib():
        out = Path(args.out)
        path = save_demo_figure(img1, img2, qmap, out / "demo.png", f"{args.scene}: {100 * args.scale_error:.1f} % scale error")
        print(f"figure: {path}")
    else:
        print("(install the 'plots' extra for a PNG of the images and the map)")
    return 0


def _cmd_generate(args: argparse.Namespace) -> int:
    from lensdist_torch.config import load_config
    from lensdist_torch.data.shards import generate

    cfg = load_config(args.config)
    shard = _parse_shard(args.shard)
    sets = args.sets.split(",")
    summary = generate(
        cfg,
        args.out,
        sets=sets,
        shard=shard,
        workers=args.workers,
        batch_size=args.batch_size,
        scenes_dir=args.scenes if args.sequence is None else args.sequence,
        sequence=args.sequence is not None,
        limit=args.limit,
        progress=not args.quiet,
    )
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from lensdist_torch.config import load_config
    from lensdist_torch.data.shards import load_set
    from lensdist_torch.workflows.evaluate import fit_classifier

    train = load_set(args.data, "train")
    cfg = train["config"] if args.config is None else load_config(args.config)
    model = fit_classifier(train, cfg, args.eigenvectors, args.metric)
    model.save(args.out)
    print(json.dumps({
        "checkpoint": str(args.out),
        "metric": model.config.classifier.metric,
        "n_eigenvectors": model.config.classifier.n_eigenvectors,
        "training_pairs": int(model.train_class.numel()),
        "left_out_failed_registration": int((~train["converged"]).sum()),
        "explained_variance": model.explained.tolist(),
        "reject_threshold": float(model.reject_threshold),
    }, indent=2))
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from lensdist_torch.data.shards import load_set
    from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
    from lensdist_torch.workflows.reports import write_report
    from lensdist_torch.workflows.evaluate import evaluate_classifier

    test = load_set(args.data, "test")
    settings = {}
    for ck in args.checkpoint or []:
        model = EigenSpaceClassifier.load(ck, expected=test["config"])
        c = model.config.classifier
        settings[f"{c.n_eigenvectors} EV, {c.metric}"] = evaluate_classifier(model, test)
    if args.regression:
        from lensdist_torch.workflows.evaluate import evaluate_regressor
        from lensdist_torch.workflows.evaluate import features_of
        from lensdist_torch.classify.regression import DeltaRegressor

        reg = DeltaRegressor.load(args.regression, expected=test["config"])
        for metric, fig in evaluate_regressor(reg, test, features_of(test, test["config"])).items():
            settings[f"regression, {metric}"] = fig
    if args.selfcal:
        from lensdist_torch.data.shards import load_scenes, read_manifest
        from lensdist_torch.workflows.evaluate import evaluate_selfcal

        if any(":" in s for s in read_manifest(args.data)["scenes"]):
            raise ValueError("--selfcal re-renders the test pairs and needs a data set of the embedded scenes")
        scenes, _ = load_scenes(test["config"])
        for metric, fig in evaluate_selfcal(test, test["config"], scenes).items():
            settings[f"selfcal, {metric}"] = fig
    if not settings:
        raise ValueError("nothing to evaluate: give --checkpoint, --regression and/or --selfcal")
    report = {"title": f"lensdist evaluate: {args.data}", "settings": settings}
    md, js = write_report(report, args.out, "evaluate")
    print(Path(md).read_text())
    print(f"written: {md}, {js}")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.reproduce import reproduce

    cfg = load_config(args.config)
    res = reproduce(cfg, args.out, quick=args.quick, workers=args.workers, batch_size=args.batch_size, progress=not args.quiet)
    print(Path(res["markdown"]).read_text())
    print(f"written: {res['markdown']}, {res['json']}")
    return 0


def _cmd_analyze(args: argparse.Namespace) -> int:
    from lensdist_torch.workflows.analyze import analyze_pair

    res, qmap = analyze_pair(
        args.img1, args.img2, checkpoint=args.checkpoint, checkpoint_max=args.checkpoint_max, method=args.method, return_map=True
    )
    if args.save_map:
        from lensdist_torch.workflows.figures import have_matplotlib, save_map_grid

        if not have_matplotlib():
            raise ValueError("--save-map needs matplotlib: pip install 'lensdist_torch[plots]'")
        save_map_grid(qmap, [f"class {res['class']}, Delta_avg {res['delta_avg']:.1f} px"], args.save_map)
    if args.json:
        print(json.dumps(res))
        return 0
    print(f"registration: {'ok' if res['registration_ok'] else 'FAILED'} (overlap {100 * res['overlap']:.0f} %)")
    conf = "" if res["confidence"] is None else f", confidence {res['confidence']:.2f}"
    print(f"method: {res['method']}{conf}")
    print(f"distortion class: {res['class']}  (1 = small ... 4 = very strong, R = none visible)")
    print(
        f"Delta_avg ~ {res['delta_avg']:.1f} px, Delta_max ~ {res['delta_max']:.1f} px at {res['analysis_size'][1]} x "
        f"{res['analysis_size'][0]} (in your {res['input_size'][1]} x {res['input_size'][0]} pixels: "
        f"{res['delta_avg_user_px']:.1f} and {res['delta_max_user_px']:.1f} px)"
    )
    if res["distances"]:
        print("eigen-space distances: " + ", ".join(f"{d:.3f}" for d in res["distances"]) + f" (reject above {res['reject_threshold']:.3f})")
    for w in res["warnings"]:
        print(f"warning: {w}")
    return 0


def _parse_shard(text: str | None) -> tuple[int, int]:
    if text is None:
        return (0, 1)
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise SystemExit(f"--shard must look like I/N (e.g. 0/4), got {text!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise SystemExit(f"--shard I/N needs 0 <= I < N, got {text!r}")
    return (i, n)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lensdist", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="quality map of a known misregistration on the embedded scene")
    p.add_argument("--scene", default="gravel")
    p.add_argument("--scale-error", type=float, default=0.01, help="relative scale error of the second view")
    p.add_argument("--config", default=None, help="TOML config (SPEC defaults when omitted)")
    p.add_argument("--out", default="results", help="folder for the PNG")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("generate", help="generate the paper's training and test pairs as shards")
    p.add_argument("--config", default=None, help="TOML config, e.g. configs/paper.toml")
    p.add_argument("--out", required=True, help="output folder (shards + manifest.json)")
    p.add_argument("--sets", default="train,test", help="comma-separated: train,test")
    p.add_argument("--shard", default=None, help="I/N: this job's share of the shards (array jobs)")
    p.add_argument("--workers", type=int, default=2, help="worker processes (one thread each)")
    p.add_argument("--batch-size", type=int, default=16, help="pairs per batch (the maps do not depend on it; H only to ~1e-6)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--scenes", default=None, help="folder of real, undistorted scene images")
    src.add_argument("--sequence", default=None, help="folder of consecutive frames of a real, undistorted sequence: "
                     "pairs of consecutive frames instead of synthetic motion")
    p.add_argument("--limit", type=int, default=None, help="only the first N pairs of each set")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_generate)

    p = sub.add_parser("train", help="fit the eigen-space classifier on generated training pairs")
    p.add_argument("--data", required=True, help="folder written by `lensdist generate`")
    p.add_argument("--out", required=True, help="checkpoint path (.pt)")
    p.add_argument("--metric", choices=["delta_avg", "delta_max"], default=None)
    p.add_argument("--eigenvectors", type=int, default=None, help="eigenvectors per class (paper: 5 or 10)")
    p.add_argument("--config", default=None, help="TOML config (default: the data set's own)")
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("evaluate", help="evaluate checkpoints on a generated test set (Markdown + JSON)")
    p.add_argument("--data", required=True, help="folder written by `lensdist generate`")
    p.add_argument("--checkpoint", nargs="+", default=None, help="one or more eigen-space checkpoints")
    p.add_argument("--regression", default=None, help="a DeltaRegressor checkpoint (e.g. checkpoints/regression.pt)")
    p.add_argument("--selfcal", action="store_true", help="also self-calibrate every test pair (re-rendered)")
    p.add_argument("--out", default="results", help="report folder")
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("reproduce", help="the paper's Tables 1 and 2 on the embedded scenes, one command")
    p.add_argument("--config", default=None, help="TOML config (SPEC defaults = configs/paper.toml)")
    p.add_argument("--out", default="results/reproduce", help="folder for data, checkpoints and the report")
    p.add_argument("--quick", action="store_true", help="a tenth of the pairs, for a first look")
    p.add_argument("--workers", type=int, default=2, help="worker processes for generation")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_reproduce)

    p = sub.add_parser("analyze", help="analyse your own pair of overlapping photographs")
    p.add_argument("img1")
    p.add_argument("img2")
    p.add_argument("--method", choices=["selfcal", "regression", "eigenspace"], default="selfcal",
                   help="selfcal (default, most accurate), regression, or the paper's eigenspace")
    p.add_argument("--checkpoint", default=None, help="eigenspace Delta_avg or regression checkpoint (default: shipped)")
    p.add_argument("--checkpoint-max", default=None, help="Delta_max checkpoint (default: shipped)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--save-map", default=None, help="PNG of the quality map")
    p.set_defaults(func=_cmd_analyze)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, TypeError) as exc:
        print(f"lensdist {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
