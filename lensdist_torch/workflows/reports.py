"""Reports of an evaluation: one method's figures on a test set, Markdown and JSON.

The paper's Tables 1 and 2 are shown beside ours; the JSON is strict (a missing figure is null).
Every term is defined under the table it appears in (:data:`TERMS`); :func:`report_summary` is
the short text a command prints (the headline table and its terms), the file holds the rest.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.geometry.distortion import CLASS_LABELS, REJECT
from lensdist_torch.metric.classification import ClassRMSE

#: The predicted-class index of "cannot tell" (after the classes 1-4 and R).
CANNOT_TELL = len(CLASS_LABELS)

__all__ = [
    "CANNOT_TELL",
    "PAPER",
    "TERMS",
    "evaluate_predictions",
    "json_safe",
    "md_goals",
    "dumps_strict",
    "report_markdown",
    "report_summary",
    "write_report",
]

# The paper's Table 1 (confusion matrices, rows 1-4, R) and Table 2 (RMSE of Delta_avg).
PAPER = {
    "table1": {
        "5ev_delta_max": {
            "rate": 62.8,
            "confusion": [
                [17, 7, 0, 0, 0],
                [6, 52, 11, 4, 0],
                [0, 25, 79, 26, 0],
                [1, 2, 30, 140, 0],
                [36, 20, 16, 2, 26],
            ],
        },
        "10ev_delta_max": {
            "rate": 66.4,
            "confusion": [
                [18, 5, 0, 1, 0],
                [6, 49, 13, 5, 0],
                [0, 33, 70, 27, 0],
                [0, 4, 22, 147, 0],
                [29, 1, 20, 2, 48],
            ],
        },
        "5ev_delta_avg": {
            "rate": 61.2,
            "confusion": [
                [23, 7, 1, 0, 0],
                [14, 56, 12, 5, 0],
                [1, 23, 115, 21, 0],
                [1, 2, 39, 80, 0],
                [45, 20, 3, 0, 32],
            ],
        },
        "10ev_delta_avg": {
            "rate": 67.8,
            "confusion": [
                [26, 4, 1, 0, 0],
                [8, 58, 18, 2, 1],
                [0, 23, 102, 32, 3],
                [0, 2, 32, 88, 0],
                [28, 3, 2, 2, 65],
            ],
        },
    },
    "table2_range_px": 30.0,
    "table2": {"5": [3.48, 4.73, 5.13, 4.85], "10": [3.56, 4.79, 5.19, 4.93]},
}


#: The ending of a setting's name answered under the config's own [analysis] (``reproduce``'s second decision).
SHIPPED_SUFFIX = ", shipped decision"

#: What each term of the reports means, shown where the term appears.
TERMS = {
    "EV": "the eigen-space classifier with 5 or 10 eigenvectors per class (the paper's settings); delta_max or "
          "delta_avg: the Delta its classes are binned on",
    "Delta": "how far the lens distortion moves a pixel: Delta_avg the mean over the frame, Delta_max the largest (px)",
    "rate": "right answers among all test pairs (\"cannot tell\" is not right)",
    "cannot tell": "share of the pairs answered \"cannot tell\" (too little evidence for a class)",
    "right among confident": "right answers among the pairs answered with a class (1-4 or R)",
    "confident wrong": "pairs answered with a wrong class",
    "R rejected": "class-R test pairs (no distortion; homography perturbed by 1 % per parameter) answered R, "
                  "i.e. rightly rejected as not distorted; the paper's of its 100",
    "registration failed": "pairs whose homography could not be estimated at generation (kept and analysed)",
    "t_y": "the pair's vertical translation (px); the distortion shows less when it is small",
    "RMSE": "root-mean-square error of the estimated Delta_avg against the truth, in px and as % of the class range",
    "bias": "mean of estimate - truth over all classes (px): > 0 overestimates",
    "right or cannot tell": "right answers plus \"cannot tell\", of all pairs: the answers that do not mislead",
    "RMSE on confident": "root-mean-square error of the estimated Delta over the distorted pairs answered with a "
                         "class, as % of the class range",
    "undistorted called R": "share of the class-R pairs answered R (R rejected, as a share)",
    "shipped decision": "the self-calibration's answers under the config's own [analysis] values (what analyze "
                        "answers without --config), from the same fits as the row without it, whose decision was "
                        "fitted on the validation split",
    "ECE": "expected calibration error of the confidence as an estimate of P(class right): the pair-weighted "
           "mean gap between confidence and share right in 10 bins; before: under the default decision, "
           "after: under the decision fitted on the validation split; lower is better",
}


def _terms(*names: str) -> list[str]:
    """Markdown lines that define ``names`` (keys of :data:`TERMS`)."""
    return ["Terms: " + "; ".join(f"**{n}**: {TERMS[n]}" for n in names) + ".", ""]


def json_safe(obj):
    """A copy of ``obj`` (dicts, lists, tuples, numbers, strings) with NaN and infinities as None.

    A missing figure is ``null`` in strict JSON, never ``NaN``.
    """
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def dumps_strict(obj, **kwargs) -> str:
    """``json.dumps`` of :func:`json_safe` (obj) with ``allow_nan=False``: valid for strict parsers."""
    return json.dumps(json_safe(obj), allow_nan=False, **kwargs)


def evaluate_predictions(
    pred_label: torch.Tensor,
    pred_delta: torch.Tensor,
    true_label: torch.Tensor,
    true_delta: torch.Tensor,
    *,
    delta_range: float,
    registration_ok: torch.Tensor | None = None,
    extra_groups: dict | None = None,
) -> dict:
    """One method's figures on a test set, "cannot tell" counted as its own outcome.

    Args:
        pred_label: (N,) predicted class indices 0..4 (1-4, R), or ``CANNOT_TELL``.
        pred_delta: (N,) predicted Delta (px); NaN where there is no estimate.
        true_label: (N,) ground-truth class indices 0..4.
        true_delta: (N,) true Delta (px).
        delta_range: the top of the class range (px), for the RMSE as a share of it.
        registration_ok: (N,) bool, counted as ``registration_failed``.
        extra_groups: {name: (N,) mask}: the rate per group.

    Returns:
        ``confusion`` (5 x 6: rows truth 1-4, R; columns predicted 1-4, R, cannot tell),
        ``rate`` (% right of all pairs), ``cannot_tell_share`` (%), ``confident_share`` (%),
        ``confident_rate`` (% right among the confident answers), ``confident_wrong`` (pairs
        answered with a wrong class), RMSE and bias per class over the pairs with an estimate
        (``n_per_class``), and more.
    """
    pred_label, true_label = pred_label.reshape(-1).long().cpu(), true_label.reshape(-1).long().cpu()
    k = len(CLASS_LABELS)
    if bool(((pred_label < 0) | (pred_label > CANNOT_TELL)).any()) or bool(
        ((true_label < 0) | (true_label >= k)).any()
    ):
        raise ValueError(
            f"predicted classes must lie in 0..{CANNOT_TELL} (the last: cannot tell), true ones in 0..{k - 1}"
        )
    conf = torch.bincount(true_label * (k + 1) + pred_label, minlength=k * (k + 1)).view(k, k + 1)
    confident = pred_label != CANNOT_TELL
    right = int(conf[:, :k].diag().sum())
    total, n_conf = int(conf.sum()), int(confident.sum())
    has = torch.isfinite(pred_delta.double().reshape(-1).cpu())
    rm = ClassRMSE()
    if bool(has.any()):
        rm.update(pred_delta.reshape(-1).cpu()[has], true_delta.reshape(-1).cpu()[has], true_label[has])
    r = rm.compute()
    nan = float("nan")
    out = {
        "confusion": conf.tolist(),
        "rate": 100.0 * right / total if total else nan,
        "correct": right,
        "total": total,
        "cannot_tell": total - n_conf,
        "cannot_tell_share": 100.0 * (total - n_conf) / total if total else nan,
        "confident_share": 100.0 * n_conf / total if total else nan,
        "confident_rate": 100.0 * right / n_conf if n_conf else nan,
        "confident_wrong": n_conf - right,
        "distorted_rate": 100.0 * float(conf[:REJECT, :REJECT].diag().sum()) / max(1, int(conf[:REJECT].sum())),
        "rejected_R": int(conf[REJECT, REJECT]),
        "n_R": int(conf[REJECT].sum()),
        "rmse_px": r["rmse"],
        "rmse_pct": [100.0 * v / delta_range if not math.isnan(v) else nan for v in r["rmse"]],
        "bias_px": r["bias"],
        "n_per_class": r["n"],
        "delta_range_px": delta_range,
        "right_or_cannot_tell_share": 100.0 * (right + total - n_conf) / total if total else nan,
        "confident_rmse_pct": _confident_rmse_pct(pred_label, pred_delta, true_label, true_delta, delta_range),
    }
    if registration_ok is not None:
        out["registration_failed"] = int((~registration_ok.bool()).sum())
    if extra_groups:
        out["groups"] = {}
        for name, mask in extra_groups.items():
            m = mask.bool().cpu()
            out["groups"][name] = {
                "n": int(m.sum()),
                "rate": 100.0 * float((pred_label[m] == true_label[m]).double().mean()) if bool(m.any()) else nan,
                "cannot_tell_share": 100.0 * float((~confident[m]).double().mean()) if bool(m.any()) else nan,
            }
    return out


def _confident_rmse_pct(pred_label, pred_delta, true_label, true_delta, delta_range: float) -> float:
    """RMSE of Delta over the distorted pairs answered with a class (1-4 or R), % of the range."""
    err = pred_delta.double().reshape(-1).cpu() - true_delta.double().reshape(-1).cpu()
    sel = (pred_label != CANNOT_TELL) & (true_label != REJECT) & torch.isfinite(err)
    return 100.0 * float(err[sel].pow(2).mean().sqrt()) / delta_range if bool(sel.any()) else float("nan")


def md_goals(settings: dict) -> list[str]:
    """The trust table: per setting, the shares that say whether its answers can be relied on."""
    lines = ["| setting | right or cannot tell | cannot tell | right among confident | RMSE on confident "
             "(% of range) | undistorted called R | registration failed |", "|---|---|---|---|---|---|---|"]
    for name, fig in settings.items():
        r = 100.0 * fig["rejected_R"] / fig["n_R"] if fig.get("n_R") else float("nan")
        lines.append(
            f"| {name} | {_pct(fig.get('right_or_cannot_tell_share'))} | {_pct(fig.get('cannot_tell_share'))} | "
            f"{_pct(fig.get('confident_rate'))} | {_pct(fig.get('confident_rmse_pct'))} | {_pct(r)} | "
            f"{fig.get('registration_failed', '-')} |"
        )
    return lines + [""]


def _md_confusion(conf) -> list[str]:
    cols = list(CLASS_LABELS) + (["cannot tell"] if len(conf[0]) > len(CLASS_LABELS) else [])
    lines = ["| truth \\ pred | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for lab, row in zip(CLASS_LABELS, conf):
        lines.append(f"| {lab} | " + " | ".join(str(int(v)) for v in row) + " |")
    return lines


def _pct(v) -> str:
    return f"{v:.1f} %" if isinstance(v, (int, float)) and math.isfinite(v) else "-"


def _md_calibration(cal: dict) -> list[str]:
    """The calibration section: the fitted decision and the ECE before and after, per split."""
    lines = ["## Calibration of the decision and the confidence", "", str(cal.get("note", "")), ""]
    fitted = cal.get("analysis", {})
    if fitted:
        lines += [
            "Fitted on the validation split ([analysis]): " + ", ".join(f"{k} = {v:.4g}" for k, v in fitted.items()),
            "",
        ]
    lines += ["| method | split | pairs | ECE before | ECE after |", "|---|---|---|---|---|"]
    for row in cal.get("ece", []):
        lines.append(
            f"| {row['method']} | {row['split']} | {row['pairs']} | "
            f"{_pct(100 * row['before'])} | {_pct(100 * row['after'])} |"
        )
    if cal.get("intervals"):
        lines += [
            "",
            "| self-calibration intervals | pairs | coverage before | coverage after | nominal |",
            "|---|---|---|---|---|",
        ]
        for row in cal["intervals"]:
            lines.append(
                f"| {row['split']} | {row['pairs']} | {_pct(100 * row['before'])} | {_pct(100 * row['after'])} | "
                f"{_pct(100 * row['nominal'])} |"
            )
    return lines + [""] + _terms("ECE")


def report_markdown(report: dict) -> str:
    """Markdown for a report {'title', 'settings': {name: figures}, 'paper': bool, ...}."""
    lines = [f"# {report.get('title', 'lensdist evaluation')}", ""]
    for key in ("protocol", "notes"):
        if report.get(key):
            lines += [str(report[key]), ""]
    settings = report["settings"]
    lines += [
        "## Table 1: classification",
        "",
        "Every pair is answered with a class or \"cannot tell\"; the rate counts right answers among all pairs.",
        "",
        "| setting | ours: rate | cannot tell | right among confident | confident wrong | ours: R rejected "
        "| paper: rate | paper: R rejected | registration failed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, fig in settings.items():
        paper = PAPER["table1"].get(fig.get("paper_key", ""), None)
        p_rate = f"{paper['rate']:.1f} %" if paper else "-"
        p_rej = f"{paper['confusion'][4][4]} of 100" if paper else "-"
        lines.append(
            f"| {name} | {_pct(fig['rate'])} ({fig['correct']}/{fig['total']}) | "
            f"{_pct(fig.get('cannot_tell_share'))} | {_pct(fig.get('confident_rate'))} | "
            f"{fig.get('confident_wrong', '-')} | {fig['rejected_R']} of {fig['n_R']} | "
            f"{p_rate} | {p_rej} | {fig.get('registration_failed', '-')} |"
        )
    lines.append("")
    lines += _terms("EV", "rate", "cannot tell", "right among confident", "confident wrong", "R rejected",
                    "registration failed")
    lines += ["Confusion matrices: rows the true class (1-4 by Delta, R no distortion), columns the answer.", ""]
    for name, fig in settings.items():
        lines += [f"### {name}", ""] + _md_confusion(fig["confusion"]) + [""]
        paper = PAPER["table1"].get(fig.get("paper_key", ""), None)
        if paper:
            lines += [f"Paper ({fig['paper_key']}):", ""] + _md_confusion(paper["confusion"]) + [""]
        if fig.get("cannot_tell_reasons"):
            lines.append("\"Cannot tell\" by reason (a pair may have several): "
                         + ", ".join(f"{code} {n}" for code, n in fig["cannot_tell_reasons"].items()))
            lines.append("")
        if fig.get("groups"):
            lines.append("Rate by group (t_y: the vertical translation): "
                         + ", ".join(f"{g}: {_pct(v['rate'])} (n={v['n']})" for g, v in fig["groups"].items()))
            lines.append("")
    lines += [
        "## Table 2: RMSE of Delta per ground-truth class",
        "",
        "Over the pairs with an estimate (a \"cannot tell\" keeps its numbers where it has them).",
        "",
        "| setting | class 1 | class 2 | class 3 | class 4 | range | bias (mean) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, fig in settings.items():
        cells = [
            f"{px:.2f} px ({pct:.1f} %)" if math.isfinite(px) else "-"
            for px, pct in zip(fig["rmse_px"], fig["rmse_pct"])
        ]
        bias = sum(b * n for b, n in zip(fig["bias_px"], fig["n_per_class"]) if n) / max(1, sum(fig["n_per_class"]))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | ]0, {fig['delta_range_px']:.1f}] px | {bias:+.2f} px |")
    for ev, vals in PAPER["table2"].items():
        cells = [f"{v:.2f} px ({100 * v / PAPER['table2_range_px']:.1f} %)" for v in vals]
        lines.append(f"| paper, {ev} EV, Delta_avg | " + " | ".join(cells) + " | ]0, 30] px | - |")
    lines.append("")
    lines += _terms("RMSE", "bias", "Delta")
    lines += ["## Can the answers be trusted?", "",
              "Right or cannot tell: right answers plus \"cannot tell\", of all pairs; RMSE over the distorted pairs "
              "answered with a class; undistorted called R: of the class-R pairs.", ""] + md_goals(settings)
    lines += _terms("right or cannot tell", "RMSE on confident", "undistorted called R", "registration failed",
                    *(["shipped decision"] if any(n.endswith(SHIPPED_SUFFIX) for n in settings) else []))
    unseen = report.get("unseen")
    if unseen:
        lines += [
            f"## On a scene no method was fitted on: {', '.join(unseen['scenes'])}",
            "",
            str(unseen.get("note", "")),
            "",
        ]
        lines += ["Columns as in \"Can the answers be trusted?\" above.", ""] + md_goals(unseen["settings"])
        for name, fig in unseen["settings"].items():
            lines += [f"### {name} (unseen scene)", ""] + _md_confusion(fig["confusion"]) + [""]
    if report.get("calibration"):
        lines += _md_calibration(report["calibration"])
    return "\n".join(lines)


def report_summary(report: dict, full_report: str | Path | None = None) -> str:
    """The short text a command prints (about 25 lines): the headline table, its terms, the file.

    One row per setting (rate, cannot tell, right among confident, R rejected, each with the
    paper's where it has one; RMSE on the confident answers), one line for the unseen scene and
    one for the calibration, every term defined; the confusion matrices, Table 2 and the rest
    stay in the file, named on the last line.
    """
    lines = [str(report.get("title", "lensdist evaluation"))]
    if report.get("protocol"):
        lines.append(str(report["protocol"]))
    lines += [
        "",
        "| setting | rate (paper) | cannot tell | right among confident | R rejected (paper) | RMSE on confident |",
        "|---|---|---|---|---|---|",
    ]
    for name, fig in report["settings"].items():
        paper = PAPER["table1"].get(fig.get("paper_key", ""), None)
        p_rate, p_rej = (f" ({paper['rate']:.1f} %)", f" ({paper['confusion'][4][4]} of 100)") if paper else ("", "")
        lines.append(f"| {name} | {_pct(fig['rate'])}{p_rate} | {_pct(fig.get('cannot_tell_share'))} | "
                     f"{_pct(fig.get('confident_rate'))} | {fig['rejected_R']} of {fig['n_R']}{p_rej} | "
                     f"{_pct(fig.get('confident_rmse_pct'))} |")
    lines.append("")
    unseen = report.get("unseen")
    if unseen:
        shares = ", ".join(f"{n} {_pct(f.get('right_or_cannot_tell_share'))}" for n, f in unseen["settings"].items())
        lines.append(
            f"On {', '.join(unseen['scenes'])}, a scene no method was fitted on, right or cannot tell: {shares}."
        )
    ece = [r for r in report.get("calibration", {}).get("ece", []) if r.get("split") == "test"]
    if ece:
        lines.append(
            "ECE on the test pairs, before -> after the fitted decision: "
            + ", ".join(f"{r['method']} {_pct(100 * r['before'])} -> {_pct(100 * r['after'])}" for r in ece)
            + "."
        )
    used = ["EV", "rate", "cannot tell", "right among confident", "R rejected", "RMSE on confident"]
    used += (["right or cannot tell"] if unseen else []) + (["ECE"] if ece else [])
    lines += [""] + [f"{n}: {TERMS[n]}." for n in used]
    if full_report is not None:
        lines += [
            "",
            f"Full report (confusion matrices, Table 2: RMSE per class, each term where it appears): {full_report}",
        ]
    return "\n".join(lines) + "\n"


def write_report(report: dict, out: str | Path, stem: str = "report") -> tuple[Path, Path]:
    """Write ``stem.md`` and ``stem.json`` (strict JSON: a missing figure is null) atomically under ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for suffix, text in ((".md", report_markdown(report)), (".json", dumps_strict(report, indent=2) + "\n")):
        path = out / f"{stem}{suffix}"
        atomic_write_text(path, text)
        paths.append(path)
    return paths[0], paths[1]
