"""The report's pictures drawn with matplotlib: training curves and the error colour scale."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

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


def plot_training(events: list[dict], path: Path) -> bool:
    """Loss and PSNR against iterations and against training seconds; False if no events."""
    train = [e for e in events if e.get("event") == "train"]
    val = [e for e in events if e.get("event") == "val"]
    if not train:
        return False
    plt = pyplot()

    figure, axes = plt.subplots(2, 2, figsize=(9, 6), dpi=100)
    for column, (key, label) in enumerate((("iteration", "iteration"), ("elapsed_s", "training time (s)"))):
        loss_axis, psnr_axis = axes[0, column], axes[1, column]
        loss_axis.plot([e[key] for e in train], [e["loss"] for e in train], linewidth=0.8)
        loss_axis.set_yscale("log")
        loss_axis.set_ylabel("training loss (MSE)")
        psnr_axis.plot([e[key] for e in train], [e["psnr"] for e in train], linewidth=0.8, label="training batch")
        if val:
            psnr_axis.plot([e[key] for e in val], [e["psnr"] for e in val], marker="o", label="validation view")
            blank = [e for e in val if e.get("blank_psnr") is not None and math.isfinite(e["blank_psnr"])]
            if blank:  # what an empty model scores on the same views: the collapse guard's floor
                psnr_axis.plot([e[key] for e in blank], [e["blank_psnr"] for e in blank], linestyle="--",
                               color="grey", linewidth=0.8, label="blank image, same view")
        for event in (e for e in events if e.get("event") == "collapse" and key in e):
            psnr_axis.axvline(event[key], color="#c0392b", linewidth=0.8)  # where the guard found a collapse
        psnr_axis.set_ylabel("PSNR (dB)")
        psnr_axis.legend(fontsize=8)
        for axis in (loss_axis, psnr_axis):
            axis.set_xlabel(label)
            axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
    return True
