"""The report's page: its HTML skeleton, style and the script that sorts tables and counts
loaded images (checked in a real headless Chromium)."""

from __future__ import annotations

import html
import shutil
from pathlib import Path

import numpy as np

from ..core.files import write_png

MARKER = "<!-- written by python -m nerf_backend report -->"

STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; } td, th { padding: 0.25em 0.6em; border-bottom: 1px solid #eee;
  text-align: left; vertical-align: middle; }
th.sortable { cursor: pointer; color: #0645ad; } .num { text-align: right; font-variant-numeric: tabular-nums; }
.headline { display: flex; gap: 1em; flex-wrap: wrap; } .card { background: #f4f6f8; padding: 0.6em 1em; border-radius: 6px; }
.card b { display: block; font-size: 1.4em; } .muted { color: #666; font-size: 0.9em; }
img.wide, video.wide { width: 100%; max-width: 900px; display: block; }
img.thumb { width: 128px; height: auto; image-rendering: pixelated; border: 1px solid #ddd; display: block; }
figure { margin: 0; } figcaption { font-size: 0.75em; color: #555; }
.alert { background: #fdecea; border-left: 4px solid #c0392b; padding: 0.5em 1em; margin: 1em 0; }
"""

# Depth is the distance along each ray in the dataset's frame (after its world_to_nerf).

SORT_SCRIPT = """
document.querySelectorAll("table.views").forEach(function (table) {
  table.querySelectorAll("th.sortable").forEach(function (header) {
    header.addEventListener("click", function () {
      var key = header.dataset.key, body = table.tBodies[0];
      var ascending = header.dataset.order !== "asc";
      header.dataset.order = ascending ? "asc" : "desc";
      var rows = Array.prototype.slice.call(body.rows);
      rows.sort(function (a, b) {
        var x = parseFloat(a.dataset[key]), y = parseFloat(b.dataset[key]);
        if (isNaN(x)) x = Infinity; if (isNaN(y)) y = Infinity;
        return ascending ? x - y : y - x;
      });
      rows.forEach(function (row) { body.appendChild(row); });
    });
  });
});
window.addEventListener("load", function () {
  var broken = Array.prototype.filter.call(document.images, function (img) { return !img.complete || img.naturalWidth === 0; });
  document.body.dataset.imagesLoaded = String(document.images.length - broken.length);
  document.body.dataset.imagesBroken = String(broken.length);
});
"""


class ReportPage:
    """An HTML page being built in ``out_dir``, with its images beside it in ``images/``."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.images = out_dir / "images"
        self.parts: list[str] = []

    def add(self, markup: str) -> None:
        self.parts.append(markup)

    def image(self, name: str, pixels: np.ndarray | None = None, source: Path | None = None) -> str:
        """Write (or copy) an image next to the page; returns its relative path."""
        target = self.images / name
        if pixels is not None:
            write_png(target, pixels)
        elif source is not None:
            shutil.copyfile(source, target)
        return f"images/{name}"

    def figure(self, relative: str, caption: str, kind: str = "thumb") -> str:
        return (f'<figure><a href="{html.escape(relative)}" target="_blank"><img class="{kind}" src="{html.escape(relative)}" '
                f'alt="{html.escape(caption)}"></a><figcaption>{html.escape(caption)}</figcaption></figure>')

    def write(self, title: str) -> Path:
        document = (f'<!DOCTYPE html>\n{MARKER}\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
                    f"<style>{STYLE}</style></head><body>\n" + "\n".join(self.parts)
                    + f"\n<script>{SORT_SCRIPT}</script></body></html>\n")
        path = self.out_dir / "index.html"
        path.write_text(document, encoding="utf-8")
        return path
