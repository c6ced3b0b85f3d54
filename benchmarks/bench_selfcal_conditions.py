"""Self-calibration and registration under one condition at a time (docs/method.md, section 10).

Renders the test pairs (indices 0 .. n-1 of the 'test' set, all distorted) of one scene under a
config, registers them as the protocol does, and self-calibrates them from the registration's H
(as ``analyze``) with the default settings and with each ``--variant``. Per variant: RMSE, bias
(and bias where Delta_avg > 10 px) and largest error of Delta_avg, pairs more than 1 px off,
median |error| / std and the share within 2 std (is the std honest?), pairs below confidence
0.5, pairs/s. With ``--effects``: the registration failures of 96 training pairs with each
realistic effect alone.

    python benchmarks/bench_selfcal_conditions.py --scene brick --variant parallax_px=0.5
    python benchmarks/bench_selfcal_conditions.py --config configs/realistic.toml --set relief=0.03 \
        --only relief --variant parallax=0
    python benchmarks/bench_selfcal_conditions.py --config configs/realistic.toml --effects \
        [--registration chunk_size=4]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from lensdist_torch.config import LensdistConfig, load_config
from lensdist_torch.core.images import load_scene
from lensdist_torch.data import realism
from lensdist_torch.data.synthesis import make_pairs
from lensdist_torch.geometry.distortion import delta_avg
from lensdist_torch.selfcal.fit import estimate_distortion

#: Each realistic effect's "off" values: the constants of data/realism.py, and the config's relief.
EFFECTS_OFF = {
    "GAIN_RANGE": (1.0, 1.0), "OFFSET_RANGE": (0.0, 0.0), "GAMMA_RANGE": (1.0, 1.0), "ILLUMINATION": 0.0,
    "NOISE_RANGE": (0.0, 0.0), "JPEG_QUALITY": (100, 100), "relief": 0.0, "OCCLUDER_RATE": 0.0,
}
EFFECTS = {"gain+offset": ("GAIN_RANGE", "OFFSET_RANGE"), "gamma": ("GAMMA_RANGE",), "illumination": ("ILLUMINATION",),
           "noise+jpeg": ("NOISE_RANGE", "JPEG_QUALITY"), "relief": ("relief",), "occluder": ("OCCLUDER_RATE",)}
_ON = {k: getattr(realism, k) for k in EFFECTS_OFF if k != "relief"}  # the method's values

def _value(text: str):
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    parts = [float(x) for x in text.split(",")]
    parts = [int(x) if x.is_integer() else x for x in parts]
    return tuple(parts) if len(parts) > 1 else parts[0]


def with_only(cfg: LensdistConfig, keep: tuple[str, ...]) -> LensdistConfig:
    """The config with every realistic effect off except ``keep`` (realism's constants set in this process)."""
    for k, v in _ON.items():
        setattr(realism, k, v if k in keep else EFFECTS_OFF[k])
    relief = cfg.protocol.relief if "relief" in keep else 0.0
    return dataclasses.replace(cfg, protocol=dataclasses.replace(cfg.protocol, relief=relief))


def figures(cfg: LensdistConfig, scene: str, n: int, variants: dict) -> dict:
    cfg = dataclasses.replace(cfg, protocol=dataclasses.replace(cfg.protocol, scenes=(scene,), unseen_scenes=()))
    pb = make_pairs([load_scene(scene)], config=cfg, set_name="test", indices=list(range(n)), keep_images=True)
    true = pb.delta["delta_avg"].double()
    out = {"pairs": n, "registration_failed": int((~pb.converged).sum())}
    for name, sc in variants.items():
        t0 = time.perf_counter()
        k2, k4, _, info = estimate_distortion(pb.img1, pb.img2, init=pb.H, config=sc)
        seconds = time.perf_counter() - t0
        err = delta_avg(k2, k4, *cfg.image.size).double() - true
        ok = torch.isfinite(err)
        z = err.abs() / info.delta_avg_std.double()
        out[name] = {
            "rmse_px": float(err[ok].pow(2).mean().sqrt()),
            "bias_px": float(err[ok].mean()),
            "bias_over_10px": float(err[ok & (true > 10)].mean()),
            "max_abs_px": float(err[ok].abs().max()),
            "over_1px": int((err.abs() > 1).sum()),
            "median_err_over_std": float(z[ok].median()),
            "within_2_std": float((z[ok] < 2).double().mean()),
            "confidence_below_half": int((info.confidence < 0.5).sum()),
            "diverged": int((~ok).sum()),
            "pairs_per_s": n / seconds,
        }
    return out


def effects(cfg: LensdistConfig, n: int = 96) -> dict:
    scenes = [load_scene(s) for s in cfg.protocol.scenes]
    out = {}
    for name, keys in {**EFFECTS, "all": tuple(EFFECTS_OFF)}.items():
        pb = make_pairs(scenes, config=with_only(cfg, keys), set_name="train", indices=list(range(n)))
        out[name] = int((~pb.converged).sum())
    return {"pairs": n, "registration_failed": out}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=None, help="TOML config (default: the defaults)")
    ap.add_argument("--scene", default="gravel", help="embedded scene")
    ap.add_argument("--n", type=int, default=96, help="test pairs")
    ap.add_argument("--only", default="", help="comma-separated effects kept on: GAIN_RANGE, ..., relief")
    ap.add_argument("--set", action="append", default=[], help="protocol FIELD=VALUE (commas for pairs)")
    ap.add_argument("--registration", action="append", default=[], help="registration FIELD=VALUE")
    ap.add_argument(
        "--variant", action="append", default=[], help="selfcal FIELD=VALUE[,VALUE...][;FIELD=...] beside the default"
    )
    ap.add_argument("--effects", action="store_true", help="registration failures per realistic effect instead")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg = load_config(a.config) if a.config else LensdistConfig()
    sets = dict(item.split("=", 1) for item in a.set)
    cfg = dataclasses.replace(
        cfg, protocol=dataclasses.replace(cfg.protocol, **{k: _value(v) for k, v in sets.items()})
    )
    regs = dict(item.split("=", 1) for item in a.registration)
    cfg = dataclasses.replace(
        cfg, registration=dataclasses.replace(cfg.registration, **{k: _value(v) for k, v in regs.items()})
    )
    if a.only:
        cfg = with_only(cfg, tuple(a.only.split(",")))
    if a.effects:
        print(json.dumps(effects(cfg), indent=1))
        return
    variants = {"default": cfg.selfcal}
    for item in a.variant:  # FIELD=VALUE[;FIELD=VALUE...]
        fields = dict(part.split("=", 1) for part in item.split(";"))
        variants[item] = dataclasses.replace(cfg.selfcal, **{k: _value(v) for k, v in fields.items()})
    print(json.dumps({"threads": a.threads, "scene": a.scene, **figures(cfg, a.scene, a.n, variants)}, indent=1))


if __name__ == "__main__":
    main()
