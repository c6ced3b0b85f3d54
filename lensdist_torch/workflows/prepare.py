"""A batch of a user's pairs made ready for every analysis method: size, registration, quality map.

:func:`prepare_batch` brings pairs to the analysis size (a centred crop, then area resampling),
registers them, measures how far each moved (the registration's mean displacement) and computes
their quality maps; :class:`PreparedPairs` holds that, and computes on first use what several methods
share: the self-calibration of each pair (with its 95 % interval) and the texture histograms.
:func:`~lensdist_torch.workflows.analyze.analyze_batch` runs the methods on it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from pathlib import Path

import torch

from lensdist_torch.config import AnalysisConfig, LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.images import as_batch, check_image, load_image, resize_to, to_grey
from lensdist_torch.core.threads import torch_threads
from lensdist_torch.geometry.distortion import (
    CLASS_LABELS,
    delta_avg,
    distortion_type,
    estimated_class,
    from_normalized,
    pixel_offsets,
)
from lensdist_torch.geometry.homography import mean_displacement
from lensdist_torch.metric.quality import counts_to_map, registration_error_counts
from lensdist_torch.registration.direct import residual_limit, warp_to_reference
from lensdist_torch.registration.wide_baseline import estimate_homography_robust
from lensdist_torch.selfcal.fit import SelfCalInfo, estimate_distortion
from lensdist_torch.workflows.class_mass import delta_interval, scene_models
from lensdist_torch.workflows.texture import texture_histogram

__all__ = ["PreparedPairs", "prepare_batch", "resolve_device", "one_thread"]


def resolve_device(device=None) -> torch.device:
    """``None`` -> the CPU; a name or torch.device, checked: a clear ValueError when CUDA is absent."""
    try:
        dev = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"device {str(dev)!r} asked for, but CUDA is not available here (torch {torch.__version__}); "
                "use --device cpu"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(
                f"device {str(dev)!r} asked for, but only {torch.cuda.device_count()} CUDA device(s) exist"
            )
    return dev




def _as_images(img, name: str) -> list[torch.Tensor]:
    """A path, a tensor (H, W), (C, H, W), (B, C, H, W), or a list of paths / tensors -> per pair (1, 1, H, W) grey."""
    if isinstance(img, (list, tuple)):
        return [x for i, one in enumerate(img) for x in _as_images(one, f"{name}[{i}]")]
    if isinstance(img, (str, Path)):
        return [load_image(img, grey=True)]
    if isinstance(img, torch.Tensor) and img.device.type == "meta":
        raise ValueError(f"{name} is on the meta device (a shape, no values): give an image")
    if isinstance(img, torch.Tensor) and img.dim() == 4:
        check_image(img, name)
        return [to_grey(x[None]).float() for x in img]
    x = as_batch(img, name)
    check_image(x, name)
    return [to_grey(x).float()]


@dataclasses.dataclass
class PreparedPairs:
    """A batch brought to the analysis size and registered: what every method starts from.

    img1, img2: (B, 1, h, w) on the analysis device; H: (B, 3, 3) float64 img1 -> img2;
    registration_ok, residual, overlap: (B,); motion: (B,) the registration's mean displacement
    (analysis px, NaN without one); qmap: (B, 1, h/8, w/8); scale: user px per analysis px;
    input_size: per pair (H, W). The self-calibration and the texture histograms are
    computed once, on first use, and shared by every method run on this batch, and by its
    copies under another decision (:meth:`with_decision`).

    Example:
        >>> from lensdist_torch.core.images import load_scene
        >>> s = load_scene("gravel")
        >>> p = prepare_batch(s[..., :320, :424], s[..., 4:324, :424])
        >>> tuple(p.qmap.shape), bool(p.registration_ok[0]), round(float(p.motion[0]))
        ((1, 1, 40, 53), True, 4)
    """

    config: LensdistConfig
    img1: torch.Tensor
    img2: torch.Tensor
    H: torch.Tensor
    registration_ok: torch.Tensor
    residual: torch.Tensor
    overlap: torch.Tensor
    motion: torch.Tensor
    qmap: torch.Tensor
    scale: list
    input_size: list
    _selfcal: list | None = None
    # what does not depend on the decision, shared with the copies of with_decision:
    # {"selfcal": per-pair fits, "texture": the histograms}
    _shared: dict = dataclasses.field(default_factory=dict)

    def selfcal(self) -> list[dict]:
        """The self-calibration of every pair (started from the registration's H where it worked), under ``config``."""
        if self._selfcal is None:
            if "selfcal" not in self._shared:
                self._shared["selfcal"] = _selfcal_fits(self)
            self._selfcal = [_answer(fit, self.config) for fit in self._shared["selfcal"]]
        return self._selfcal

    def with_decision(self, analysis: AnalysisConfig) -> PreparedPairs:
        """This batch answered under another decision: ``analysis``, an ``[analysis]`` section.

        ``analysis`` is an :class:`~lensdist_torch.config.AnalysisConfig`. The registration, the quality
        maps and the self-calibration's fit are this batch's (fitted once, whichever copy asks first);
        only the answers (class, confidence, relief found, interval) follow the new section.
        ``reproduce`` reports the shipped decision beside the fitted one this way: the same fits,
        answered as ``analyze`` answers under each.

        Example:
            >>> import dataclasses
            >>> from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
            >>> frames, _ = synthetic_sequence(2, 3e-7, 0.0)  # a pan through a lens of Delta_avg ~1.2 px
            >>> p = prepare_batch(frames[0], frames[1])
            >>> strict = p.with_decision(dataclasses.replace(p.config.analysis, no_distortion_px=2.0))
            >>> a, b = p.selfcal()[0], strict.selfcal()[0]  # one fit, two R thresholds (0.75 and 2 px)
            >>> a["estimated_class"], b["estimated_class"], a["delta_avg"] == b["delta_avg"]
            ('1', 'R', True)

        Raises:
            TypeError: ``analysis`` is not an ``AnalysisConfig`` (a whole config is refused: only
                the decision may differ from the batch's).
        """
        if not isinstance(analysis, AnalysisConfig):
            raise TypeError(
                f"analysis (with_decision) must be an AnalysisConfig (a config's [analysis]), "
                f"got {type(analysis).__name__}"
            )
        return dataclasses.replace(self, config=dataclasses.replace(self.config, analysis=analysis), _selfcal=None)

    def texture(self) -> torch.Tensor:
        """(B, n) gradient-magnitude histograms of both images together."""
        if "texture" not in self._shared:
            self._shared["texture"] = 0.5 * (texture_histogram(self.img1) + texture_histogram(self.img2))
        return self._shared["texture"]


def prepare_batch(img1, img2, *, config: LensdistConfig | None = None, homography=None, device=None) -> PreparedPairs:
    """Bring pairs to the analysis size, register them and compute their quality maps.

    Args:
        img1: as for :func:`analyze_batch`.
        img2: as for :func:`analyze_batch`.
        config: settings (analysis size, registration, quality); the defaults when None.
        homography: optional (B, 3, 3) registrations img1 -> img2 at the analysis size, used
            instead of estimating them (the pairs count as registered).
        device: where the tensors go (default: the CPU).

    Example:
        >>> from lensdist_torch.core.images import load_scene
        >>> s = load_scene("grass")
        >>> p = prepare_batch(s[..., :320, :424], s[..., :320, 3:427])
        >>> [round(v, 1) for v in p.H[0, :2, 2].tolist()], float(p.overlap[0]) > 0.9  # 3 px to the left
        ([-3.0, 0.0], True)
    """
    cfg = or_defaults(config, LensdistConfig)
    dev = resolve_device(device)
    ones, twos = _as_images(img1, "img1"), _as_images(img2, "img2")
    if len(ones) != len(twos):
        raise ValueError(f"img1 and img2 must hold as many images, got {len(ones)} and {len(twos)}")
    h, w = cfg.image.size
    a, b, scale, sizes = [], [], [], []
    for x, y in zip(ones, twos):
        if x.shape[-2:] != y.shape[-2:]:
            raise ValueError(
                f"img1 and img2 must have the same size, got {tuple(x.shape[-2:])} and {tuple(y.shape[-2:])}"
            )
        oh, ow = x.shape[-2:]
        scale.append(min(ow / w, oh / h))  # user px per analysis px (the crop keeps the aspect)
        sizes.append([int(oh), int(ow)])
        a.append(resize_to(x.to(dev), h, w).clamp(0, 1))
        b.append(resize_to(y.to(dev), h, w).clamp(0, 1))
    a, b = torch.cat(a), torch.cat(b)
    n = a.shape[0]
    if homography is None:
        with one_thread(dev):
            regs = [estimate_homography_robust(a[g], b[g], config=cfg.registration, validate=False)
                    for g in _groups(dev, n)]
        H = torch.cat([r[0] for r in regs]).double()
        ok = torch.cat([r[1].converged for r in regs]).bool().cpu()
        residual = torch.cat([r[1].residual for r in regs]).float().cpu()
    else:
        H = torch.as_tensor(homography, dtype=torch.float64).to(dev)
        if H.shape != (n, 3, 3):
            raise ValueError(f"homography must be ({n}, 3, 3), got {tuple(H.shape)}")
        ok, residual = torch.isfinite(H).all(dim=(1, 2)).cpu(), torch.full((n,), float("nan"))
    finite = torch.isfinite(H).all(dim=(1, 2))[:, None, None]  # a missing registration warps by the identity
    warped, valid = warp_to_reference(
        b, torch.where(finite, H, torch.eye(3, dtype=H.dtype, device=dev)), validate=False
    )
    qmap = counts_to_map(registration_error_counts(a, warped, valid, config=cfg.quality, validate=False), cfg.quality)
    overlap = valid.flatten(1).float().mean(1).cpu()
    motion = mean_displacement(H, h, w).cpu()
    return PreparedPairs(
        config=cfg, img1=a, img2=b, H=H, registration_ok=ok, residual=residual, overlap=overlap, motion=motion,
        qmap=qmap, scale=scale, input_size=sizes)


def _batched(dev: torch.device) -> bool:
    """Whether the estimators take the batch together (:func:`_groups`): on a GPU."""
    return dev.type != "cpu"


def _groups(dev: torch.device, n: int, same=None) -> list:
    """How the estimators take a batch of ``n``: pair by pair on the CPU, together on a GPU.

    On the CPU, batched kernels round differently with the batch size: pair by pair, a pair's
    answer is the same to the bit alone or in a batch (``reproduce`` reports what ``analyze_pair``
    answers). A GPU's kernels round differently from the CPU's anyway (the answers agree to
    ~1e-3 px, ``benchmarks/bench_gpu.py``) and one call for the batch keeps it busy.

    Args:
        dev: the batch's device.
        n: the batch size.
        same: optional (n,) bool; on a GPU, the pairs where it is True and those where it is
            False go in separate calls (the self-calibration with and without a start).

    Returns:
        Slices (one pair each) on the CPU; index tensors on ``dev`` otherwise.
    """
    if not _batched(dev):
        return [slice(i, i + 1) for i in range(n)]
    keys = torch.ones(n, dtype=torch.bool) if same is None else torch.as_tensor(same, dtype=torch.bool).cpu()
    return [idx.to(dev) for idx in (keys.nonzero()[:, 0], (~keys).nonzero()[:, 0]) if idx.numel()]


@contextlib.contextmanager
def one_thread(dev: torch.device):
    """On the CPU, an analysis on one torch thread, the count restored after (a no-op on a GPU).

    The estimators take one pair at a time there (:func:`_groups`), and one pair's tensors are
    small (a 320 x 424 frame, a few thousand samples): a second thread halves little of each
    operation but meets the first at a barrier after every one, and on a machine whose cores are
    busy each such meeting waits for a time slice (docs/method.md, section 10). With one thread a
    pair's float32 reductions, and so its answer, no longer depend on the thread count either.
    """
    if _batched(dev):
        yield
        return
    with torch_threads(1):
        yield


def _selfcal_fits(p: PreparedPairs) -> list[tuple]:
    """Self-calibration of every pair, from the registration's H wherever finite: (k2, k4, info, aligned, motion) each.

    Also where the registration failed its own test: its H is still the nearest start on most
    such pairs, and beside it the phase-correlation start is fitted (``selfcal.fit.BOTH_STARTS``).
    The fit aligned the pair where it converged and its RMS residual (the lens and the photometry
    modelled; the worst ``selfcal.fit.OCCLUDED_SHARE`` of the frame's rectangles left out, where an
    occluder may be: ``aligned_residual``) passes the registration's own test
    (:func:`~lensdist_torch.registration.direct.residual_limit`).
    """
    cfg, n = p.config, p.img1.shape[0]
    start = torch.isfinite(p.H).all(dim=(1, 2)).cpu()
    limit = residual_limit(p.img1).cpu()
    out: list = [None] * n
    for g in _groups(p.img1.device, n, start):
        pairs = range(n)[g] if isinstance(g, slice) else g.tolist()
        init = p.H[g] if bool(start[pairs[0]]) else None
        with one_thread(p.img1.device):
            k2, k4, _, sc = estimate_distortion(p.img1[g], p.img2[g], init=init, config=cfg.selfcal, validate=False)
        k2, k4, sc = k2.cpu(), k4.cpu(), SelfCalInfo(*(f.cpu() for f in sc))  # one copy, not one per number
        for j, i in enumerate(pairs):
            one = SelfCalInfo(*(f[j : j + 1] for f in sc))
            # the registration's own residual test, passed with the lens and the photometry modelled
            aligned = bool(one.converged[0]) and float(one.aligned_residual[0]) <= float(limit[i])
            out[i] = (k2[j : j + 1], k4[j : j + 1], one, aligned, float(one.motion[0]))
    return out


def _answer(fit: tuple, cfg: LensdistConfig) -> dict:
    """One pair's self-calibration answer under ``cfg`` from its fit (:func:`_selfcal_fits`)."""
    k2, k4, one, aligned, motion = fit
    return _selfcal_answer(k2, k4, one, cfg) | {"_aligned": aligned, "_aligned_motion_px": motion}


def _selfcal_answer(k2: torch.Tensor, k4: torch.Tensor, sc: SelfCalInfo, cfg: LensdistConfig) -> dict:
    """One pair's answer from its self-calibration (k2, k4 and ``sc`` of a batch of one)."""
    if not bool(sc.converged[0]):  # flagged, never a number and never "R"
        return {"estimated_class": None, "estimated_class_max": None, "delta_avg": None, "delta_max": None,
                "raw_confidence": 0.0, "_diverged": True}
    h, w = cfg.image.size
    off = pixel_offsets(k2, k4, h, w).flatten(1)  # one map for both Deltas
    d_avg, d_max = off.mean(1), off.amax(1)
    label = CLASS_LABELS[int(estimated_class(d_avg, d_avg, metric="delta_avg", config=cfg)[0])]
    std = float(sc.delta_avg_std[0])  # the fit's own; analysis.interval_std_scale widens the interval
    out = {
        "estimated_class": label,
        "estimated_class_max": CLASS_LABELS[int(estimated_class(d_max, d_avg, metric="delta_max", config=cfg)[0])],
        "delta_avg": float(d_avg[0]),
        "delta_max": float(d_max[0]),
        "k2": float(k2[0]),
        "k4": float(k4[0]),
        "delta_avg_std": std,
        "delta_avg_interval": delta_interval(float(d_avg[0]), std, cfg.analysis),
        "relief": bool(sc.relief[0]),  # the plane + parallax model's answer kept (selfcal.fit.PARALLAX_TEST)
        "relief_z": float(sc.relief_z[0]),  # Hausman's statistic; NaN without that model
        "distortion_type": distortion_type(float(sc.ab[0, 0]), float(sc.ab[0, 1])),
    }
    return out | _two_models(out, sc, cfg)


def _two_models(out: dict, sc, cfg: LensdistConfig) -> dict:
    """``raw_confidence``, ``relief_found``, ``relief_agreement``, ``relief_parted`` of a pair; both answers if found.

    The models' class masses are :func:`~lensdist_torch.workflows.class_mass.scene_models`'.

    Where relief is found, both answers stay beside the "cannot tell" (``decision.decide``) as
    ``planar_delta_avg``, ``relief_delta_avg``, their intervals and the fit's own stds (given
    wherever the plane + parallax model converged).
    """
    size = cfg.image.size
    # the plane + parallax model is not fitted where selfcal.parallax = 0: its coefficients are NaN
    d0, d1 = (float(delta_avg(*from_normalized(ab, *size), *size)[0]) if bool(torch.isfinite(ab).all()) else math.nan
              for ab in (sc.planar_ab, sc.relief_ab))
    s0, s1 = float(sc.planar_std[0]), float(sc.relief_std[0])
    m = scene_models(out["estimated_class"], (d0, s0), (d1, s1), cfg)
    if not (math.isfinite(d1) and math.isfinite(s1)):
        return {"raw_confidence": m.confidence, "relief_found": False}
    both = {
        "relief_agreement": m.agreement,
        "relief_parted": m.parted,
        "planar_delta_avg": d0,
        "planar_delta_avg_std": s0,
        "planar_delta_avg_interval": delta_interval(d0, s0, cfg.analysis),
        "relief_delta_avg": d1,
        "relief_delta_avg_std": s1,
        "relief_delta_avg_interval": delta_interval(d1, s1, cfg.analysis),
    }
    return {"raw_confidence": m.confidence, "relief_found": m.relief_found, **both}
