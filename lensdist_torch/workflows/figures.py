"""Figures (PNG). The only module that imports matplotlib, an optional extra (`.[plots]`)."""

from __future__ import annotations

import io
from pathlib import Path

import torch

from lensdist_torch.core.storage import atomic_write_bytes

__all__ = [
    "MAP_UNITS",
    "figure_formats",
    "have_matplotlib",
    "save_demo_figure",
    "save_map_grid",
    "save_confusion",
    "save_eigenvectors",
    "save_curves",
    "save_reliability",
]


def have_matplotlib() -> bool:
    """Whether matplotlib (the ``plots`` extra) is installed."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


MAP_UNITS = "share of error pixels per block"
_INVALID = "0.55"  # grey: blocks without a valid pixel, distinct from black "no error"


def figure_formats() -> list[str]:
    """The file suffixes a figure can be written as (``.png``, ``.pdf``, ``.svg``, ...)."""
    fig = _plt().figure()
    try:
        return sorted("." + ext for ext in fig.canvas.get_supported_filetypes())
    finally:
        _plt().close(fig)


def _save(fig, path: str | Path) -> Path:
    """Write atomically, in the format the suffix names (PNG without one).

    A half-written figure never replaces a good one, and a .jpg holds JPEG bytes, not PNG.
    """
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".") or "png"
    try:
        if fmt not in fig.canvas.get_supported_filetypes():
            raise ValueError(f"cannot write a figure as {path.name}: use one of {', '.join(figure_formats())}")
        buf = io.BytesIO()
        fig.savefig(buf, dpi=110, bbox_inches="tight", format=fmt)
    finally:
        _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def _block_mask(valid: torch.Tensor | None, maps: torch.Tensor) -> torch.Tensor | None:
    """(N, 1, h, w) True where a block has a valid pixel, from a block or pixel validity mask."""
    if valid is None:
        return None
    v = valid.detach().cpu().float().reshape(maps.shape[0], 1, *valid.shape[-2:])
    (h, w), (vh, vw) = maps.shape[-2:], v.shape[-2:]
    if (vh, vw) != (h, w):
        b = vh // h
        if b < 1 or vw // w != b or vh - h * b >= b or vw - w * b >= b:
            raise ValueError(
                f"valid must be block-sized {(h, w)} or pixel-sized (a block size times it), got {(vh, vw)}"
            )
        v = torch.nn.functional.max_pool2d(v[..., : h * b, : w * b], b)
    return v > 0


def _map_image(ax, m: torch.Tensor, ok: torch.Tensor | None):
    """One quality map on ``ax`` with the magma scale; blocks with no valid pixel in grey."""
    import matplotlib

    cmap = matplotlib.colormaps["magma"].with_extremes(bad=_INVALID)
    m = m.detach().cpu().float().clone()
    if ok is not None:
        m[~ok] = float("nan")
    return ax.imshow(m.numpy(), cmap=cmap, vmin=0, vmax=1)


def _map_colorbar(fig, im, axes, ok) -> None:
    label = MAP_UNITS + ("\n(grey: no valid pixel)" if ok is not None and not bool(ok.all()) else "")
    fig.colorbar(im, ax=axes, fraction=0.035, pad=0.02).set_label(label, fontsize=8)


def save_demo_figure(
    img1: torch.Tensor,
    img2: torch.Tensor,
    qmap: torch.Tensor,
    path,
    *,
    title: str = "",
    valid: torch.Tensor | None = None,
) -> Path:
    """Two (1, 1, H, W) images and their (1, 1, h, w) quality map side by side.

    ``valid`` (block or pixel validity) greys out the blocks without a valid pixel.
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].imshow(img1[0, 0].detach().cpu().float().numpy(), cmap="gray", vmin=0, vmax=1)
    axes[0].set_title("I1")
    axes[1].imshow(img2[0, 0].detach().cpu().float().numpy(), cmap="gray", vmin=0, vmax=1)
    axes[1].set_title("I2 registered")
    ok = _block_mask(valid, qmap)
    im = _map_image(axes[2], qmap[0, 0], None if ok is None else ok[0, 0])
    axes[2].set_title("registration-error map")
    _map_colorbar(fig, im, axes[2], ok)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_map_grid(
    maps: torch.Tensor,
    labels: list[str],
    path,
    *,
    title: str = "",
    valid: torch.Tensor | None = None,
    classes: list[str] | None = None,
) -> Path:
    """A row of (N, 1, h, w) quality maps with a label each (the paper's Fig. 1).

    Args:
        maps: (N, 1, h, w) quality maps in [0, 1].
        labels: one title per map.
        path: the file to write; its suffix names the format.
        title: the figure's title.
        valid: optional (N, 1, h, w) block validity, or a pixel validity mask a whole multiple
            of that size; blocks without a valid pixel are grey, not black ("no error").
        classes: optional class label per map ("1"-"4" or "R"), put before its label; class R
            reads "class R (no distortion)".
    """
    plt = _plt()
    n = maps.shape[0]
    if len(labels) != n or (classes is not None and len(classes) != n):
        raise ValueError(f"need one label (and class) per map: {n} maps, {len(labels)} labels")
    ok = _block_mask(valid, maps)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n + 0.8, 2.8), squeeze=False)
    for i, (ax, m, lab) in enumerate(zip(axes[0], maps, labels)):
        im = _map_image(ax, m[0], None if ok is None else ok[i, 0])
        if classes is not None:
            c = classes[i]
            lab = f"class {c}" + (" (no distortion)" if c == "R" else "") + (f"\n{lab}" if lab else "")
        ax.set_title(lab, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    _map_colorbar(fig, im, list(axes[0]), ok)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_confusion(confusion: torch.Tensor, labels, path, title: str = "") -> Path:
    """A (C, C) confusion matrix, rows ground truth, columns predicted; white counts on dark cells."""
    plt = _plt()
    conf = confusion.detach().cpu()
    fig, ax = plt.subplots(figsize=(4.6, 3.8))
    im = ax.imshow(conf.float().numpy(), cmap="Blues", vmin=0)
    top = float(conf.max()) or 1.0
    for i in range(conf.shape[0]):
        for j in range(conf.shape[1]):
            v = int(conf[i, j])
            ax.text(j, i, v, ha="center", va="center", fontsize=9, color="white" if v > 0.5 * top else "black")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("predicted")
    ax.set_ylabel("ground truth")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04).set_label("test pairs", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def save_eigenvectors(vectors: dict[str, torch.Tensor], shape: tuple[int, int], path, title: str = "") -> Path:
    """Rows of eigenvectors (name -> (k, h*w)) shown as maps (the paper's Fig. 3).

    Each has its own symmetric scale and a colour bar (unit-norm eigenvectors: a weight per block).
    """
    plt = _plt()
    names = list(vectors)
    k = max(v.shape[0] for v in vectors.values())
    fig, axes = plt.subplots(len(names), k, figsize=(3.0 * k, 2.2 * len(names)), squeeze=False)
    for r, name in enumerate(names):
        for c in range(k):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if c < vectors[name].shape[0]:
                v = vectors[name][c].detach().reshape(shape).cpu().float()
                lim = float(v.abs().max()) or 1.0
                im = ax.imshow(v.numpy(), cmap="RdBu_r", vmin=-lim, vmax=lim)
                ax.set_title(f"{name} EV{c + 1}", fontsize=8)
                cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
                cb.ax.tick_params(labelsize=6)
                if c == vectors[name].shape[0] - 1:
                    cb.set_label("weight per block", fontsize=7)
            else:
                ax.axis("off")
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_curves(
    curves: dict[str, list[float]], path, *, xlabel: str = "step", ylabel: str = "loss", title: str = ""
) -> Path:
    """Line plot of named series."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for name, ys in curves.items():
        ax.plot(range(1, len(ys) + 1), ys, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.legend()
    if title:
        ax.set_title(title)
    return _save(fig, path)


def save_reliability(curves: dict[str, dict], path, title: str = "") -> Path:
    """A reliability diagram: share right against confidence, per named curve, with the pairs per bin.

    Each curve is a dict with ``confidence`` and ``accuracy`` (per bin; NaN for an empty bin),
    ``n`` (pairs per bin) and ``ece``, as ``workflows.confidence.reliability`` returns it. A
    calibrated confidence lies on the diagonal.
    """
    plt = _plt()
    fig, (ax, axn) = plt.subplots(2, 1, figsize=(4.8, 5.6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="calibrated")
    width = 1.0 / (len(next(iter(curves.values()))["n"]) if curves else 10)
    for k, (name, c) in enumerate(curves.items()):
        conf, acc, n = c["confidence"], c["accuracy"], c["n"]
        pts = [(x, y) for x, y, m in zip(conf, acc, n) if m and x is not None and y is not None and x == x and y == y]
        ece = c.get("ece")
        label = f"{name} (ECE {100 * ece:.1f} %)" if isinstance(ece, float) and ece == ece else name
        ax.plot([x for x, _ in pts], [y for _, y in pts], marker="o", markersize=4, label=label)
        shift = (k - (len(curves) - 1) / 2) * width / max(1, len(curves))
        axn.bar([(i + 0.5) * width + shift for i in range(len(n))], n, width=width / max(1, len(curves)), alpha=0.8)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_ylabel("share right")
    ax.legend(fontsize=7, loc="upper left")
    axn.set_xlabel("confidence")
    axn.set_ylabel("pairs")
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)
