"""The training configuration: defaults <- a TOML file <- ``--set key=value`` overrides.

Read, merged and key-checked by the package's config reader (:mod:`lensdist_torch.config.toml`):
one TOML reader, one set of messages, for the package and its training scripts.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lensdist_torch.config import check_tables, layered_tables, parse_overrides

__all__ = [
    "ARM_NAMES",
    "DEFAULTS",
    "ARM_DEFAULTS",
    "config_from_args",
    "load_train_config",
    "parse_overrides",
    "comparable",
]

ARM_NAMES = ("l1", "l1_quality", "l1_quality_distorted")

DEFAULTS: dict[str, dict[str, Any]] = {
    "data": {
        "scenes": ["gravel", "grass"],
        "patch": 128,  # side of the patches (a multiple of the metric's block size, 8)
        "rho": 8.0,  # corner perturbation: each coordinate uniform in [-rho, rho] px
        "eval_rows": 160,  # the bottom eval_rows rows of every scene are held out for evaluation
        "photometric": 1.0,  # strength of the photometric changes (0 = none)
        "gain": 0.35,  # contrast gain in [1 - gain, 1 + gain]
        "offset": 0.12,  # brightness offset in [-offset, offset]
        "gamma": 1.6,  # gamma log-uniform in [1 / gamma, gamma]
        "ramp": 0.6,  # brightness ramp across the patch (moving light): factor 1 +- ramp / 2
        "noise": 0.03,  # Gaussian noise sigma in [0, noise]
        "k2_max": 3.0e-6,  # radial distortion of the distorted arm, in patch pixels (SPEC 6):
        "k4_max": 3.0e-10,  # k2 in ]0, k2_max], k4 in ]0, k4_max]: up to ~4 px at the corners
    },
    "model": {"kind": "correlation", "width": 16, "hidden": 256, "batch_norm": True},
    "train": {
        "seed": 0,
        "steps": 800,
        "batch_size": 16,
        "lr": 2e-3,
        "lr_final": 1e-4,  # cosine decay from lr to lr_final
        "weight_decay": 0.0,
        "checkpoint_every": 100,
        "threads": 2,  # torch.set_num_threads: the float results can depend on it
        "log_every": 10,
        "l1_levels": 4,  # pyramid levels of the photometric L1 (1 = full resolution only)
    },
    "eval": {"seed": 12345, "n_pairs": 256, "batch_size": 64},
    "arms": {
        "l1": {"lambda_quality": 0.0},
        "l1_quality": {"lambda_quality": 0.2, "quality_start": 0.25, "quality_ramp": 0.1},
        "l1_quality_distorted": {
            "lambda_quality": 0.2,
            "quality_start": 0.25,
            "quality_ramp": 0.1,
            "distorted": True,
        },
    },
}

ARM_DEFAULTS: dict[str, Any] = {
    "lambda_quality": 0.0,  # weight of the quality loss
    "quality_start": 0.0,  # fraction of the steps trained on L1 alone before the quality loss
    "quality_ramp": 0.0,  # fraction of the steps over which lambda ramps linearly from 0
    "tau_scale_start": 1.0,  # temperature scale of the metric when the quality loss starts ...
    "tau_scale_end": 1.0,  # ... annealed geometrically to this at the last step
    "l1_weight": 1.0,  # weight of the L1 loss
    "distorted": False,  # both patches carry the same radial lens distortion
}

# Keys that do not change the trained parameters: a checkpoint may be resumed with others.
_NOT_TRAINING = ("log_every", "checkpoint_every")


def config_from_args(args, load) -> dict:
    """The config a training script's command line asks for, or SystemExit with a one-line reason.

    ``--set KEY=VALUE`` overrides and ``--steps`` go over ``--config`` through ``load(path,
    overrides)``; ``--device cuda`` needs CUDA.
    """
    try:
        overrides = parse_overrides(args.set)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    if args.steps is not None:
        overrides["train.steps"] = args.steps
    cfg = load(args.config or None, overrides)
    import torch  # only here: the config itself needs no torch

    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device available")
    return cfg


def _check_keys(cfg: dict) -> None:
    check_tables({k: v for k, v in cfg.items() if k != "arms"}, {k: v for k, v in DEFAULTS.items() if k != "arms"})
    check_tables(cfg["arms"], {name: ARM_DEFAULTS for name in cfg["arms"]})


def load_train_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> dict:
    """The training configuration: DEFAULTS <- the TOML file <- ``overrides``.

    ``overrides`` maps dotted keys (``"train.steps"``, ``"arms.l1_quality.lambda_quality"``) to
    values. The file's ``[arms.*]`` replace the default arms. Unknown sections or keys are an
    error, as in the package's configs.
    """
    cfg = layered_tables(DEFAULTS, path, overrides, replaced=("arms",))
    _check_keys(cfg)
    for name, arm in cfg["arms"].items():
        cfg["arms"][name] = {**ARM_DEFAULTS, **arm}
    if cfg["data"]["patch"] % 8:
        raise ValueError("data.patch must be a multiple of 8 (the metric's block size)")
    return cfg


def comparable(cfg: dict) -> dict:
    """The config without the keys that do not change the training (logging, checkpoint period).

    ``train.threads`` stays: the float results can depend on the thread count, so a run resumed
    with another one might not reach the parameters of an uninterrupted run.
    """
    out = json.loads(json.dumps(cfg))
    for key in _NOT_TRAINING:
        out["train"].pop(key, None)
    return out
