"""Checks run on a scene before rendering, as a pure decision over facts Blender reported.

Real .blend files arrive with missing textures (they render magenta), missing linked
libraries (their objects vanish), nothing renderable at all, or an engine that cannot run
headless.  `scene_facts` (Blender-facing) collects a `SceneFacts`; `evaluate` decides here,
without bpy, what refuses the run, what --allow-missing lets through, and what is only noted.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

#: Engines that render the same materials as Cycles but cannot run headless here.
CYCLES_SUBSTITUTES = ("BLENDER_EEVEE", "BLENDER_EEVEE_NEXT", "BLENDER_WORKBENCH")
ALLOW_HINT = "pass --allow-missing to render anyway"


@dataclass(frozen=True)
class MissingFile:
    """An external file the scene refers to that is not on disk."""

    kind: str  # "image", "library", "volume", "cache file", "font"
    path: str  # as resolved to an absolute path
    datablock: str = ""  # the datablock that refers to it (e.g. the image's name)
    users: Sequence[str] = ()  # what uses it (for a library: what is linked from it), e.g. "object 'Cube'"
    stored_path: str = ""  # the path as the .blend holds it, when that says more (e.g. "//textures/a.png")

    def describe(self) -> str:
        text = f"missing {self.kind} file {self.path}"
        details = [f"{self.kind} {self.datablock!r}"] if self.datablock else []
        if self.stored_path:
            details.append(f"stored as {self.stored_path!r}")
        if details:
            text += f" ({', '.join(details)})"
        if self.users:
            text += f" {'linking' if self.kind == 'library' else 'used by'} {', '.join(self.users)}"
        return text


@dataclass(frozen=True)
class SceneFacts:
    """What the checks need to know about a scene, collected by Blender-facing code."""

    scene: str  # the scene's name
    source: str  # the .blend path or "demo", for messages
    engine: str
    renderable_objects: Sequence[str] = ()
    render_hidden_objects: Sequence[str] = ()  # surface objects excluded (hidden from render/camera)
    other_objects: Sequence[str] = ()  # lights, empties, armatures... (for the "nothing to render" message)
    missing_files: Sequence[MissingFile] = ()
    view_transform: str = "Standard"
    look: str = "None"
    exposure: float = 0.0
    gamma: float = 1.0
    film_transparent: bool = True


@dataclass
class CheckOutcome:
    """The decision: `errors` refuse the run; `allowed` are problems --allow-missing let through."""

    errors: list[str] = field(default_factory=list)
    allowed: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    render_engine: str = "CYCLES"
    source_engine: str = "CYCLES"
    allow_missing: bool = False

    def record(self) -> dict[str, Any]:
        """For the dataset's JSON: what was found and what was decided."""
        return asdict(self)

    def error_message(self, source: str) -> str:
        """One line naming the file and every problem."""
        return f"{source}: " + "; ".join(self.errors)


def evaluate(facts: SceneFacts, allow_missing: bool, color_management: str = "standard") -> CheckOutcome:
    """Decide what to do with a scene (see the module docstring).

    `color_management` "standard" forces the protocol's (noted when the file differs); "scene"
    keeps the file's.
    """
    outcome = CheckOutcome(source_engine=facts.engine, allow_missing=allow_missing)
    problems: list[str] = [missing.describe() for missing in facts.missing_files]

    protocol_colour = ("Standard", "None", 0.0, 1.0)
    colour = (facts.view_transform, facts.look, float(facts.exposure), float(facts.gamma))
    if color_management == "standard" and colour != protocol_colour:
        outcome.notes.append(
            f"scene {facts.scene!r} uses view transform {facts.view_transform!r}, look {facts.look!r}, "
            f"exposure {facts.exposure:g}, gamma {facts.gamma:g}: rendered with the protocol's Standard, "
            "None, 0, 1 (--color-management scene keeps the file's)"
        )
    if not facts.film_transparent:
        outcome.notes.append(f"scene {facts.scene!r} has an opaque film: rendered with a transparent film")

    if facts.engine in CYCLES_SUBSTITUTES:
        outcome.notes.append(
            f"scene {facts.scene!r} is set to {facts.engine}, which cannot render headless: "
            "rendered with Cycles instead"
        )
    elif facts.engine != "CYCLES":
        problems.append(
            f"scene {facts.scene!r} uses the add-on render engine {facts.engine!r}; its materials "
            "may render wrongly in Cycles"
        )

    if problems:
        if allow_missing:
            outcome.allowed.extend(problems)
            outcome.notes.append(
                "rendering despite: " + "; ".join(problems) + " (--allow-missing; missing images render magenta)"
            )
        else:
            outcome.errors.extend(problems)
            outcome.errors[-1] += f" ({ALLOW_HINT})"

    if not facts.renderable_objects:
        # Never allowed: there is nothing to reconstruct, and no fit is possible.
        detail = []
        if facts.render_hidden_objects:
            detail.append("hidden from render: " + ", ".join(sorted(facts.render_hidden_objects)))
        if facts.other_objects:
            detail.append("other objects: " + ", ".join(sorted(facts.other_objects)))
        message = (
            f"scene {facts.scene!r} has nothing to render: no visible mesh, curve, surface, "
            "text or metaball object"
        )
        if detail:
            message += " (" + "; ".join(detail) + ")"
        outcome.errors.insert(0, message)
    return outcome
