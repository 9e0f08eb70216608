"""A run's folder, as the backend writes it and the add-on reads it::

    RUN/config.json          dataset, seed, device, the full training config, decisions made
    RUN/events.jsonl         the training events, one JSON object a line (training_events)
    RUN/checkpoint.pt        the latest checkpoint, replaced atomically
    RUN/preview.png          the latest validation render
    RUN/renders/SPLIT/       rendered views; RUN/metrics.json from ``eval``
    RUN/animation/CAMERA/    a camera path's frames, video and animation.json (``render --camera-path``)
    RUN/asset/nerf_asset.glb the baked asset (``export``) and its record, nerf_asset.glb.json
    RUN/asset/renders/ENGINE/ the asset rendered by Blender from the test cameras (``datasets_gen
                             --render-asset``: STEM.png, asset_render.json) and scored (``eval
                             --dataset D --renders DIR``: metrics.json); ENGINE cycles or eevee
    RUN/report/index.html    the comparison page (``report``)

and what ``compare`` and ``render --camera-path`` write into their ``--out`` folder::

    OUT/compare.json, OUT/difference.png, OUT/side_by_side.png
    OUT/animation.json, OUT/frames/
"""

CONFIG_NAME = "config.json"
EVENTS_NAME = "events.jsonl"
CHECKPOINT_NAME = "checkpoint.pt"
PREVIEW_NAME = "preview.png"
RENDERS_DIR = "renders"
ANIMATIONS_DIR = "animation"  # RUN/animation/CAMERA: a camera path's renders by default
METRICS_NAME = "metrics.json"
REPORT_DIR = "report"
REPORT_INDEX = "index.html"

COMPARE_NAME = "compare.json"
DIFFERENCE_NAME = "difference.png"
SIDE_BY_SIDE_NAME = "side_by_side.png"
ANIMATION_RECORD = "animation.json"
ANIMATION_FRAMES_DIR = "frames"

ASSET_DIR = "asset"  # RUN/asset: the Import NeRF Asset job's folder
ASSET_NAME = "nerf_asset.glb"
# ``export``'s record, ``ASSET.glb`` + this: rewritten after each of its stages with how many
# are done (ASSET_STAGES_DONE of ASSET_STAGES), and with ASSET_COMPLETE true once the asset is
# written; what a job watching the export reads.
ASSET_RECORD_SUFFIX = ".json"
ASSET_STAGES_DONE, ASSET_STAGES, ASSET_COMPLETE = "stages_done", "stages", "complete"
ASSET_RENDERS_DIR = "renders"
ASSET_ENGINES = ("cycles", "eevee")
ASSET_RENDER_RECORD = "asset_render.json"
