"""Every rule that plans a run, in the order they decide (``RULES``, at the end): each a pure
function of the facts and the plan so far, yielding its proposals with their reasons
(``plan.Proposal``). Adding a rule is one function here and one entry in ``RULES``.

Rules for every start of a run (a resumed one too): the device, the time budget, the views,
the rays' bounds, the occupancy prior and the images' sizes. Rules that shape a new run's
preset to the scene (a resumed run keeps what they chose): ``auto``'s (Blender knows the
scene, and the dataset carries that knowledge, ``scene_profile.json``, along with the images),
the surface preset's softness and opacity, the plenoxels preset's grid.

The examples plan 100×100 views at radius 4 of a 2 × 2 × 0.5 box (``_example``), a pixel
0.0288 units across.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterator

import torch

from ..configs.train_config import SCHEDULES
from ..core.cameras import Intrinsics
from ..core.devices import choose_device
from ..core.errors import NerfError
from ..core.scene_bounds import SceneBounds, vertices_for
from ..data.dataset import DatasetSplit
from ..data.occupancy_prior import GLASS_MIN_WALL_SHARE, PRIOR_KINDS
from ..model_components.ray_bounds import choose_ray_bounds
from ..models.marched import FIT_MAX_KEPT, REFIT_MAX_KEPT
from ..models.registry import model_class
from .facts import RunFacts, RunRequest, starting_settings
from .footprint import MIN_RESOLUTION, finest_resolution, pixel_footprint, pixel_resolution
from .plan import Proposal, Rule, RunPlan, plan_run

# --- measured choices ---------------------------------------------------------------------
# The model auto trains, chosen by measurement against the others at equal time (the bench
# tables of docs/benchmarks_lego.md and docs/benchmarks_800px.md).
AUTO_MODEL = "grid"
AUTO_MODEL_REASON = (
    "the factorised grids (the fast preset's model), measured against the plenoxels preset (a sparse voxel grid "
    "of density and harmonics, no network) on lego at 800×800 on 2 CPU cores, they scored 28.04 dB after 2 minutes "
    "against 21.01, and 31.88 after 10 against 26.58 (docs/benchmarks_lego.md, \"Plenoxels\")")
# Rays a step, chosen by measurement on 2 CPU cores (docs/benchmarks_lego.md, "Rays a step"): a
# step's fixed costs are shared by more rays.
RAYS_PER_STEP = 2048
RAYS_REASON = (
    "measured on lego at 800×800 on 2 CPU cores, with the box fitted again at each growth: 2 048 rays a step scored "
    "28.20 dB after 2 minutes against 1 024's 27.99, and 33.04 after 10 against 32.58 (they move 1.2-1.5 times "
    "as many rays a second: a step's fixed costs are shared by more rays); 4 096 lost at 2 minutes (25.65 dB "
    "against 28.25 before the refit); on the three shared real scenes at 100×100, 2 048 scored 0.19-0.42 dB more "
    "after 2 minutes (docs/benchmarks_lego.md, \"Rays a step\" and \"The box fitted again\")")
# Colour deferred to once a ray (SNeRG's deferred shading: grid.deferred_colour), measured
# against per-sample colour side by side (docs/benchmarks_lego.md, "Deferred colour").
DEFERRED_COLOUR_REASON = (
    "the appearance features composited along each ray and the colour network run once a ray: measured on lego at "
    "800×800 on 2 CPU cores (an AVX2 machine's code), 35.60 dB after 30 minutes against per-sample colour's "
    "35.49 (69 708 steps against 41 851; the grid's training pass and compositing are one compiled "
    "call with deferred colour) and eval 1.08 s a view against 1.79; after 10 minutes 33.71 dB against "
    "33.20; on the 100×100 suite after 120 s ahead on 8 of 9 scenes (+0.02 to +0.90 dB), 0.15 dB behind on "
    "20_specular (docs/benchmarks_lego.md, \"Deferred colour\"; on another machine later 0.43 dB behind there, "
    "44.69 dB over three runs against 45.12 over two, and 0.26 dB ahead on it at 800×800: docs/benchmarks.md)")
# Colour shaped by the scene's materials (grid.region_appearance): metal samples see the view
# reflected about Blender's true surface, thin-film ones that and the view (docs/benchmarks.md,
# "Colour shaped by the scene's materials"). Glossy dielectrics keep the view (A.blend's scored
# less with it reflected). It costs a quarter of the steps, so it pays where these are a large
# part of the surface: at 0.41 of the prior's surface cells +1.28 dB (mirror_in_room), +0.09
# (rough_in_room) and +0.19 and +0.32 (thin_film_coat, two sessions), at 0.19-0.21 −0.27 (the
# demo) and +0.20 (glass_and_gloss).
REFLECTIVE_REGIONS = ("metal", "thin_film")
MIN_REFLECTIVE_SHARE = 0.3
_REFLECTIVE_WORDS = " or ".join(region.replace("_", " ") for region in REFLECTIVE_REGIONS)
REGION_APPEARANCE_REASON = (
    "{share:.0%} of the prior's surface cells are metal or thin film, and the dataset holds the true surface: metal "
    "samples see the view reflected about its normals, thin-film ones the view and its reflection, diffuse ones no "
    "view; measured at 100×100 after 120 s on 2 CPU cores, mirror_in_room (41 % metal) scored 34.40 dB against 33.12 "
    "without, thin_film_coat (41 % thin film) 38.00 against 37.68 (docs/benchmarks.md, \"Colour shaped by the "
    "scene's materials\")")
REFLECTION_FREQUENCIES = 6
# Rays bent through clear glass (refraction): what the glass shows is then the field itself, seen
# through it as Cycles sees it, not a colour the network must learn to change with the view.
REFRACTION_REASON = (
    "the scene's glass ({triangles} triangles, IOR {ior}) bends the rays that meet it, as Cycles does, and "
    "the field is marched beyond it: measured at 100×100 after 120 s on 2 CPU cores, glass_over_checker (a glass "
    "ball on a checkerboard) scored 33.06 dB against 27.23 with straight rays, glass_and_gloss (a clear ball bent, "
    "a green cube not) 32.00 against 31.19 (docs/benchmarks.md, \"Rays bent through glass\")")
THIN_GLASS_REASON = (
    "the scene's smooth glass is thin-walled ({bodies}, mean chord at most {share:.3f} of the size, under "
    "{least}: a dish, a vase, a pane), so a ray through it is only shifted and rays go straight: measured at "
    "100×100 after 120 s on 2 CPU cores, a glass dish with olives in it scored 32.78 dB straight against 25.72 "
    "bent (docs/benchmarks.md, \"Rays bent through glass\")")
REFLECTION_FREQUENCIES_REASON = (
    "the reflected view's encoding in 6 bands: a mirror's reflections are as sharp as the world it reflects; "
    "mirror_in_room scored 34.66 dB with 6 against 33.86 with 4 (docs/benchmarks.md)")
# Steps a time budget must still allow (at the run's rate so far) for the grid's last growth:
# RobotExpressive at 800×800 without a prior had about 1 000 left at 60 s (the coarser grid then
# better) and 2 200 at 120 s (the final grid as good); held back with 60 s, three real scenes
# scored 0.19-1.17 dB more (docs/benchmarks_800px.md, "auto sizes its grid for the budget").
LAST_GROWTH_MIN_STEPS = 1500
# Which of the prior's fills auto uses (measured with bench: see the README), and
# occupancy_prior's value for "that kind where the dataset has a prior, else none".
PRIOR_KIND = "solid"
AVAILABLE_PRIOR = "available"
# The surface preset's final β in cells: this share of a pixel's footprint in cells, within
# these bounds. VolSDF's density outside the surface piles up along rays that graze it, so a
# silhouette lies outside the distance's zero level and training pulls the surface inward
# (docs/benchmarks.md, "Why the surface sits inside"); pixels finer than the cells pin
# silhouettes more tightly than that bias, and a sharper β moves the surface out: at 800×800
# (a pixel 0.36 of a cell) a quarter cell took the F-score from 0.486 to 0.611 on A.blend and
# from 0.323 to 0.495 on RobotExpressive (PSNR −0.83 and +0.44 dB); at 100×100 (2.9 cells a
# pixel) the same cost 1.7-3.5 dB for no F-score.
BETA_PER_PIXEL = 0.7
SHARPEST_BETA_CELLS, SOFTEST_BETA_CELLS = 0.25, 0.5

# A GPU's step is bound by its kernel launches, not its work: more rays a step cost little more
# time. Measured on lego at 800×800 on an NVIDIA H200 (torch 2.11.0+cu130, the PyTorch path).
GPU_RAYS_PER_STEP = 8192
GPU_RAYS_REASON = (
    "on CUDA; measured on lego at 800×800 on an NVIDIA H200: 8 192 rays a step trained 643 660 rays a second and "
    "scored 34.42 dB on the 13 held-out views after 90 s, 16 384 939 460 and 34.53 dB; 2 048 trained 177 747 rays a "
    "second (27.14 dB on the validation views after 150 s, 8 192's 33.20 after 90). 8 192 for half 16 384's memory; "
    "MPS not measured (it keeps the CPU's 2 048)")


def _new_run(facts: RunFacts) -> bool:
    """Whether the preset is still to be shaped (a resumed run keeps its stored shape)."""
    return facts.stored is None


def _auto(facts: RunFacts, plan: RunPlan) -> bool:
    return _new_run(facts) and plan.config.preset == "auto"


def _views(facts: RunFacts, plan: RunPlan) -> DatasetSplit:
    """The training views the plan trains on."""
    split = facts.train_split
    return split.subset(plan.train_views) if 0 < plan.train_views < len(split) else split


# --- every start ---------------------------------------------------------------------------
def device(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """The device the user named (``auto``: the fastest present).

    Example:
        >>> facts, plan = _example()
        >>> [(p.key, str(p.value)) for p in device(facts, plan)]
        [('device', 'cpu')]
    """
    chosen, reason = choose_device(facts.request.device, facts.devices)
    yield Proposal("device", "device", chosen, reason)


def budget(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """What ends the run and what its schedule spans: ``--iters`` and ``--max-seconds`` (a
    resumed run's stored ones where not given again). A time budget alone trains until the
    time is spent, the schedule laid over it; with ``--iters`` as well, whichever comes first.

    Example:
        >>> facts, plan = _example(max_seconds=60.0)
        >>> {p.key: p.value for p in budget(facts, plan)}
        {'max_seconds': 60.0, 'stop_at_iterations': False, 'schedule_seconds': 60.0}
    """
    request, stored = facts.request, facts.stored
    if stored is None:
        max_seconds = request.max_seconds
        stop = request.iterations is not None or max_seconds is None
        schedule = request.schedule_seconds or max_seconds
    else:
        max_seconds = request.max_seconds if request.max_seconds is not None else stored.get("max_seconds")
        stop = request.iterations is not None or stored.get("stop_at_iterations", True)
        schedule = request.schedule_seconds or request.max_seconds or stored.get("schedule_seconds")
    if plan.config.schedule not in SCHEDULES:
        raise NerfError(f"schedule {plan.config.schedule!r}: choose {' or '.join(SCHEDULES)}")
    spans = "the schedule counts steps" if plan.config.schedule == "iterations" else "the schedule spans it"
    yield Proposal("max_seconds", "max_seconds", max_seconds,
                   "no time budget" if max_seconds is None else f"a budget of {max_seconds:g} s of training")
    yield Proposal("stop_at_iterations", "stop_at_iterations", stop,
                   "the iteration count ends the run" if stop else "the time budget alone ends the run")
    yield Proposal("schedule_seconds", "schedule_seconds", None if plan.config.schedule == "iterations" else schedule,
                   "no time budget: the schedule counts steps" if schedule is None else f"{schedule:g} s: {spans}")
    if request.iterations is not None:
        yield Proposal("iterations", "iterations", request.iterations, "--iters")


def train_views(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Every training view, or the first ``max_train_views`` (the paper's view ablation).

    Example:
        >>> facts, plan = _example()
        >>> next(train_views(facts, plan)).value
        4
    """
    views, asked = len(facts.train_split), plan.config.max_train_views
    if asked is not None and asked < views:
        yield Proposal("train_views", "train_views", asked, f"max_train_views: the first {asked} of {views} views")
    else:
        yield Proposal("train_views", "train_views", views, f"every training view ({views})")


def ray_bounds(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Where along each ray the scene can be: the scene's box (``ray_bounds=scene``) or the
    protocol's near and far.

    Example:
        >>> facts, plan = _example()
        >>> next(ray_bounds(facts, plan)).value.box.box_max  # padded by 5 % of its longest side
        (1.1, 1.1, 0.35)
    """
    bounds, reason = choose_ray_bounds(plan.config.ray_bounds, facts.scene_bounds)
    yield Proposal("ray_bounds", "ray_bounds", bounds, reason)


def occupancy_prior(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Which of the dataset's occupancy priors the model starts from, if any (grid models
    only); a prior asked for that the dataset lacks is an error.

    Example:
        >>> facts, plan = _example()
        >>> next(occupancy_prior(facts, plan)).value is None  # the example's dataset has none
        True
    """
    config, kind = plan.config, plan.config.occupancy_prior
    if not model_class(config.model).uses_occupancy_prior or kind == "none":
        yield Proposal("prior_kind", "prior_kind", None, f"none: occupancy_prior={kind} for the {config.model} model")
    elif kind == AVAILABLE_PRIOR:
        present = PRIOR_KIND in facts.priors
        yield Proposal("prior_kind", "prior_kind", PRIOR_KIND if present else None,
                       f"the dataset's {PRIOR_KIND} prior" if present else "the dataset has no occupancy prior")
    elif kind not in PRIOR_KINDS:
        raise NerfError(f"occupancy_prior {kind!r}: choose none, {AVAILABLE_PRIOR}, {', '.join(PRIOR_KINDS)}")
    elif kind not in facts.priors:
        raise NerfError(f"{facts.dataset}: occupancy_prior={kind} asked for, but the dataset has no occupancy "
                        f"prior (scene_profile.json names none); use occupancy_prior=none")
    else:
        yield Proposal("prior_kind", "prior_kind", kind, f"occupancy_prior={kind}")


def coarse_images(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Coarse-to-fine images (``coarse_images``): a full-size pixel's footprint on the scene,
    which each downsampled level is measured against; None: full-size images throughout.

    Example (auto trains on full-size images from the first step):
        >>> facts, plan = _example(before=coarse_images)
        >>> next(coarse_images(facts, plan)).value is None
        True
    """
    box = plan.ray_bounds.box
    if plan.config.coarse_images and box is not None:
        footprint = pixel_footprint(_views(facts, plan), box)
        yield Proposal("coarse_images", "coarse_image_pixel", footprint,
                       f"a full-size pixel covers {footprint:.4f} units: images downsampled to the model's detail")
    else:
        yield Proposal("coarse_images", "coarse_image_pixel", None, "full-size images from the first step")


# --- auto ----------------------------------------------------------------------------------
def auto_model(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """auto's model: the factorised grids, measured against the others at equal time.

    Example:
        >>> facts, plan = _example()
        >>> next(auto_model(facts, plan)).value
        'grid'
    """
    if _auto(facts, plan):
        yield Proposal("model", "model", AUTO_MODEL, AUTO_MODEL_REASON)


def auto_rays(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Rays a step: for the factorised grids 2 048, or 8 192 on CUDA (both measured), else the preset's.

    Example:
        >>> facts, plan = _example()
        >>> next(auto_rays(facts, plan)).value
        2048
        >>> import dataclasses
        >>> next(auto_rays(facts, dataclasses.replace(plan, device=torch.device("cuda")))).value
        8192
    """
    if _auto(facts, plan):
        if plan.config.model != AUTO_MODEL:
            yield Proposal("rays", "rays_per_batch", plan.config.rays_per_batch,
                           f"the preset's: {RAYS_PER_STEP} was measured for the factorised grids only")
        elif plan.device.type == "cuda":
            yield Proposal("rays", "rays_per_batch", GPU_RAYS_PER_STEP, GPU_RAYS_REASON)
        else:
            yield Proposal("rays", "rays_per_batch", RAYS_PER_STEP, RAYS_REASON)


def auto_view_dependence(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """No glossy, metallic, specular, transmissive, clearcoat or sheen material: colour takes
    no direction input.

    Example:
        >>> facts, plan = _example(profile={"view_dependent": False})
        >>> next(auto_view_dependence(facts, plan)).value
        False
    """
    if not _auto(facts, plan):
        return
    profile = facts.profile
    if profile is not None and isinstance(profile.get("view_dependent"), bool):
        dependent = profile["view_dependent"]
        reason = ("the scene has view-dependent materials" if dependent
                  else "every material is diffuse: colour needs no viewing direction")
    else:
        dependent = plan.config.grid.view_dependent
        reason = "the dataset does not say whether its materials are view-dependent: keep direction input"
    yield Proposal("view_dependence", "grid.view_dependent", dependent, reason)


def auto_colour(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Colour deferred to once a ray, at every budget: measured against per-sample colour at
    equal time after 10 and 30 minutes.

    Example:
        >>> facts, plan = _example()
        >>> next(auto_colour(facts, plan)).value
        True
    """
    if not _auto(facts, plan):
        return
    yield Proposal("colour", "grid.deferred_colour", True, DEFERRED_COLOUR_REASON)


def auto_region_appearance(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Colour shaped by the scene's materials (``grid.region_appearance``): where Blender says
    much of the surface is metal or thin film (REFLECTIVE_REGIONS, at least MIN_REFLECTIVE_SHARE
    of the prior's surface cells together) and the dataset holds the true surface to reflect the view about
    (``scene_geometry.ply``), samples there see the view reflected, and diffuse ones see none;
    the reflected view's encoding as wide as a mirror needs.

    Example:
        >>> profile = {"view_dependent": True, "geometry": {"file": "scene_geometry.ply"},
        ...            "occupancy_prior": {"file": "p.npz", "regions": {"diffuse": 0.6, "metal": 0.4}}}
        >>> facts, plan = _example(profile=profile, before=auto_region_appearance)
        >>> [(p.name, p.value) for p in auto_region_appearance(facts, plan)]
        [('region_appearance', True), ('reflection_frequencies', 6)]
        >>> film = {**profile, "occupancy_prior": {"file": "p.npz", "regions": {"diffuse": 0.6, "thin_film": 0.4}}}
        >>> facts, plan = _example(profile=film, before=auto_region_appearance)
        >>> next(auto_region_appearance(facts, plan)).value
        True
        >>> facts, plan = _example(profile={**profile, "geometry": None}, before=auto_region_appearance)
        >>> next(auto_region_appearance(facts, plan)).reason
        'no true surface in the dataset (scene_geometry.ply) to reflect the view about: colour as before'
    """
    if not _auto(facts, plan):
        return
    profile = facts.profile or {}
    prior = profile.get("occupancy_prior")
    shares = prior.get("regions") if isinstance(prior, dict) else None
    geometry = profile.get("geometry")
    reflective = sum(float(shares.get(region, 0.0)) for region in REFLECTIVE_REGIONS) if isinstance(shares, dict) else 0.0
    if not plan.config.grid.view_dependent:
        chosen, reason = False, "colour takes no direction at all (every material is diffuse)"
    elif not isinstance(shares, dict):
        chosen, reason = False, "the dataset does not say what its surfaces are made of (no regions in its prior): colour as before"
    elif not (isinstance(geometry, dict) and geometry.get("file")):
        chosen, reason = False, "no true surface in the dataset (scene_geometry.ply) to reflect the view about: colour as before"
    elif reflective <= 0.0:
        chosen, reason = False, f"no {_REFLECTIVE_WORDS} surface in the prior: colour as before"
    elif reflective < MIN_REFLECTIVE_SHARE:
        chosen, reason = False, (
            f"{reflective:.0%} of the prior's surface cells are {_REFLECTIVE_WORDS}, under "
            f"{MIN_REFLECTIVE_SHARE:.0%}: the reflected view costs a quarter of the steps, and the demo (19 % metal) "
            "scored 0.27 dB less with it; colour as before")
    else:
        chosen, reason = True, REGION_APPEARANCE_REASON.format(share=reflective)
    yield Proposal("region_appearance", "grid.region_appearance", chosen, reason)
    if chosen:
        yield Proposal("reflection_frequencies", "grid.reflection_frequencies", REFLECTION_FREQUENCIES,
                       REFLECTION_FREQUENCIES_REASON)


def auto_refraction(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Rays bent through the scene's smooth glass (``refraction``, model_components/glass.py),
    where Blender says what the glass is (smooth, fully transmissive, nearly colourless materials
    with no volume or other shader mixed in:
    ``data.occupancy_prior.smooth_glass``) and where it is (the dataset's true surface, each
    triangle with its material), and where a body of it is thick enough for bending to show
    (``wall_share``: thin-walled glass goes straight).

    Example:
        >>> facts, plan = _example(before=auto_refraction)
        >>> next(auto_refraction(facts, plan)).reason
        'no occupancy prior and true surface in the dataset: no glass to bend rays through'
    """
    if not _auto(facts, plan) or plan.config.model != AUTO_MODEL:
        return
    prior = next(iter(facts.priors.values()), None)
    if prior is None or prior.geometry is None:
        yield Proposal("refraction", "refraction", False,
                       "no occupancy prior and true surface in the dataset: no glass to bend rays through")
        return
    surfaces, thin = prior.glass_surfaces(), [share for shares in prior.thin_glass().values() for share in shares]
    if surfaces is None and thin:
        yield Proposal("refraction", "refraction", False, THIN_GLASS_REASON.format(
            bodies=_bodies(len(thin)), share=max(thin), least=GLASS_MIN_WALL_SHARE))
        return
    if surfaces is None:
        yield Proposal("refraction", "refraction", False,
                       "no smooth glass in the scene (a transmissive material smooth, fully transmissive, nearly "
                       "colourless, with no volume or other shader mixed in): rays go straight")
        return
    iors = sorted(set(surfaces[2].tolist()))
    straight = (f"; {_bodies(len(thin))} of thin-walled glass (mean chord under {GLASS_MIN_WALL_SHARE} of the "
                f"size) left to the field, straight" if thin else "")
    yield Proposal("refraction", "refraction", True, REFRACTION_REASON.format(
        triangles=surfaces[0].shape[0], ior=", ".join(f"{ior:.3g}" for ior in iors)) + straight)


def _bodies(count: int) -> str:
    return f"{count} body" if count == 1 else f"{count} bodies"


def auto_grid_resolution(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Detail: the grid needs no vertex finer than a pixel's footprint on the scene (Nyquist
    for the training images), up to a limit a budget of 30 minutes or more raises; the cells
    no finer than that footprint when the box narrows.

    Example (a 71-vertex cube's cells spread over the flat box as cubic cells):
        >>> facts, plan = _example()
        >>> [(p.name, p.value) for p in auto_grid_resolution(facts, plan)][0]
        ('grid_resolution', 114)
    """
    if not _auto(facts, plan):
        return
    box, grid = plan.ray_bounds.box, plan.config.grid
    footprint = pixel_footprint(_views(facts, plan), box)
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    most, most_reason = finest_resolution(plan.schedule_seconds)
    clamped, reason = pixel_resolution(footprint, sides, grid.cubic_cells, most)
    vertices = vertices_for(clamped, sides) if grid.cubic_cells else (clamped,) * 3
    yield Proposal("grid_resolution", "grid.resolution", clamped,
                   reason + f"; vertices per axis {vertices[0]}×{vertices[1]}×{vertices[2]}; {most_reason}",
                   {"vertices": list(vertices)})
    yield Proposal("finest_cell", "grid.finest_cell", footprint,
                   "a pixel's footprint at the scene's centre: a narrowed box's cells are never finer")


def auto_growth(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """The grid grows from the preset's start to its final resolution on the preset's
    schedule; under a time budget, the last growth waits for steps enough to fill it in.

    Example (48 vertices to the example's 114, at the preset's scheduled steps):
        >>> facts, plan = _example(before=auto_growth)
        >>> [p.value for p in auto_growth(facts, plan)]
        [48, (300, 600, 1000), 1500]
    """
    if not _auto(facts, plan):
        return
    grid = plan.config.grid
    initial = min(grid.initial_resolution, grid.resolution)
    schedule = grid.upsample_iterations if grid.resolution > initial else ()
    yield Proposal("initial_resolution", "grid.initial_resolution", initial,
                   "the preset's start" if initial == grid.initial_resolution else "the final resolution: no growth")
    yield Proposal("growth", "grid.upsample_iterations", schedule,
                   "the preset's schedule" if schedule else "the grid starts at its final resolution")
    yield Proposal("last_growth", "grid.last_growth_min_steps", LAST_GROWTH_MIN_STEPS if schedule else 0, (
        f"under a time budget the grid grows to its final {grid.resolution} vertices only with "
        f"{LAST_GROWTH_MIN_STEPS} steps left at the run's rate so far (a finer grid needs steps to fill in), else it "
        "stays one growth coarser; without a budget it always grows" if schedule else "the grid does not grow"))


def auto_background(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """A transparent film gives an alpha channel: training composites over random colours and
    the alpha decides what is background.

    Example (the example's views have a transparent border):
        >>> facts, plan = _example()
        >>> next(auto_background(facts, plan)).value
        True
    """
    if not _auto(facts, plan):
        return
    transparent = bool((_views(facts, plan).rgba[..., 3] < 255).any())
    yield Proposal("background", "random_background", transparent, (
        "the images have an alpha channel with transparent pixels (transparent film): random background colours, "
        "the alpha as mask" if transparent
        else "every pixel is opaque, so there is no background to separate: background is scene content"))


def auto_occupancy_prior(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Empty space: where the dataset carries Blender's geometry as an occupancy prior, the
    occupancy grid starts from it and never marks what it leaves out.

    Example:
        >>> facts, plan = _example(profile={"occupancy_prior": {"file": "occupancy_prior.npz"}})
        >>> next(auto_occupancy_prior(facts, plan)).value
        'solid'
    """
    if not _auto(facts, plan):
        return
    has_prior = facts.profile is not None and isinstance(facts.profile.get("occupancy_prior"), dict)
    yield Proposal("occupancy_prior", "occupancy_prior", PRIOR_KIND if has_prior else "none", (
        f"the dataset holds Blender's geometry voxelised ({PRIOR_KIND}): empty space is skipped from the first step"
        if has_prior else "the dataset has no occupancy prior: empty space is found from the field's own density"))


def auto_box_fit(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Bounds: without Blender's, the box is a guess, narrowed at the first growth to what the
    field has filled (``fit_box_at``) and again after each later growth.

    Example (the example's profile has no bounds):
        >>> facts, plan = _example(before=auto_box_fit)
        >>> plan.config.grid.upsample_iterations, next(auto_box_fit(facts, plan)).value
        ((300, 600, 1000), 300)
    """
    if not _auto(facts, plan):
        return
    profile, grid = facts.profile, plan.config.grid
    if profile is not None and profile.get("bounds") is not None:
        yield Proposal("box_fit", "fit_box_at", 0, "the box is the scene's own bounds (scene_profile.json): it stays")
    elif not (grid.upsample_iterations and grid.cubic_cells):
        yield Proposal("box_fit", "fit_box_at", 0, "the grid does not grow (or has no cubic cells): its box stays")
    else:
        first = grid.upsample_iterations[0]
        yield Proposal("box_fit", "fit_box_at", first, (
            f"the box is a guess (no scene bounds in the dataset): at the first growth (scheduled step {first}) the "
            f"grids narrow to the box around the pieces of what the field has filled (floaters left out), if that "
            f"keeps at most {FIT_MAX_KEPT:.0%} of the volume, with as many cells as before, so their cells shrink "
            f"with it (not below the pixel footprint, {grid.finest_cell:.4f}); after each later growth, again, where "
            f"the finer grid's occupancy keeps at most {REFIT_MAX_KEPT:.0%} of the box"))


def auto_samples(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Samples: one march step per grid cell covers the depth range at the grid's detail
    (recorded; the model derives it).

    Example (the example's 114-vertex grid, a step a cell, along the box's diagonal):
        >>> facts, plan = _example(before=auto_samples)
        >>> proposal = next(auto_samples(facts, plan))
        >>> proposal.key, proposal.value
        (None, 165)
    """
    if not _auto(facts, plan):
        return
    box, config = plan.ray_bounds.box, plan.config
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    diagonal = math.sqrt(sum(side ** 2 for side in sides))
    steps = math.ceil(diagonal / (max(sides) / (config.grid.resolution - 1) * config.grid_step_ratio)) + 1
    yield Proposal("samples", None, steps,
                   "one march step per grid cell along the box's diagonal; empty cells are skipped")


# --- the surface and plenoxels presets -----------------------------------------------------
def surface_softness(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """The surface model's final softness β from the pixel's footprint in the final grid's
    cells (``BETA_PER_PIXEL``).

    Example (100×100 views: a pixel is several cells, β stays at half a cell):
        >>> facts, plan = _example(preset="surface")
        >>> next(surface_softness(facts, plan)).value
        0.5
    """
    if not (_new_run(facts) and plan.config.model == "surface"):
        return
    box, surface = plan.ray_bounds.box, plan.config.surface
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    cell = min(side / (n - 1) for side, n in zip(sides, vertices_for(surface.resolution, sides)))
    pixel_cells = pixel_footprint(_views(facts, plan), box) / cell
    chosen = round(min(SOFTEST_BETA_CELLS, max(SHARPEST_BETA_CELLS, BETA_PER_PIXEL * pixel_cells)), 3)
    yield Proposal("surface_softness", "surface.final_beta_cells", chosen, (
        f"a pixel covers {pixel_cells:.2f} cells of the final grid at the scene's centre: the final β is "
        f"{BETA_PER_PIXEL} of that within [{SHARPEST_BETA_CELLS}, {SOFTEST_BETA_CELLS}] cells (sharper where pixels "
        "resolve VolSDF's silhouette bias)"))


def surface_opacity(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """NeuS's opacity where the model's prior bounds the surface to a band, else VolSDF's.

    NeuS puts a silhouette exactly at the distance's zero level, but never shows a surface that
    rays only leave: alone it left flaps behind A.blend's cube (F-score 0.445 against VolSDF's
    0.486 at 800×800). Blender's solid prior bounds the distance on both sides of a thin band,
    which leaves no room for them; there NeuS wins (A.blend, 600 s at 800×800: F-score 0.980
    against 0.957, 33.43 against 30.28 dB).

    Example (the example's dataset has no prior):
        >>> facts, plan = _example(preset="surface")
        >>> next(surface_opacity(facts, plan)).value
        'volsdf'
    """
    if not (_new_run(facts) and plan.config.model == "surface"):
        return
    prior = facts.priors.get(plan.prior_kind) if plan.prior_kind else None
    bounded = plan.config.surface.prior_band and prior is not None and prior.bounds_the_surface
    yield Proposal("surface_opacity", "surface.opacity", "neus" if bounded else "volsdf", (
        "Blender's occupancy prior bounds the surface to a band (surface.prior_band), where NeuS's unbiased "
        "silhouettes leave no flaps" if bounded else "no prior bounds the surface (none, or surface.prior_band "
        "off): NeuS would leave surfaces no ray shows, VolSDF's density does not"))


def sparse_grid_size(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """The plenoxels grid's final resolution: auto's, one vertex per pixel footprint (a vertex
    of a sparse grid is learnt only from the rays near it, so a grid finer than the pixels holds
    vertices no ray pins down: on the 40×40 demo 256³ stayed blank after 300 steps, 16.3 dB,
    where 64³ reached 32.2), its cells never finer than that footprint.

    Example:
        >>> facts, plan = _example(preset="plenoxels")
        >>> next(sparse_grid_size(facts, plan)).value
        114
    """
    if not (_new_run(facts) and plan.config.model == "plenoxels"):
        return
    box = plan.ray_bounds.box
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    footprint = pixel_footprint(_views(facts, plan), box)
    resolution, reason = pixel_resolution(footprint, sides)  # type: ignore[arg-type]
    yield Proposal("grid_resolution", "plenoxels.resolution", resolution, reason)
    yield Proposal("finest_cell", "plenoxels.finest_cell", footprint, "a pixel's footprint at the scene's centre")


def sparse_grid_growth(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """The plenoxels grid grows once, from half its final resolution.

    Example:
        >>> facts, plan = _example(preset="plenoxels", before=sparse_grid_growth)
        >>> plan.config.plenoxels.resolution, next(sparse_grid_growth(facts, plan)).value
        (114, 57)
    """
    if not (_new_run(facts) and plan.config.model == "plenoxels"):
        return
    yield Proposal("initial_resolution", "plenoxels.initial_resolution",
                   max(MIN_RESOLUTION, plan.config.plenoxels.resolution // 2),
                   "half the final resolution (not below 32): one growth, when the coarse grid has found where the "
                   "scene is")


def sparse_grid_box_fit(facts: RunFacts, plan: RunPlan) -> Iterator[Proposal]:
    """Where the box is a guess (no Blender bounds), the plenoxels grid's box narrows at its
    growth to what the field fills.

    Example (the example's profile has no bounds):
        >>> facts, plan = _example(preset="plenoxels", before=sparse_grid_box_fit)
        >>> next(sparse_grid_box_fit(facts, plan)).value
        1000
    """
    if not (_new_run(facts) and plan.config.model == "plenoxels"):
        return
    grid = plan.config.plenoxels
    grown = grid.resolution > grid.initial_resolution and bool(grid.upsample_iterations)
    guessed = facts.profile is None or facts.profile.get("bounds") is None
    yield Proposal("box_fit", "fit_box_at", grid.upsample_iterations[0] if grown and guessed else 0, (
        "the box is a guess (no scene bounds in the dataset): at the growth it narrows to what the field fills"
        if guessed else "the box is the scene's own bounds (scene_profile.json): it stays"))


# --- the order they decide in --------------------------------------------------------------
# The plan so far is what each sees: the budget before auto's grid (a long budget grows it
# finer), the views before anything measured on them, the prior before the surface's opacity.
RULES: tuple[Rule, ...] = (
    device, budget, train_views, ray_bounds,
    auto_model, auto_rays, auto_view_dependence, auto_colour, auto_region_appearance, auto_refraction,
    auto_grid_resolution,
    auto_growth, auto_background, auto_occupancy_prior, auto_box_fit, auto_samples,
    surface_softness, sparse_grid_size, sparse_grid_growth, sparse_grid_box_fit,
    occupancy_prior, surface_opacity, coarse_images,
)


def _example(preset: str = "auto", profile: dict | None = None, max_seconds: float | None = None,
             before: Rule = auto_model):
    """The examples' facts and the plan so far (the rules of ``RULES`` before ``before``):
    four 100×100 views at radius 4 with a transparent border, of a 2 × 2 × 0.5 box (padded by
    5 % of its longest side, as ``ray_bounds`` pads it), on the CPU."""
    rgba = torch.full((4, 100, 100, 4), 255, dtype=torch.uint8)
    rgba[:, :10, :, 3] = 0
    poses = torch.eye(4).repeat(4, 1, 1)
    poses[:, 2, 3] = 4.0
    split = DatasetSplit("train", Intrinsics(100, 100, 138.9, 138.9, 50.0, 50.0), poses, rgba, [])
    request = RunRequest(preset=preset, max_seconds=max_seconds)
    facts = RunFacts(request, starting_settings(request, None), Path("example"), split, profile,
                     SceneBounds((-1.0, -1.0, -0.25), (1.0, 1.0, 0.25)), {}, ("cpu",))
    return facts, plan_run(facts, RULES[:RULES.index(before)])
