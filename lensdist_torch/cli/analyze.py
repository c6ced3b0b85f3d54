"""The ``lensdist analyze`` command, a user's pair: its parser and running it.

Like ``commands.py`` it imports torch only inside the command. It prints the pair's
:class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis`: its ``to_json()`` with ``--json``,
else its ``summary()``, the text answer (one reason per "cannot tell": a failed registration is
not also "too little motion or texture"; barrel or pincushion on the class line; the estimate
said to lie beyond the classes' range where it does). With ``--pairs FILE --out DIR`` it runs
every pair of a list (:mod:`~lensdist_torch.workflows.pair_archive`) and prints the run's counts.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lensdist_torch.cli import support as argtypes
from lensdist_torch.cli.support import fmt as _fmt
from lensdist_torch.cli.support import note as _note
from lensdist_torch.cli.support import print_json as _print_json
from lensdist_torch.core.outputs import check_output_file

__all__ = ["add_analyze_command", "print_analysis"]


def cmd_analyze(args: argparse.Namespace) -> int:
    if args.pairs is not None:
        return _cmd_pairs(args)
    for option, given in (("--out", args.out), ("--shard", args.shard)):
        if given is not None:
            raise ValueError(f"{option} is for --pairs FILE (many pairs); one pair's answer is printed")
    missing = [name for name in ("img1", "img2") if getattr(args, name) is None]
    if missing:
        raise ValueError(f"the following arguments are required: {', '.join(missing)} (or --pairs FILE)")
    for name in ("img1", "img2"):  # before the imports below: a missing input's error at once
        argtypes.existing(getattr(args, name), "image file")
    if args.save_map:
        from lensdist_torch.workflows.figures import figure_formats, have_matplotlib

        if not have_matplotlib():
            raise ValueError("--save-map needs matplotlib: pip install 'lensdist_torch[plots]'")
        check_output_file(args.save_map, "--save-map", suffixes=tuple(figure_formats()),
                          shown=".png, .pdf, .svg or .jpg (any format matplotlib writes)",
                          inputs={"img1": args.img1, "img2": args.img2, "--checkpoint": args.checkpoint,
                           "--checkpoint-max": args.checkpoint_max, "--config": args.config})
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.analyze import analyze_pair, resolve_device

    cfg, device = None if args.config is None else load_config(args.config), resolve_device(args.device)
    res, qmap = analyze_pair(args.img1, args.img2, checkpoint=args.checkpoint, checkpoint_max=args.checkpoint_max,
                             method=args.method, config=cfg, return_map=True, device=device)
    # the result first: a failure to write the map must not lose the analysis
    if args.json:
        _print_json(res.to_json())
    else:
        print_analysis(res)
    if args.save_map:
        from lensdist_torch.workflows.figures import save_map_grid

        label = f"{res.method}: Delta_avg {_fmt(res.delta_avg)}"
        save_map_grid(
            qmap.cpu(), [label], args.save_map, valid=_valid_blocks(res, qmap), classes=[res.class_label or "?"]
        )
        _note(args, f"map: {args.save_map}")
    return 3 if args.strict and res.cannot_tell else 0


def _cmd_pairs(args: argparse.Namespace) -> int:
    """``lensdist analyze --pairs FILE --out DIR [--shard I/N]``: every pair's answer, one table; exit 0 if it ran."""
    if args.img1 is not None:
        raise ValueError("--pairs FILE lists the pairs: give no IMG1 IMG2 with it")
    for option, given in (("--save-map", args.save_map), ("--strict", args.strict)):
        if given:
            raise ValueError(f"{option} is for one pair, not --pairs (each pair's answer is in --out/answers/)")
    if not args.out:
        raise ValueError("--out DIR is needed with --pairs (answers/, rows/, answers.csv)")
    argtypes.existing(args.pairs, "pairs file")  # before the imports below: a missing file's error at once
    from lensdist_torch.core.outputs import check_output_dir

    check_output_dir(
        args.out,
        "--out",
        {
            "--pairs": args.pairs,
            "--config": args.config,
            "--checkpoint": args.checkpoint,
            "--checkpoint-max": args.checkpoint_max,
        },
    )
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.analyze import resolve_device
    from lensdist_torch.workflows.pair_archive import pair_inputs, run_pair_archive

    pairs = pair_inputs(args.pairs)
    cfg = None if args.config is None else load_config(args.config)
    run = run_pair_archive(pairs, args.out, method=args.method, checkpoint=args.checkpoint,
                           checkpoint_max=args.checkpoint_max, settings=cfg, device=resolve_device(args.device),
                           shard=args.shard or (0, 1), quiet=args.quiet)
    if args.json:
        _print_json({"pairs": run.pairs, "selected": run.selected, "computed": run.computed, "reused": run.reused,
                     "failed": run.failed, "rows": [r.columns() for r in run.rows], "files": list(run.files)})
        return 0
    share = "" if run.selected == run.pairs else f" ({run.selected} in this share)"
    print(f"{run.pairs} pairs{share}: {run.computed} analysed, {run.reused} reused from an earlier run; "
          f"{len(run.rows)} rows in the table, {run.failed} without an answer")
    for row in run.rows:
        if not row.ok:
            print(f"  failed: {row.img1} {row.img2}: {row.reason}")
    print("written: " + ", ".join(run.files) + f", {Path(run.out) / 'answers'}/")
    return 0


def print_analysis(res) -> None:
    """Print a pair's text answer: its :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis`'s ``summary()``."""
    print(res.summary())


def _valid_blocks(res, qmap):
    """(1, 1, h, w): blocks of the analysis frame with a valid pixel after the registration.

    The metric's eroded validity, so that the map shows blocks without a valid pixel in grey.
    """
    import torch

    from lensdist_torch import warp_to_reference
    from lensdist_torch.metric import erode_valid

    h, w = res.analysis_size
    _, valid = warp_to_reference(torch.ones(1, 1, h, w), torch.tensor([res.homography]))
    b = h // qmap.shape[-2]
    v = erode_valid(valid.float())[..., : qmap.shape[-2] * b, : qmap.shape[-1] * b]
    return torch.nn.functional.max_pool2d(v, b) > 0


def add_analyze_command(command) -> None:
    """Register ``analyze`` through ``command`` (``cli.build_parser``'s helper: name, help, example, function)."""
    p = command("analyze", "analyse your own pair of overlapping photographs",
                "lensdist analyze left.jpg right.jpg --method regression --save-map map.png", cmd_analyze,
                "print the result as one JSON object", "no notes on stderr (with --pairs, no progress bar)")
    p.add_argument("img1", nargs="?", help="first image")
    p.add_argument("img2", nargs="?", help="second image, overlapping the first")
    p.add_argument("--pairs", default=None, help="many pairs instead of IMG1 IMG2: CSV with img1, img2 and an optional "
                   "camera column, or two paths per line (relative to the file's folder); needs --out")
    p.add_argument("--out", default=None, help="with --pairs: folder for answers/, rows/ and answers.csv "
                   "(docs/guide/archive.md)")
    p.add_argument("--shard", type=argtypes.shard, default=None,
                   help="with --pairs: I/N, this job's share of the pairs, k %% N == I (array jobs; default: all)")
    p.add_argument("--method", choices=["selfcal", "regression", "eigenspace"], default="selfcal",
                   help="selfcal (most accurate), regression, or the paper's eigenspace")
    p.add_argument("--checkpoint", default=None,
                   help="eigenspace: the Delta_avg classifier; regression: the regressor (default: shipped)")
    p.add_argument(
        "--checkpoint-max", default=None, help="eigenspace only: the Delta_max classifier (default: shipped)"
    )
    p.add_argument(
        "--save-map", default=None, help="figure of the quality map; the suffix names the format (.png, .pdf, .svg)"
    )
    p.add_argument("--strict", action="store_true", help="exit with status 3 when the answer is 'cannot tell'")
    p.add_argument(
        "--config",
        default=None,
        help=argtypes.CONFIG_HELP + ", e.g. a calibration.toml written by `lensdist reproduce`",
    )
    p.add_argument("--device", type=argtypes.device, default="cpu", help=argtypes.DEVICE_HELP)
