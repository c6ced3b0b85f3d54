"""The ``lensdist`` command line.

Results go to stdout: human text, or with ``--json`` exactly one strict JSON object (a missing
figure is null). Progress bars and notes go to stderr. Every failure is one line
``lensdist CMD: error: ...`` on stderr with exit status 2 (1 for an internal error, 130 after
Ctrl-C); the global ``--debug`` adds the traceback. A result that cannot be written to stdout
(closed, disk full) is such an error too; a broken pipe (``| head``) ends quietly with status 1.
Argument types, the parser class and the output helpers live in ``support.py``. The commands
go by concept: the protocol's (demo, generate, train, evaluate, reproduce) here, a user's pair
(``analyze``) in ``cli/analyze.py``, a user's camera (``calibrate``, ``undistort``) in
``cli/calibrate.py``, each module with its parsers; output paths are checked (and
refused where they name an input) by ``core/outputs.py``. torch is imported inside the commands
only, so ``lensdist --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
import traceback
from pathlib import Path

from lensdist_torch.cli import support as argtypes
from lensdist_torch.cli.analyze import add_analyze_command
from lensdist_torch.cli.support import StdoutError, guarded_stdout, silence_stdout
from lensdist_torch.cli.support import note as _note
from lensdist_torch.cli.support import print_json as _print_json
from lensdist_torch.config.checks import one_line
from lensdist_torch.core.outputs import check_output_dir, check_output_file, refuse_inputs, refuse_inside

__all__ = ["main", "build_parser"]

#: Exceptions that are the user's input or environment (a one-line error, exit 2); any other
#: exception is an internal error (exit 1). CheckpointError and ShardError are ValueErrors.
_USER_ERRORS = (ValueError, TypeError, OSError, ImportError)


# ----------------------------------------------------------------------------- commands
def _cmd_demo(args: argparse.Namespace) -> int:
    """Two views of the gravel scene, the second misregistered by a known scale error."""
    out = check_output_dir(args.out, "--out", {"--config": args.config}, writes=["demo.png"])
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.demo import scale_error_demo
    from lensdist_torch.workflows.figures import have_matplotlib, save_demo_figure

    summary, (img1, img2, qmap, valid) = scale_error_demo(load_config(args.config), args.scene, args.scale_error)
    summary["figure"] = None
    if have_matplotlib():
        title = f"{args.scene}: {100 * args.scale_error:.1f} % scale error"
        summary["figure"] = str(save_demo_figure(img1, img2, qmap, out / "demo.png", title=title, valid=valid))
    else:
        _note(args, "(install the 'plots' extra for a PNG of the images and the map)")
    if args.json:
        _print_json(summary)
        return 0
    print(
        f"A {100 * args.scale_error:.1f} % scale error moves pixels by up to {summary['max_offset_px']:.1f} px: "
        f"{summary['blocks_with_errors']} of {summary['blocks']} blocks show registration errors, "
        f"{summary['mean_error_ratio_outer_third']:.3f} mean ratio in the outer third vs "
        f"{summary['mean_error_ratio_centre_third']:.3f} in the centre (quality index {summary['quality_index']:.3f})."
    )
    if summary["figure"]:
        _note(args, f"figure: {summary['figure']}")
    return 0


def _shards(summary: dict) -> tuple[int, int]:
    """(shards written, shards reused) from a ``data.shards.generate`` summary."""
    written = int(summary.get("written", 0))
    total = sum(int(info.get("n_shards", 0)) for info in summary.get("sets", {}).values())
    return written, max(0, total - written)


def _cmd_generate(args: argparse.Namespace) -> int:
    import os

    inputs = {"--config": args.config, "--scenes": args.scenes, "--sequence": args.sequence}
    if (Path(args.out) / "manifest.json").is_file() and not os.access(args.out, os.W_OK | os.X_OK):
        refuse_inputs(args.out, "--out", inputs)  # a read-only data set is re-checked; generate says if it must write
        refuse_inputs(Path(args.out) / "manifest.json", "--out", inputs, written=True)
    else:
        check_output_dir(args.out, "--out", inputs, writes=["manifest.json"], data_set=True)
    from lensdist_torch.config import load_config
    from lensdist_torch.data.shards import generate

    cfg = load_config(args.config)
    summary = generate(
        cfg,
        args.out,
        sets=args.sets.split(","),
        shard=args.shard or (0, 1),
        workers=args.workers,
        batch_size=args.batch_size,
        scenes_dir=args.scenes if args.sequence is None else args.sequence,
        sequence=args.sequence is not None,
        limit=args.limit,
        progress=not args.quiet,
    )
    if args.json:
        _print_json(summary)
        return 0
    written, reused = _shards(summary)
    print(f"{args.out}: {written} shards written ({summary.get('pairs_generated', '?')} pairs), {reused} reused")
    for what in summary.get("regenerated", []):
        print(f"  regenerated: {what}")
    for name, info in summary.get("sets", {}).items():
        if info.get("complete"):
            print(f"  {name}: {info['n_pairs']} pairs, complete; registration failed for {info['registration_failed']}")
        else:
            print(
                f"  {name}: {info.get('shards_present', 0)} of {info['n_shards']} shards present (other --shard jobs)"
            )
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    out = check_output_file(args.out, "--out", suffixes=(".pt",), inputs={"--config": args.config, "--data": args.data})
    refuse_inside(out, "--out", args.data, "--data")
    from lensdist_torch.config import load_config
    from lensdist_torch.data.shards import load_set
    from lensdist_torch.workflows.evaluate import fit_classifier

    train = load_set(args.data, "train")
    cfg = train["config"] if args.config is None else load_config(args.config)
    model = fit_classifier(train, cfg, n_eigenvectors=args.eigenvectors, metric=args.metric)
    model.save(out)
    summary = {
        "checkpoint": str(out),
        "metric": model.config.classifier.metric,
        "n_eigenvectors": model.config.classifier.n_eigenvectors,
        "training_pairs": int(model.train_class.numel()),
        "left_out_failed_registration": int((~train["converged"]).sum()),
        "explained_variance": model.explained.tolist(),
        "reject_threshold": float(model.reject_threshold),
    }
    if args.json:
        _print_json(summary)
        return 0
    print(
        f"{out}: eigen-space classifier for {summary['metric']}, {summary['n_eigenvectors']} eigenvectors per class, "
        f"{summary['training_pairs']} training pairs ({summary['left_out_failed_registration']} left out: "
        f"registration failed); explained variance per class "
        + ", ".join(f"{v:.2f}" for v in summary["explained_variance"])
        + f"; reject above {summary['reject_threshold']:.3f}"
    )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    check_output_dir(
        args.out,
        "--out",
        {
            "--data": args.data,
            "--checkpoint": args.checkpoint or [],
            "--regression": args.regression,
            "--config": args.config,
        },
        writes=["evaluate.md", "evaluate.json"],
    )
    refuse_inside(Path(args.out) / "evaluate.json", "--out", args.data, "--data")
    if not (args.checkpoint or args.regression or args.selfcal):
        raise ValueError("nothing to evaluate: give --checkpoint, --regression and/or --selfcal")
    from lensdist_torch.config import load_config
    from lensdist_torch.data.shards import load_set, read_manifest
    from lensdist_torch.workflows.analyze import resolve_device
    from lensdist_torch.workflows.evaluate import evaluate_checkpoints
    from lensdist_torch.workflows.reports import write_report

    device = resolve_device(args.device)
    if any(":" in s for s in read_manifest(args.data)["scenes"]):
        raise ValueError(
            "evaluate re-renders the test pairs for the analysis and needs a data set of the embedded scenes"
        )
    test = load_set(args.data, "test")
    cfg = None if args.config is None else load_config(args.config)
    settings = evaluate_checkpoints(test, args.checkpoint or [], regression=args.regression, selfcal=args.selfcal,
                                    progress=not args.quiet, device=device, config=cfg)
    report = {"title": f"lensdist evaluate: {args.data}", "settings": settings}
    md, js = write_report(report, args.out, "evaluate")
    if args.json:
        _print_json({**report, "written": [str(md), str(js)]})
        return 0
    print(Path(md).read_text())
    _note(args, f"written: {md}, {js}")
    return 0


def _cmd_reproduce(args: argparse.Namespace) -> int:
    check_output_dir(args.out, "--out", {"--config": args.config},
                     writes=["reproduce.md", "reproduce.json", "calibration.toml", "calibration.json"])
    from lensdist_torch.config import load_config
    from lensdist_torch.workflows.analyze import resolve_device
    from lensdist_torch.workflows.reproduce import reproduce

    cfg, device = load_config(args.config), resolve_device(args.device)
    res = reproduce(
        cfg,
        args.out,
        quick=args.quick,
        workers=args.workers,
        batch_size=args.batch_size,
        progress=not args.quiet,
        device=device,
    )
    report = json.loads(Path(res["json"]).read_text())
    written, reused = _shards(report.get("generation", {}))
    if args.json:
        _print_json({**report, "written": [res["markdown"], res["json"]]})
    else:  # the headline table and its terms; the rest is in the report file
        from lensdist_torch.workflows.reports import report_summary

        print(report_summary(report, res["markdown"]), end="")
    _note(
        args,
        f"data: {written} shards generated, reused {reused} shards" if reused else f"data: {written} shards generated",
    )
    _note(args, f"written: {res['markdown']}, {res['json']}")
    return 0


# ----------------------------------------------------------------------------- the parser
def _scale_error(text: str) -> float:
    """``demo --scale-error``: the range the demo can show (``workflows.demo.MAX_SCALE_ERROR``)."""
    from lensdist_torch.workflows.demo import MAX_SCALE_ERROR

    return argtypes.float_in(0.0, MAX_SCALE_ERROR)(text)




def build_parser() -> argparse.ArgumentParser:
    """The ``lensdist`` parser: one subcommand per workflow."""
    from lensdist_torch import __version__
    from lensdist_torch.cli.calibrate import add_calibrate_commands

    parser = argtypes.Parser(
        prog="lensdist",
        description="Registration-quality maps and the analysis of lens distortions (docs/method.md).\n"
        "Results on stdout (--json: one JSON object), progress and notes on stderr, errors as one line.",
        epilog="examples:\n  lensdist demo\n  lensdist analyze left.jpg right.jpg --json\n  lensdist reproduce --quick",
        formatter_class=argtypes.Formatter,
    )
    parser.add_argument("--version", action="version", version=f"lensdist {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    common = argtypes.debug_parent()

    def command(name: str, help: str, example: str, func, json_help: str, quiet: str | None = None):
        p = sub.add_parser(name, help=help, description=help, epilog=f"example:\n  {example}", parents=[common],
                           formatter_class=argtypes.Formatter)
        p.add_argument("--json", action="store_true", help=json_help)
        if quiet:
            p.add_argument("--quiet", action="store_true", help=quiet)
        p.set_defaults(func=func)
        return p

    for add in (_add_demo, _add_generate, _add_train, _add_evaluate, _add_reproduce, add_analyze_command):
        add(command)
    add_calibrate_commands(sub, [common])  # calibrate, undistort
    return parser


def _add_demo(command) -> None:
    p = command(
        "demo",
        "quality map of a known misregistration on the embedded scene",
        "lensdist demo --scale-error 0.02 --out results",
        _cmd_demo,
        "print only the summary as one JSON object",
    )
    p.add_argument("--scene", default="gravel", help="embedded scene")
    p.add_argument(
        "--scale-error",
        type=_scale_error,
        default=0.01,
        help="relative scale error of the second view, from 0 to 0.1 (beyond, errors no longer grow outwards)",
    )
    p.add_argument("--config", default=None, help=argtypes.CONFIG_HELP)
    p.add_argument("--out", default="results", help="folder for demo.png")


def _add_generate(command) -> None:
    p = command("generate", "generate the paper's training and test pairs as shards",
                "lensdist generate --config configs/paper.toml --out data/paper --workers 4", _cmd_generate,
                "print the summary as one JSON object", "no progress bar")
    p.add_argument("--config", default=None, help=argtypes.CONFIG_HELP + ", e.g. configs/paper.toml")
    p.add_argument("--out", required=True, help="output folder (shards + manifest.json)")
    p.add_argument("--sets", default="train,test", help="comma-separated: train,test")
    p.add_argument(
        "--shard",
        type=argtypes.shard,
        default=None,
        help="I/N: this job's share of the shards (array jobs; default: all)",
    )
    p.add_argument("--workers", type=argtypes.positive_int, default=2, help="worker processes (one thread each)")
    p.add_argument(
        "--batch-size",
        type=argtypes.positive_int,
        default=16,
        help="pairs per batch (the maps do not depend on it; H only to ~1e-6)",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument(
        "--scenes", default=None, help="folder of real, undistorted scene images (default: the embedded scenes)"
    )
    src.add_argument("--sequence", default=None, help="folder of consecutive frames of a real, undistorted sequence: "
                     "pairs of consecutive frames instead of synthetic motion")
    p.add_argument(
        "--limit", type=argtypes.positive_int, default=None, help="only the first N pairs of each set (default: all)"
    )


def _add_train(command) -> None:
    p = command(
        "train",
        "fit the eigen-space classifier on generated training pairs",
        "lensdist train --data data/paper --out ckpt/eigenspace_avg_10ev.pt --metric delta_avg --eigenvectors 10",
        _cmd_train,
        "print the summary as one JSON object",
    )
    p.add_argument("--data", required=True, help="folder written by `lensdist generate`")
    p.add_argument(
        "--out", required=True, help="checkpoint file path, ending in .pt (not a folder), outside the --data folder"
    )
    p.add_argument(
        "--metric", choices=["delta_avg", "delta_max"], default=None, help="Delta metric (default: the config's)"
    )
    p.add_argument(
        "--eigenvectors",
        type=argtypes.positive_int,
        default=None,
        help="eigenvectors per class (paper: 5 or 10; default: the config's)",
    )
    p.add_argument("--config", default=None, help="TOML config (default: the data set's own)")


def _add_evaluate(command) -> None:
    p = command("evaluate", "evaluate checkpoints on a generated test set (Markdown + JSON)",
                "lensdist evaluate --data data/paper --checkpoint ckpt/eigenspace_avg_10ev.pt --selfcal --out results",
                _cmd_evaluate, "print the report as one JSON object", "no progress bar, no notes")
    p.add_argument("--data", required=True, help="folder written by `lensdist generate`")
    p.add_argument("--checkpoint", nargs="+", default=None, help="one or more eigen-space checkpoints")
    p.add_argument("--regression", default=None, help="a DeltaRegressor checkpoint")
    p.add_argument("--selfcal", action="store_true", help="also self-calibrate every test pair (re-rendered)")
    p.add_argument("--out", default="results", help="report folder")
    p.add_argument("--config", default=None, help="TOML config of the analysis (default: the data set's), e.g. the "
                   "calibration.toml of `lensdist reproduce`")
    p.add_argument("--device", type=argtypes.device, default="cpu", help=argtypes.DEVICE_HELP)


def _add_reproduce(command) -> None:
    p = command("reproduce", "the paper's Tables 1 and 2 on the embedded scenes, one command",
                "lensdist reproduce --quick --out results/quick", _cmd_reproduce,
                "print the report as one JSON object", "no progress bars, no notes")
    p.add_argument("--config", default=None, help=argtypes.CONFIG_HELP + " (= configs/paper.toml)")
    p.add_argument("--out", default="results/reproduce", help="folder for data, checkpoints and the report")
    p.add_argument("--quick", action="store_true", help="a tenth of the pairs, for a first look")
    p.add_argument("--workers", type=argtypes.positive_int, default=2, help="worker processes for generation")
    p.add_argument(
        "--batch-size", type=argtypes.positive_int, default=16, help="pairs per batch for generation and analysis"
    )
    p.add_argument("--device", type=argtypes.device, default="cpu", help=argtypes.DEVICE_HELP)


def _one_line(exc: BaseException) -> str:
    """The error line of ``exc``; an OSError as 'FILE: what the system said'."""
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        exc = OSError(f"{exc.filename}: {exc.strerror}")
    return one_line(exc, 500)


def main(argv: list[str] | None = None) -> int:
    """Run ``lensdist`` with ``argv`` (default: the process arguments); returns the exit status."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # a usage error, one line already on stderr: its status (2) returned
        if exc.code in (0, None):  # --help, --version
            raise
        return exc.code if isinstance(exc.code, int) else 2
    prog = f"lensdist {args.command}"
    if sys.stdout is None:  # started with stdout closed (`>&-`): the result would be lost
        print(
            f"{prog}: error: stdout is closed, the result would be lost (redirect it, e.g. > /dev/null)",
            file=sys.stderr,
        )
        return 2
    try:
        with guarded_stdout():
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        if args.debug:
            traceback.print_exc()
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout closed early (`| head`): not an error worth a message
        silence_stdout()
        return 1
    except StdoutError as exc:
        silence_stdout()
        print(f"{prog}: error: cannot write the result to stdout: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        if args.debug:
            traceback.print_exc()
        if isinstance(exc, _USER_ERRORS):
            print(f"{prog}: error: {argtypes.as_flags(_one_line(exc))}", file=sys.stderr)
            return 2
        hint = "" if args.debug else " (run with --debug for the traceback)"
        print(f"{prog}: error: internal error: {type(exc).__name__}: {_one_line(exc)}{hint}", file=sys.stderr)
        return 1

