"""``lensdist reproduce``: the paper's Tables 1 and 2 beside ours, one command.

Generates the paper's sets, fits every method, fits the decision (the R threshold and the
confidence maps) on a validation split, and reports every method's figures on the test pairs
as the user's analysis answers them (:func:`~lensdist_torch.workflows.analyze.analyze_batch`),
with the calibration's ECE and reliability diagrams; then the same on the test pairs rendered
on ``protocol.unseen_scenes``, a scene no method was fitted on.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.shards import generate, load_scenes, load_set
from lensdist_torch.metric.quality import counts_to_map
from lensdist_torch.workflows.decision_fit import calibration_table, coverage_row, fit_confidence
from lensdist_torch.workflows.evaluate import (
    analyze_test_set,
    evaluate_classifier,
    evaluate_regressor,
    evaluate_selfcal,
    fit_classifier,
    fit_regressor,
    training_extra,
)
from lensdist_torch.workflows.reports import SHIPPED_SUFFIX, write_report

__all__ = ["reproduce", "SETTINGS", "quick_config"]

#: The paper's four settings: (eigenvectors, metric), as in its Table 1 (docs/method.md, section 9).
SETTINGS = [(5, "delta_max"), (10, "delta_max"), (5, "delta_avg"), (10, "delta_avg")]
#: The run of the self-calibration under the config's own decision, beside the one fitted on the validation split.
SHIPPED = f"selfcal{SHIPPED_SUFFIX}"


def quick_config(config: LensdistConfig, fraction: float = 0.1) -> LensdistConfig:
    """A tenth (by default) of every set, for a first look."""
    p = config.protocol
    return dataclasses.replace(
        config,
        protocol=dataclasses.replace(
            p,
            n_train=max(100, int(p.n_train * fraction)),
            n_test_distorted=max(20, int(p.n_test_distorted * fraction)),
            n_test_undistorted=max(5, int(p.n_test_undistorted * fraction)),
        ),
    )


def reproduce(
    config: LensdistConfig,
    out: str | Path,
    *,
    quick: bool = False,
    workers: int = 1,
    batch_size: int = 16,
    progress: bool = True,
    figures: bool = True,
    methods: bool = True,
    device=None,
    calibrate: bool = True,
) -> dict:
    """Generate the paper's sets, fit the four settings, and write the side-by-side report.

    With ``methods``, the regression and the self-calibration are evaluated on the same test
    pairs and reported beside the eigen-space settings; with ``calibrate`` too, the decision is
    first fitted on a validation split (:func:`fit_confidence`) and the test pairs are
    analysed under it. ``device`` is where the analysis runs.

    Example:
        A run generates thousands of pairs and fits every method (``quick``: a tenth of the pairs,
        a few minutes on 2 CPU cores; ``lensdist reproduce --quick``), too long for an example; here
        the pairs that ``quick`` keeps, and an argument refused before anything is written:

        >>> import tempfile
        >>> quick_config(LensdistConfig()).protocol.n_train
        1200
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     reproduce(LensdistConfig(), tmp, workers=0)
        Traceback (most recent call last):
        ...
        ValueError: workers must be a positive int, got 0
    """
    out = Path(out)
    if quick:
        config = quick_config(config)
    t0 = time.perf_counter()
    gen = generate(config, out / "data", workers=workers, batch_size=batch_size, progress=progress)
    t_gen = time.perf_counter() - t0
    train, test = load_set(out / "data", "train"), load_set(out / "data", "test")
    scenes, names = load_scenes(config)
    extra = training_extra(config, scenes, names)
    models = {}
    for n_ev, metric in SETTINGS:
        model = fit_classifier(train, config, n_eigenvectors=n_ev, metric=metric, extra=extra)
        models[f"{n_ev} EV, {metric}"] = model
        model.save(out / "checkpoints" / f"eigenspace_{metric}_{n_ev}ev.pt")
    runs = {f"{n} EV": {"method": "eigenspace", "checkpoint": models[f"{n} EV, delta_avg"],
                        "checkpoint_max": models[f"{n} EV, delta_max"]} for n in (5, 10)}
    cal, acfg, reg = None, config, None
    if methods:
        reg = fit_regressor(train, config, extra=extra)
        reg.save(out / "checkpoints" / "regression.pt")
        runs.update(regression={"method": "regression", "checkpoint": reg}, selfcal={"method": "selfcal"})
        if calibrate:
            cal = fit_confidence(config, out, regression=reg, scenes=scenes, workers=workers, batch_size=batch_size,
                                       progress=progress, device=device, figures=figures)
            acfg = cal["config"]
            # what analyze answers without --config: the same fits, the config's own [analysis]
            runs[SHIPPED] = {"method": "selfcal", "decision": config.analysis}
    results = analyze_test_set(test, runs, scenes, config=acfg, batch_size=batch_size, progress=progress, device=device)
    settings = _settings(models, reg, test, results, acfg)
    unseen = _unseen(config, out, runs, models, reg, acfg, workers, batch_size, progress, device)
    p = config.protocol
    report = {
        "title": "lensdist reproduce: the paper's Tables 1 and 2" + (" (quick: a tenth of the pairs)" if quick else ""),
        "protocol": (
            f"{p.n_train} training pairs, {p.n_test_distorted} distorted + {p.n_test_undistorted} class-R test pairs "
            f"on the scenes {list(p.scenes)}, {config.image.height} x {config.image.width}; "
            f"{_generation_note(gen, t_gen)}; "
            f"registration failed for {gen['sets']['train'].get('registration_failed', '?')} training "
            f"and {gen['sets']['test'].get('registration_failed', '?')} test pairs (at generation)."
        ),
        "notes": (
            "Every figure is what `lensdist analyze` answers on the test pairs (re-rendered from their seeds; the "
            "class-R pairs analysed with the protocol's perturbed registration). "
            "Delta_avg spans ]0, 14.4] px at this size (the paper's unnamed pixel selection spans ]0, 30]), "
            "so RMSE is also given as a share of each range."
        ),
        "settings": settings,
        "generation": gen,
    }
    if unseen is not None:
        report["unseen"] = unseen
    curves = {}
    if cal is not None:
        rows, curves = calibration_table(
            {k: results[k] for k in ("selfcal", "regression")}, test, before=config, after=acfg, split="test"
        )
        report["calibration"] = {
            "note": (
                f"Fitted on a validation split ({cal['validation_pairs']} pairs of the protocol with seed "
                f"{cal['validation_seed']}, never the test set); ECE of the confidence as an estimate of "
                "P(class right), 10 bins, over the pairs answered or withheld for low confidence (not those "
                "withheld for another reason: registration, overlap, motion, relief, domain); the "
                "self-calibration's interval coverage over the same pairs."
            ),
            "analysis": cal["analysis"],
            "ece": cal["ece"] + rows,
            "intervals": cal["intervals"]
            + [coverage_row(results["selfcal"], test, before=config, after=acfg, split="test")],
        }
    md, js = write_report(report, out, "reproduce")
    if figures:
        _figures(models, settings, test, config, out, curves)
    return {"markdown": str(md), "json": str(js), "settings": settings}


def _settings(models: dict, reg, test: dict, results: dict, config: LensdistConfig) -> dict:
    """Every method's figures on a test set, from the one analysis path's ``results``."""
    settings = {}
    for n_ev, metric in SETTINGS:
        other = models[f"{n_ev} EV, {'delta_avg' if metric == 'delta_max' else 'delta_max'}"]
        settings[f"{n_ev} EV, {metric}"] = evaluate_classifier(models[f"{n_ev} EV, {metric}"], test, partner=other,
                                                               results=results[f"{n_ev} EV"], config=config)
    if "regression" in results:
        for metric, fig in evaluate_regressor(reg, test, results=results["regression"], config=config).items():
            settings[f"regression, {metric}"] = fig
    for run, suffix in (("selfcal", ""), (SHIPPED, SHIPPED_SUFFIX)):
        if run in results:
            for metric, fig in evaluate_selfcal(test, config=config, results=results[run]).items():
                settings[f"selfcal, {metric}{suffix}"] = fig
    return settings


def _unseen(config, out: Path, runs, models, reg, acfg, workers, batch_size, progress, device) -> dict | None:
    """Every method, as fitted on the training scenes, on the test pairs of the unseen scenes.

    The test protocol rendered on ``protocol.unseen_scenes`` (the same draws, another scene) and
    analysed through the same path; None without such scenes.
    """
    p = config.protocol
    if not p.unseen_scenes:
        return None
    ucfg = dataclasses.replace(config, protocol=dataclasses.replace(p, scenes=p.unseen_scenes, unseen_scenes=()))
    gen = generate(ucfg, out / "unseen", sets=("test",), workers=workers, batch_size=batch_size, progress=progress)
    test = load_set(out / "unseen", "test")
    scenes, _ = load_scenes(ucfg)
    results = analyze_test_set(test, runs, scenes, config=dataclasses.replace(acfg, protocol=ucfg.protocol),
                               batch_size=batch_size, progress=progress, device=device)
    failed = gen["sets"]["test"].get("registration_failed", "?")
    return {
        "scenes": list(p.unseen_scenes),
        "note": (f"The {p.n_test_distorted} + {p.n_test_undistorted} test pairs drawn again (the same motions and "
                 f"distortions) on {', '.join(p.unseen_scenes)}, which no method was fitted on; the learned methods "
                 "should answer right or say cannot tell (out of domain). Registration failed for "
                 f"{failed} of them at generation."),
        "settings": _settings(models, reg, test, results, acfg),
    }


def _generation_note(gen: dict, seconds: float) -> str:
    """'generated N shards in T s', or 'reused N shards' when the data were on disk already."""
    total = sum(info.get("n_shards", 0) for info in gen["sets"].values())
    written = gen.get("written", 0)
    if written == 0:
        return f"reused {total} shards already on disk"
    reused = f", reused {total - written}" if total > written else ""
    return f"generated {written} shards in {seconds:.0f} s{reused}"


def _figures(models: dict, settings: dict, test: dict, config: LensdistConfig, out: Path, curves: dict) -> None:
    from lensdist_torch.workflows.figures import (
        have_matplotlib,
        save_confusion,
        save_eigenvectors,
        save_map_grid,
        save_reliability,
    )

    if not have_matplotlib():
        return
    from lensdist_torch.geometry.distortion import CLASS_LABELS

    hb, wb = config.image.height // config.quality.block_size, config.image.width // config.quality.block_size
    for name, fig in settings.items():
        stem = name.replace(", ", "_").replace(" ", "")
        conf = torch.tensor(fig["confusion"])  # 5 x 6: a last, empty truth row "?" makes it square
        conf = torch.cat([conf, torch.zeros(1, conf.shape[1], dtype=conf.dtype)])
        save_confusion(conf, list(CLASS_LABELS) + ["?"], out / f"confusion_{stem}.png", f"{name} (? = cannot tell)")
    if curves:
        save_reliability(curves, out / "reliability_test.png", "reliability on the test pairs")
    best = models.get("10 EV, delta_avg")
    if best is not None:
        vecs = {"class 1": best.bases[0, :4], "class 4": best.bases[-1, :4]}
        save_eigenvectors(vecs, (hb, wb), out / "eigenvectors_10ev_delta_avg.png", "first 4 eigenvectors (Fig. 3)")
    maps = counts_to_map(test["counts"], config.quality)
    order = torch.argsort(test["delta_avg"])
    distorted = order[test["delta_avg"][order] > 0]
    picks = [int(distorted[int(q * (len(distorted) - 1))]) for q in (0.1, 0.4, 0.7, 1.0)] if len(distorted) else []
    r_pairs = (test["delta_avg"] == 0).nonzero().flatten()
    if len(r_pairs):
        picks.append(int(r_pairs[0]))
    labels = [f"Delta_avg {float(test['delta_avg'][i]):.1f} px, vertical motion {float(test['motion'][i, 0]):.0f} px"
              for i in picks]
    classes = [CLASS_LABELS[int(test["class_avg"][i])] for i in picks]
    save_map_grid(maps[picks], labels, out / "maps_by_distortion.png", title="quality maps (Fig. 1)", classes=classes)
