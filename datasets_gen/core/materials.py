"""Which materials look different from different directions, decided from a plain description.

The backend models view dependence (and transparency) only when the scene needs it, so the
scene profile classifies each material that renders.  Blender-facing code (`scene_facts`)
describes a material as the shader nodes Cycles evaluates (reachable from the Cycles output,
through groups), each with the inputs that matter (value, whether a link drives it) and which
of its outputs are used; the decision here is pure and conservative: an input driven by a link
(e.g. a texture) counts as non-zero.  Beside the verdict, ``appearance_facts`` records what the
surface is made of (the Principled BSDF's roughness, metallic, transmission, IOR, coat, sheen,
thin film, emission and alpha): a value where the node tree makes it constant, and why not
where it does not.

Covers Blender 3.x and 4.x+ socket names ("Specular" -> "Specular IOR Level", "Clearcoat" ->
"Coat Weight", "Sheen" -> "Sheen Weight", "Transmission" -> "Transmission Weight").
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Mapping, Optional, Sequence

#: Principled BSDF lobes that depend on the view direction: (reason, socket names across versions).
PRINCIPLED_VIEW_DEPENDENT = (
    ("metallic", ("Metallic",)),
    ("specular", ("Specular IOR Level", "Specular")),
    ("transmission", ("Transmission Weight", "Transmission")),
    ("clearcoat", ("Coat Weight", "Clearcoat")),
    ("sheen", ("Sheen Weight", "Sheen")),
)
PRINCIPLED_TRANSMISSION = ("Transmission Weight", "Transmission")

#: Whole nodes whose output depends on the view direction.
VIEW_DEPENDENT_NODES = {
    "BSDF_GLOSSY": "glossy BSDF",
    "BSDF_ANISOTROPIC": "anisotropic glossy BSDF",
    "BSDF_METALLIC": "metallic BSDF",
    "EEVEE_SPECULAR": "specular BSDF",
    "BSDF_GLASS": "glass BSDF (transmission)",
    "BSDF_REFRACTION": "refraction BSDF (transmission)",
    "BSDF_SHEEN": "sheen BSDF",
    "BSDF_VELVET": "velvet BSDF (sheen)",
    "BSDF_HAIR": "hair BSDF (glossy)",
    "BSDF_HAIR_PRINCIPLED": "principled hair BSDF (glossy)",
    "BSDF_TOON": "toon BSDF",
    "FRESNEL": "Fresnel node (uses the viewing angle)",
    "LAYER_WEIGHT": "Layer Weight node (uses the viewing angle)",
}
#: Geometry node outputs that depend on the view direction.
VIEW_DEPENDENT_OUTPUTS = {"NEW_GEOMETRY": ("Incoming", "Backfacing")}

TRANSPARENT_NODES = {
    "BSDF_TRANSPARENT": "transparent BSDF",
    "HOLDOUT": "holdout",
    "BSDF_GLASS": "glass BSDF",
    "BSDF_REFRACTION": "refraction BSDF",
    "VOLUME_ABSORPTION": "volume",
    "VOLUME_SCATTER": "volume",
    "VOLUME_COEFFICIENTS": "volume",
    "PRINCIPLED_VOLUME": "volume",
}

NO_MATERIAL = "(no material)"

#: The Principled BSDF's inputs that shape a surface's appearance, as the scene profile's material
#: facts name them: (fact, socket names across versions).  Blender 3.x has no thin film.
APPEARANCE_INPUTS = (
    ("base_colour", ("Base Color",)),
    ("roughness", ("Roughness",)),
    ("metallic", ("Metallic",)),
    ("specular", ("Specular IOR Level", "Specular")),
    ("transmission", ("Transmission Weight", "Transmission")),
    ("ior", ("IOR",)),
    ("coat", ("Coat Weight", "Clearcoat")),
    ("coat_roughness", ("Coat Roughness", "Clearcoat Roughness")),
    ("sheen", ("Sheen Weight", "Sheen")),
    ("thin_film_thickness", ("Thin Film Thickness",)),
    ("thin_film_ior", ("Thin Film IOR",)),
    ("emission_colour", ("Emission Color", "Emission")),
    ("emission_strength", ("Emission Strength",)),
    ("alpha", ("Alpha",)),
)
#: Shader nodes other than the Principled BSDF: what the facts say a material mixes in (the
#: view-dependent and transparent ones above, but for Fresnel and Layer Weight, which are inputs).
OTHER_SHADERS = {
    "BSDF_DIFFUSE": "diffuse BSDF", "EMISSION": "emission", "MIX_SHADER": "mix shader",
    "ADD_SHADER": "add shader", "SUBSURFACE_SCATTERING": "subsurface scattering",
    **{kind: label for kind, label in VIEW_DEPENDENT_NODES.items() if kind not in ("FRESNEL", "LAYER_WEIGHT")},
    **TRANSPARENT_NODES,
}


@dataclass
class MaterialProfile:
    """The verdict on one material, with the reasons a reader can check."""

    name: str
    view_dependent: bool
    reasons: list[str] = field(default_factory=list)
    transparent: bool = False
    transparency_reasons: list[str] = field(default_factory=list)
    objects: list[str] = field(default_factory=list)
    #: What the surface is made of (``appearance_facts``).
    appearance: dict[str, Any] = field(default_factory=dict)
    #: Its appearance region (one of ``APPEARANCE_REGIONS``) and why (``appearance_region``).
    region: str = "diffuse"
    region_reason: str = ""

    def record(self) -> dict[str, Any]:
        return asdict(self)


def _input(node: Mapping[str, Any], names: Sequence[str]) -> Optional[Mapping[str, Any]]:
    inputs = node.get("inputs", {})
    for name in names:
        if name in inputs:
            return inputs[name]
    return None


def _describe_input(socket: Mapping[str, Any]) -> str:
    if socket.get("linked"):
        return "driven by a link"
    return f"{socket.get('value', 0.0):g}"


def _nonzero(socket: Optional[Mapping[str, Any]]) -> bool:
    if socket is None:
        return False
    if socket.get("linked"):
        return True
    value = socket.get("value", 0.0)
    return isinstance(value, (int, float)) and value > 0.0


def _principled(node: Mapping[str, Any], profile: MaterialProfile) -> None:
    label = f"Principled BSDF {node.get('name', '')!r}"
    for reason, names in PRINCIPLED_VIEW_DEPENDENT:
        socket = _input(node, names)
        if _nonzero(socket):
            assert socket is not None
            profile.reasons.append(f"{label}: {reason} {_describe_input(socket)}")
    transmission = _input(node, PRINCIPLED_TRANSMISSION)
    if _nonzero(transmission):
        assert transmission is not None
        profile.transparency_reasons.append(f"{label}: transmission {_describe_input(transmission)}")
    alpha = _input(node, ("Alpha",))
    if alpha is not None and (alpha.get("linked") or float(alpha.get("value", 1.0)) < 1.0):
        profile.transparency_reasons.append(f"{label}: alpha {_describe_input(alpha)}")


def _source_label(socket: Mapping[str, Any]) -> str:
    """What drives a linked input, in words: the node its link comes from, where known."""
    source = socket.get("from")
    if not source:
        return "a link"
    if source.get("type") == "GROUP_INPUT":
        return "a node group's input"
    kind = source.get("label") or source.get("type", "").lower().replace("_", " ")
    return f"the {kind} node {source.get('name', '')!r}"


def _input_fact(sockets: list[Mapping[str, Any]]) -> dict[str, Any]:
    """One appearance input over a material's Principled BSDFs: its value where every one holds
    the same constant, else why it varies."""
    linked = [socket for socket in sockets if socket.get("linked")]
    if linked:
        return {"varies": f"driven by {_source_label(linked[0])}"}
    values = sorted({_six_digits(socket.get("value")) for socket in sockets}, key=str)
    if len(values) == 1:
        return {"value": list(values[0]) if isinstance(values[0], tuple) else values[0]}
    return {"varies": f"{len(sockets)} Principled BSDFs hold {', '.join(f'{v}' for v in values)}"}


def _six_digits(value: Any) -> Any:
    """A socket's number, or a colour's tuple of them, to the six digits Blender's float32 holds
    (0.1 is read back as 0.10000000149)."""
    if isinstance(value, (list, tuple)):
        return tuple(_six_digits(channel) for channel in value)
    return float(f"{float(value or 0.0):.6g}")


def appearance_facts(description: Mapping[str, Any]) -> dict[str, Any]:
    """What a material's surface is made of, from the nodes Cycles evaluates (the description's
    shape: see the module docstring): each of APPEARANCE_INPUTS of its Principled BSDFs as
    ``{"value": v}`` where the node tree makes it constant, or ``{"varies": why}`` where a link
    (a texture, a node group's input) or several BSDFs make it differ across the surface; the
    other shader nodes it mixes in; and the shader: ``principled``, ``other`` (no Principled
    BSDF) or ``default`` (no node tree: Cycles renders a plain diffuse surface).

    Example:
        >>> facts = appearance_facts({"uses_nodes": True, "nodes": [{"type": "BSDF_PRINCIPLED", "inputs": {
        ...     "Roughness": {"value": 0.25, "linked": False},
        ...     "Metallic": {"value": None, "linked": True,
        ...                  "from": {"type": "TEX_IMAGE", "label": "Image Texture", "name": "Rust"}}}}]})
        >>> facts["shader"], facts["inputs"]["roughness"], facts["inputs"]["metallic"]
        ('principled', {'value': 0.25}, {'varies': "driven by the Image Texture node 'Rust'"})
    """
    nodes = list(description.get("nodes", ()))
    if not description.get("uses_nodes", True):
        return {"shader": "default", "inputs": {}, "other_shaders": []}
    principled = [node for node in nodes if node.get("type") == "BSDF_PRINCIPLED"]
    others = sorted({f"{OTHER_SHADERS[node['type']]} {node.get('name', '')!r}"
                     for node in nodes if node.get("type") in OTHER_SHADERS})
    inputs = {}
    for fact, names in APPEARANCE_INPUTS:
        sockets = [socket for node in principled if (socket := _input(node, names)) is not None]
        if sockets:
            inputs[fact] = _input_fact(sockets)
    return {"shader": "principled" if principled else "other", "inputs": inputs, "other_shaders": others}


def classify_material(description: Mapping[str, Any]) -> MaterialProfile:
    """Classify one material description (see the module docstring for its shape).

    A material without nodes renders in Cycles as a plain diffuse surface, and so does an
    object slot without a material, so both are view-independent and opaque.
    """
    profile = MaterialProfile(
        name=str(description.get("name", NO_MATERIAL)),
        view_dependent=False,
        objects=sorted(description.get("objects", ())),
    )
    for node in description.get("nodes", ()):
        node_type = node.get("type", "")
        if node_type == "BSDF_PRINCIPLED":
            _principled(node, profile)
        if node_type in VIEW_DEPENDENT_NODES:
            profile.reasons.append(f"{VIEW_DEPENDENT_NODES[node_type]} {node.get('name', '')!r}")
        for output in VIEW_DEPENDENT_OUTPUTS.get(node_type, ()):
            if output in node.get("linked_outputs", ()):
                profile.reasons.append(f"{node.get('name', node_type)!r} output {output!r} (depends on the view)")
        if node_type in TRANSPARENT_NODES:
            profile.transparency_reasons.append(f"{TRANSPARENT_NODES[node_type]} {node.get('name', '')!r}")
    profile.view_dependent = bool(profile.reasons)
    profile.transparent = bool(profile.transparency_reasons)
    profile.appearance = appearance_facts(description)
    transmitting = [f"{TRANSPARENT_NODES[node['type']]} {node.get('name', '')!r}"
                    for node in description.get("nodes", ()) if node.get("type") in TRANSMITTING_NODES]
    profile.region, profile.region_reason = appearance_region(profile, transmitting)
    return profile


#: Shader nodes that send light through a surface (besides the Principled BSDF's transmission).
TRANSMITTING_NODES = {"BSDF_GLASS", "BSDF_REFRACTION"}
#: Metallic at or above this counts as metal (Blender's own presets use 0 or 1).
METAL_FROM = 0.5


def _present(fact: Optional[Mapping[str, Any]]) -> Optional[str]:
    """A Principled input fact in words where it makes a lobe (a value above zero, or one that
    varies: a texture may raise it), else None."""
    if not fact:
        return None
    if "varies" in fact:
        return f"varies ({fact['varies']})"
    value = fact.get("value")
    return f"{value:g}" if isinstance(value, (int, float)) and value > 0 else None


def appearance_region(profile: MaterialProfile, transmitting: Sequence[str] = ()) -> tuple[str, str]:
    """The material's appearance region (``nerf_contract.dataset_layout.APPEARANCE_REGIONS``)
    and why, from its verdicts and facts: ``transmissive`` where light passes through it
    (transmission, or ``transmitting``: its glass and refraction BSDFs, in words), ``thin_film`` where it has a thin film,
    ``metal`` where metallic is METAL_FROM or more (or varies), ``glossy`` where anything else
    in it depends on the view, ``diffuse`` where nothing does. The first that holds wins, as
    the prior keeps the later region where two share a cell.

    Example:
        >>> glass = classify_material({"name": "Glass", "nodes": [{"type": "BSDF_PRINCIPLED", "inputs": {
        ...     "Transmission Weight": {"value": 1.0, "linked": False}}}]})
        >>> glass.region, glass.region_reason
        ('transmissive', 'transmission 1')
        >>> classify_material({"name": "Clay", "uses_nodes": False}).region
        'diffuse'
        >>> classify_material({"name": "Film", "nodes": [{"type": "BSDF_PRINCIPLED", "inputs": {
        ...     "Thin Film Thickness": {"linked": True, "from": {"type": "MIX", "name": "Mix"}}}}]}).region_reason
        "thin film varies (driven by the mix node 'Mix')"
    """
    inputs = profile.appearance.get("inputs", {})
    transmission = _present(inputs.get("transmission"))
    if transmission:
        return "transmissive", f"transmission {transmission}"
    if transmitting:
        return "transmissive", transmitting[0]
    film_fact = inputs.get("thin_film_thickness")
    film = _present(film_fact)
    if film:  # a thickness in nm, or why it varies (a texture, a node)
        return "thin_film", f"thin film {film}" + ("" if "varies" in film_fact else " nm")
    metallic = inputs.get("metallic") or {}
    if "varies" in metallic or (isinstance(metallic.get("value"), (int, float)) and metallic["value"] >= METAL_FROM):
        return "metal", f"metallic {_present(metallic)}"
    if profile.view_dependent:
        return "glossy", profile.reasons[0]
    return "diffuse", "nothing in it depends on the view"


def choose_output_node(outputs: Sequence[Mapping[str, Any]], engine_target: str = "CYCLES") -> Optional[int]:
    """Index of the output node an engine uses, as Blender picks it (ntreeShaderOutputNode).

    `outputs` lists the tree's output nodes in tree order, each with "target" ("ALL", "CYCLES",
    "EEVEE") and "is_active_output".  An exact target beats "ALL"; among equals, the active one.
    """
    chosen: Optional[int] = None
    for index, node in enumerate(outputs):
        target = node.get("target", "ALL")
        if target not in ("ALL", engine_target):
            continue
        if chosen is None:
            chosen = index
            continue
        current = outputs[chosen]
        current_exact = current.get("target", "ALL") == engine_target
        if target == engine_target and not current_exact:
            chosen = index
        elif (target == engine_target) == current_exact:
            if node.get("is_active_output") and not current.get("is_active_output"):
                chosen = index
    return chosen
