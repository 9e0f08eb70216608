"""The report's pictures drawn with matplotlib: training curves, the error colour scale, and the
NeRF's surface coloured by its distance to the true one."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from nerf_contract.training_events import Collapse, Event, Train, Val

from ..core.plotting import pyplot
from .error_images import ERROR_COLOURMAP, ERROR_SCALE


def plot_error_scale(path: Path) -> None:
    plt = pyplot()

    figure, axis = plt.subplots(figsize=(4.0, 0.9), dpi=100)
    axis.imshow(np.linspace(0, 1, 256)[None, :], aspect="auto", cmap=ERROR_COLOURMAP, extent=(0, ERROR_SCALE, 0, 1))
    axis.set_yticks([])
    axis.set_xlabel("mean |render − ground truth| per pixel (RGB in [0, 1])", fontsize=7)
    axis.tick_params(labelsize=7)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def plot_training(events: list[Event], path: Path) -> bool:
    """Loss and PSNR against iterations and against training seconds; False if no events."""
    train = [e for e in events if isinstance(e, Train)]
    val = [e for e in events if isinstance(e, Val)]
    if not train:
        return False
    plt = pyplot()

    figure, axes = plt.subplots(2, 2, figsize=(9, 6), dpi=100)
    for column, (key, label) in enumerate((("iteration", "iteration"), ("elapsed_s", "training time (s)"))):
        loss_axis, psnr_axis = axes[0, column], axes[1, column]
        loss_axis.plot([getattr(e, key) for e in train], [e.loss for e in train], linewidth=0.8)
        loss_axis.set_yscale("log")
        loss_axis.set_ylabel("training loss (MSE)")
        psnr_axis.plot([getattr(e, key) for e in train], [e.psnr for e in train], linewidth=0.8, label="training batch")
        if val:
            psnr_axis.plot([getattr(e, key) for e in val], [e.psnr for e in val], marker="o", label="validation view")
            blank = [e for e in val if e.blank_psnr is not None and math.isfinite(e.blank_psnr)]
            if blank:  # what an empty model scores on the same views: the collapse guard's floor
                psnr_axis.plot([getattr(e, key) for e in blank], [e.blank_psnr for e in blank], linestyle="--",
                               color="grey", linewidth=0.8, label="blank image, same view")
        for event in (e for e in events if isinstance(e, Collapse)):
            psnr_axis.axvline(getattr(event, key), color="#c0392b", linewidth=0.8)  # where the guard found a collapse
        psnr_axis.set_ylabel("PSNR (dB)")
        psnr_axis.legend(fontsize=8)
        for axis in (loss_axis, psnr_axis):
            axis.set_xlabel(label)
            axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
    return True


# Orthographic views of the NeRF frame (z up): (title, horizontal axis, vertical axis, the axis
# the view looks along, the side of it the viewer stands on).
SURFACE_VIEWS = (("front (from −y)", 0, 2, 1, -1.0), ("side (from +x)", 1, 2, 0, 1.0), ("top (from +z)", 0, 1, 2, 1.0))
SURFACE_ERROR_SCALE = 3.0  # colours run to this many τ


def plot_surface_error(path: Path, points: np.ndarray, distances: np.ndarray, true_points: np.ndarray,
                       tau: float) -> None:
    """The NeRF's surface ``points`` coloured by their ``distances`` to the truth (up to 3 τ),
    drawn far to near over the truth's points in grey, from three orthographic views."""
    plt = pyplot()

    figure, axes = plt.subplots(1, len(SURFACE_VIEWS), figsize=(12, 4.2), dpi=110, layout="constrained")
    low = np.minimum(points.min(axis=0), true_points.min(axis=0))
    high = np.maximum(points.max(axis=0), true_points.max(axis=0))
    for axis, (title, u, v, depth, viewer) in zip(axes, SURFACE_VIEWS):
        axis.scatter(true_points[:, u], true_points[:, v], s=0.4, c="#cfcfcf", linewidths=0, rasterized=True)
        order = np.argsort(viewer * points[:, depth])  # the farthest first: nearer points cover them
        shown = axis.scatter(points[order, u], points[order, v], s=1.0, c=distances[order] / tau, cmap="plasma",
                             vmin=0.0, vmax=SURFACE_ERROR_SCALE, linewidths=0, rasterized=True)
        axis.set_xlim(low[u], high[u])
        axis.set_ylim(low[v], high[v])
        axis.set_aspect("equal")
        axis.set_title(title, fontsize=9)
        axis.set_xticks([])
        axis.set_yticks([])
    bar = figure.colorbar(shown, ax=list(axes), shrink=0.8)
    bar.set_label(f"distance of the NeRF's surface to the truth, in τ = {tau:.4g}; grey: the truth", fontsize=8)
    figure.savefig(path)
    plt.close(figure)
