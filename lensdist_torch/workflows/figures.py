"""Figures (PNG). The only module that imports matplotlib, an optional extra (`.[plots]`)."""

from __future__ import annotations

import io
from pathlib import Path

import torch

from lensdist_torch.core.storage import atomic_write_bytes

__all__ = ["have_matplotlib", "save_demo_figure", "save_map_grid", "save_confusion", "save_eigenvectors", "save_curves"]


def have_matplotlib() -> bool:
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


def _save(fig, path: str | Path) -> Path:
    """Write atomically: a half-written PNG never replaces a good one."""
    path = Path(path)
    buf = io.BytesIO()
    try:
        fig.savefig(buf, dpi=110, bbox_inches="tight", format="png")
    finally:
        _plt().close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def save_demo_figure(img1: torch.Tensor, img2: torch.Tensor, qmap: torch.Tensor, path, title: str = "") -> Path:
    """Two (1, 1, H, W) images and their (1, 1, h, w) quality map side by side."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    axes[0].imshow(img1[0, 0].cpu(), cmap="gray", vmin=0, vmax=1)
    axes[0].set_title("I1")
    axes[1].imshow(img2[0, 0].cpu(), cmap="gray", vmin=0, vmax=1)
    axes[1].set_title("I2 registered")
    im = axes[2].imshow(qmap[0, 0].cpu(), cmap="magma", vmin=0, vmax=1)
    axes[2].set_title("registration-error map")
    fig.colorbar(im, ax=axes[2], fraction=0.035)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_map_grid(maps: torch.Tensor, labels: list[str], path, title: str = "") -> Path:
    """A row of (N, 1, h, w) quality maps with a label each (the paper's Fig. 1)."""
    plt = _plt()
    n = maps.shape[0]
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 2.8), squeeze=False)
    for ax, m, lab in zip(axes[0], maps, labels):
        ax.imshow(m[0].cpu(), cmap="magma", vmin=0, vmax=1)
        ax.set_title(lab, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_confusion(confusion: torch.Tensor, labels, path, title: str = "") -> Path:
    """A (C, C) confusion matrix, rows ground truth, columns predicted."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.2, 3.8))
    ax.imshow(confusion.cpu(), cmap="Blues")
    for i in range(confusion.shape[0]):
        for j in range(confusion.shape[1]):
            ax.text(j, i, int(confusion[i, j]), ha="center", va="center", fontsize=9)
    ax.set_xticks(range(len(labels)), labels)
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("predicted")
    ax.set_ylabel("ground truth")
    if title:
        ax.set_title(title, fontsize=10)
    return _save(fig, path)


def save_eigenvectors(vectors: dict[str, torch.Tensor], shape: tuple[int, int], path, title: str = "") -> Path:
    """Rows of eigenvectors (name -> (k, h*w)) shown as maps (the paper's Fig. 3)."""
    plt = _plt()
    names = list(vectors)
    k = max(v.shape[0] for v in vectors.values())
    fig, axes = plt.subplots(len(names), k, figsize=(2.6 * k, 2.2 * len(names)), squeeze=False)
    for r, name in enumerate(names):
        for c in range(k):
            ax = axes[r][c]
            ax.set_xticks([])
            ax.set_yticks([])
            if c < vectors[name].shape[0]:
                v = vectors[name][c].reshape(shape).cpu()
                lim = float(v.abs().max()) or 1.0
                ax.imshow(v, cmap="RdBu_r", vmin=-lim, vmax=lim)
                ax.set_title(f"{name} EV{c + 1}", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def save_curves(curves: dict[str, list[float]], path, xlabel: str = "step", ylabel: str = "loss", title: str = "") -> Path:
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
