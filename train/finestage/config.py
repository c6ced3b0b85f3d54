"""The fine-stage configuration: defaults <- a TOML file <- ``--set key=value`` overrides."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lensdist_torch.config import check_tables, layered_tables, parse_overrides

__all__ = ["DEFAULTS", "PEERS", "load_config", "parse_overrides", "comparable", "arm_spec", "arm_name"]

PEERS = ("l1", "ncc", "ngf")

DEFAULTS: dict[str, dict[str, Any]] = {
    "data": {
        "scenes": ["gravel", "grass"],
        "patch": 128,  # patch side, px (a multiple of 32: the network and the metric's blocks)
        "r_min": 0.5,  # each corner's residual offset has a length uniform in [r_min, r_max] px
        "r_max": 3.0,  # ... and a uniform direction: the coarse stage left 0.5-3 px
        "held_out_rows": 160,  # the bottom rows of every scene: never trained on
        "val_cols": 256,  # validation: held-out rows, columns < val_cols; test: columns >= val_cols
        "photometric": 1.0,  # strength of all photometric changes (0 = none)
        "gain": 0.5,  # contrast gain in [1 - gain, 1 + gain]
        "offset": 0.15,  # brightness offset in [-offset, offset]
        "gamma": 2.0,  # gamma log-uniform in [1 / gamma, gamma]
        "ramp": 1.0,  # brightness ramp across the patch: factor 1 +- ramp / 2
        "vignette": 0.5,  # radial fall-off 1 - v (r / r_max)^2, v in [0, vignette], off-centre
        "noise": 0.03,  # Gaussian noise sigma in [0, noise]
        "k2_max": 3.0e-6,  # lens distortion of the distorted arm, patch px (SPEC 6, ~4 px at 128)
        "k4_max": 3.0e-10,
    },
    "model": {"width": 16, "hidden": 256, "radius": 2, "batch_norm": True},
    "loss": {
        "levels": 2,  # pyramid levels of the peer losses (L1, NCC, NGF); the quality loss: full res
        "ncc_window": 9,  # box window of the local NCC
        "ncc_eps": 1.0e-4,  # added to each local variance (intensities in [0, 1])
        "ngf_eta": 0.2,  # NGF eps of each image = ngf_eta * its RMS gradient over valid pixels
    },
    "train": {
        "seeds": [0, 1, 2],
        "steps": 300,
        "batch_size": 8,
        "lr": 2e-3,
        "lr_final": 1e-4,  # cosine decay
        "weight_decay": 0.0,
        "threads": 2,  # torch.set_num_threads per run: the floats can depend on it
        "checkpoint_every": 100,
        "log_every": 10,
        "group_size": 16,  # arms of one seed trained together on the same batches (generated once)
        "quality_start": 0.0,  # fraction of the steps before the quality loss is on
        "quality_ramp": 0.05,  # fraction of the steps over which lambda ramps up
        "tau_scale": 1.0,  # temperature scale of the metric
    },
    "sweep": {
        "lambdas": [0.05, 0.2, 0.5],  # every seed; chosen per peer on the validation pairs (mean median)
        "variants": ["tau_scale=0.5", "tau_scale=2.0", "quality_start=0.5"],  # L1 + quality, first seed
        "variant_lambda": 0.2,  # the lambda of the variants (validation only, informative)
        "distorted": ["l1", "ncc", "ngf"],  # peers trained on distorted pairs too (alone and + each lambda)
    },
    "eval": {"val_seed": 777, "val_pairs": 128, "test_seed": 12345, "test_pairs": 256, "batch_size": 64},
    "refine": {
        "enabled": True,
        "steps": 100,  # Adam steps on the 8 corner offsets of each pair
        "lrs": [0.01, 0.03, 0.1],  # chosen per loss on the validation pairs
        "lambdas": [0.05, 0.2, 0.5],  # chosen jointly with lr per peer + quality on the validation pairs
        "val_pairs": 64,
        "test_sets": 3,  # disjoint test sets (the 'seeds' of the refinement arms)
        "test_pairs": 128,
        "batch_size": 64,
        "distorted": True,
    },
}

# Keys that do not change a trained run: a checkpoint may be resumed with other values.
_NOT_TRAINING = {
    "train": ("log_every", "checkpoint_every", "seeds", "group_size"),
    "sweep": None,
    "eval": None,
    "refine": None,
}


def _check(cfg: dict) -> None:
    check_tables(cfg, DEFAULTS)
    d = cfg["data"]
    if int(d["patch"]) % 32:
        raise ValueError("data.patch must be a multiple of 32")
    if not 0 <= float(d["r_min"]) <= float(d["r_max"]):
        raise ValueError("data.r_min and data.r_max must satisfy 0 <= r_min <= r_max")
    if len(cfg["train"]["seeds"]) < 1 or not cfg["sweep"]["lambdas"]:
        raise ValueError("train.seeds and sweep.lambdas must not be empty")
    for v in cfg["sweep"]["variants"]:
        variant_overrides(v)
    for p in cfg["sweep"]["distorted"]:
        if p not in PEERS:
            raise ValueError(f"sweep.distorted: unknown peer {p!r}; peers are {PEERS}")


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> dict:
    """DEFAULTS <- the TOML file <- ``overrides`` (dotted keys); unknown keys are errors."""
    cfg = layered_tables(DEFAULTS, path, overrides)
    _check(cfg)
    return cfg


def comparable(cfg: dict) -> dict:
    """The parts of the config that decide a trained run (not logging, evaluation or sweeps)."""
    out = json.loads(json.dumps(cfg))
    for section, keys in _NOT_TRAINING.items():
        if keys is None:
            out.pop(section, None)
        else:
            for k in keys:
                out[section].pop(k, None)
    return out


def variant_overrides(text: str) -> dict[str, float]:
    """``"tau_scale=2.0"`` -> ``{"tau_scale": 2.0}``; only schedule keys may vary."""
    out = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in ("tau_scale", "quality_start", "quality_ramp"):
            raise ValueError(f"sweep.variants: expected tau_scale=, quality_start= or quality_ramp=, got {text!r}")
        out[key] = float(value)
    return out


def arm_spec(cfg: dict, peer: str, lam: float = 0.0, distorted: bool = False, variant: str = "") -> dict:
    """Everything that decides one arm's training besides the seed."""
    if peer not in PEERS:
        raise ValueError(f"unknown peer {peer!r}; peers are {PEERS}")
    t = cfg["train"]
    spec = {
        "peer": peer,
        "lambda": float(lam),
        "quality_start": float(t["quality_start"]),
        "quality_ramp": float(t["quality_ramp"]),
        "tau_scale": float(t["tau_scale"]),
        "distorted": bool(distorted),
        "variant": variant,
    }
    spec.update(variant_overrides(variant) if variant else {})
    return spec


def arm_name(spec: dict) -> str:
    """``l1``, ``l1+q0.2``, ``dist-ncc+q0.05``, ``l1+q0.2[tau_scale=2.0]``: file-name safe."""
    name = spec["peer"] + (f"+q{spec['lambda']:g}" if spec["lambda"] else "")
    if spec["variant"]:
        name += "[" + spec["variant"].replace(" ", "") + "]"
    return ("dist-" if spec["distorted"] else "") + name
