"""The generator's pure parts, without Blender: fit transform, scene checks, material
classification, EXR/PNG files, depth conversion, output folder decisions, shard merging, options.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from PIL import Image

from datasets_gen import generate_dataset
from datasets_gen.cli import build_parser, options_from_args
from datasets_gen.cli import main as cli_main
from datasets_gen.core import trajectories as tr
from datasets_gen.core.frame_fit import (
    IDENTITY,
    bounding_sphere_radius,
    fit_similarity,
    fit_target_radius,
    view_half_angle,
)
from datasets_gen.core.intrinsics import CameraSettings, ray_length_factors
from datasets_gen.core.materials import appearance_facts, choose_output_node, classify_material
from datasets_gen.core.options import (
    DEFAULT_OPTIONS,
    SETTINGS,
    DatasetGenError,
    GeneratorOptions,
    Shard,
    options_from_keywords,
    options_to_argv,
    parse_pixel_aspect,
)
from datasets_gen.core.scene_checks import MissingFile, SceneFacts, evaluate
from datasets_gen.io import exr
from datasets_gen.io.depth_normals import depth_channels, normal_channels
from datasets_gen.io.output_dir import (
    check_output_dir,
    remove_stale_frames,
    remove_temporary_files,
    require_same_settings,
    settings_difference,
)
from datasets_gen.io.png_check import PngError, check_rgba8
from datasets_gen.io.shards import merge

CAMERAS = {
    "protocol": CameraSettings(),
    "portrait": CameraSettings(resolution_x=600, resolution_y=800),
    "vertical_fit": CameraSettings(resolution_x=800, resolution_y=600, sensor_fit="VERTICAL", lens_mm=35.0),
    "shifted": CameraSettings(resolution_x=800, resolution_y=600, shift_x=0.1, shift_y=-0.05),
    "wide_pixels": CameraSettings(resolution_x=800, resolution_y=600, pixel_aspect_x=2.0, resolution_percentage=50),
}


# --- the fit transform ---------------------------------------------------------------------


def test_protocol_fit_radius() -> None:
    """0.9 * 4.0311 * sin(atan(18 / 50)) = 1.2289: the demo scene (radius 1.17) is inside it."""
    assert fit_target_radius(CameraSettings().intrinsics()) == pytest.approx(0.9 * tr.RIG_RADIUS * math.sin(math.atan(0.36)))
    assert fit_target_radius(CameraSettings().intrinsics()) == pytest.approx(1.2289, abs=1e-4)


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_fitted_sphere_stays_inside_every_protocol_view(name: str) -> None:
    """Points on the fitted sphere project inside the image for every train, val and test pose."""
    k = CAMERAS[name].intrinsics()
    radius = fit_target_radius(k)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(2000, 3))
    points = radius * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    poses = tr.hemisphere_poses(60, tr.split_rng(0, "train"), full_sphere=True) + tr.test_spiral_poses(200)[::10]
    tightest = math.inf
    for pose in poses:
        world_to_camera = np.linalg.inv(np.asarray(pose.matrix))
        camera_points = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        u = k.cx + k.fl_x * camera_points[:, 0] / -camera_points[:, 2]
        v = k.cy - k.fl_y * camera_points[:, 1] / -camera_points[:, 2]
        assert (u > 0).all() and (u < k.w).all() and (v > 0).all() and (v < k.h).all(), name
        tightest = min(tightest, u.min(), k.w - u.max(), v.min(), k.h - v.max())
    assert tightest < 0.15 * max(k.w, k.h), "the fit should fill most of the narrow side, not be tiny"


def test_view_half_angle_uses_the_principal_point() -> None:
    centred = view_half_angle(CameraSettings(resolution_x=800, resolution_y=600).intrinsics())
    shifted = view_half_angle(CameraSettings(resolution_x=800, resolution_y=600, shift_y=0.1).intrinsics())
    assert centred == pytest.approx(math.atan(300 / (800 * 50 / 36)))
    assert shifted == pytest.approx(math.atan((300 - 80) / (800 * 50 / 36)))
    with pytest.raises(ValueError, match="principal point"):
        view_half_angle(CameraSettings(shift_x=0.6).intrinsics())


def test_similarity_maps_points_cameras_and_bounds() -> None:
    frame = fit_similarity((1e5, -2e5, 3e4), 866.0, 1.2)
    assert frame.apply((1e5, -2e5, 3e4)) == pytest.approx((0, 0, 0), abs=1e-9)
    assert frame.scale * 866.0 == pytest.approx(1.2)
    matrix = np.asarray(frame.matrix())
    point = np.array([1e5 + 10, -2e5 - 3, 3e4 + 7, 1.0])
    np.testing.assert_allclose(matrix @ point, [*frame.apply(point[:3]), 1.0])
    assert frame.inverse_apply(frame.apply((1.0, 2.0, 3.0))) == pytest.approx((1.0, 2.0, 3.0))
    pose = tr.look_at((0.3, -4.0, 0.5))
    blender = frame.camera_to_blender(pose)
    np.testing.assert_allclose(np.asarray(blender)[:3, :3], np.asarray(pose)[:3, :3])
    np.testing.assert_allclose(frame.camera_to_nerf(blender), pose, atol=1e-9)
    low, high = frame.bounds((1e5 - 1, -2e5 - 2, 3e4 - 3), (1e5 + 1, -2e5 + 2, 3e4 + 3))
    assert all(lo < hi for lo, hi in zip(low, high))
    record = frame.record("fit: test", margin=0.1)
    assert record["scale"] == frame.scale and record["matrix"] == frame.matrix() and record["margin"] == 0.1
    assert IDENTITY.apply((1.0, 2.0, 3.0)) == (1.0, 2.0, 3.0)
    with pytest.raises(ValueError):
        fit_similarity((0, 0, 0), 0.0, 1.0)


def test_bounding_sphere_radius_is_the_farthest_point() -> None:
    points = [1.0, 0.0, 0.0, 0.0, -3.0, 0.0, 0.5, 0.5, 0.5]
    assert bounding_sphere_radius((0.0, 0.0, 0.0), points) == pytest.approx(3.0)
    assert bounding_sphere_radius((0.0, -1.0, 0.0), points) == pytest.approx(2.0)


def test_ray_length_factors_match_the_pixel_rays() -> None:
    k = CameraSettings(resolution_x=9, resolution_y=7, shift_x=0.1, pixel_aspect_x=2.0).intrinsics()
    factors = np.asarray(ray_length_factors(k)).reshape(k.h, k.w)
    rows, columns = np.mgrid[0:k.h, 0:k.w] + 0.5
    expected = np.sqrt(1 + ((columns - k.cx) / k.fl_x) ** 2 + ((rows - k.cy) / k.fl_y) ** 2)
    np.testing.assert_allclose(factors, expected)


# --- scene checks --------------------------------------------------------------------------


def facts(**overrides) -> SceneFacts:
    values = dict(scene="Scene", source="/x/scene.blend", engine="CYCLES", renderable_objects=["Cube"])
    values.update(overrides)
    return SceneFacts(**values)


def test_a_clean_cycles_scene_passes_silently() -> None:
    outcome = evaluate(facts(), allow_missing=False)
    assert outcome.errors == [] and outcome.allowed == [] and outcome.notes == []


def test_missing_files_refuse_and_name_the_file_unless_allowed() -> None:
    missing = [MissingFile("image", "/x/textures/brick.png", "brick.png", ("material 'brick'",), "//textures/brick.png"),
               MissingFile("library", "/x/props.blend", "props.blend", ("object 'Chair'",))]
    outcome = evaluate(facts(missing_files=missing), allow_missing=False)
    message = outcome.error_message("/x/scene.blend")
    assert "\n" not in message and message.startswith("/x/scene.blend: ")
    for needle in ("/x/textures/brick.png", "'//textures/brick.png'", "material 'brick'", "/x/props.blend",
                   "linking object 'Chair'", "--allow-missing"):
        assert needle in message
    allowed = evaluate(facts(missing_files=missing), allow_missing=True)
    assert allowed.errors == [] and len(allowed.allowed) == 2 and allowed.allow_missing
    assert any("magenta" in note for note in allowed.notes)


@pytest.mark.parametrize("allow_missing", [False, True])
def test_nothing_to_render_is_always_refused(allow_missing: bool) -> None:
    outcome = evaluate(facts(renderable_objects=[], render_hidden_objects=["Hidden cube"],
                             other_objects=["Empty", "Light"]), allow_missing)
    assert len(outcome.errors) == 1
    assert "nothing to render" in outcome.errors[0]
    assert "Hidden cube" in outcome.errors[0] and "Empty" in outcome.errors[0]


@pytest.mark.parametrize("engine", ["BLENDER_EEVEE", "BLENDER_EEVEE_NEXT", "BLENDER_WORKBENCH"])
def test_headless_incapable_engines_are_rendered_with_cycles_and_noted(engine: str) -> None:
    outcome = evaluate(facts(engine=engine), allow_missing=False)
    assert outcome.errors == [] and outcome.render_engine == "CYCLES" and outcome.source_engine == engine
    assert any(engine in note and "Cycles" in note for note in outcome.notes)


def test_an_add_on_engine_needs_allow_missing() -> None:
    assert "LUXCORE" in evaluate(facts(engine="LUXCORE"), allow_missing=False).errors[0]
    assert evaluate(facts(engine="LUXCORE"), allow_missing=True).errors == []


def test_colour_management_and_film_are_noted() -> None:
    filmic = facts(view_transform="Filmic", look="Medium High Contrast", exposure=0.5, film_transparent=False)
    notes = " ".join(evaluate(filmic, allow_missing=False).notes)
    assert "Filmic" in notes and "Standard" in notes and "opaque film" in notes
    kept = evaluate(filmic, allow_missing=False, color_management="scene").notes
    assert not any("Filmic" in note for note in kept)


# --- materials -----------------------------------------------------------------------------


def principled(**inputs) -> dict:
    sockets = {"Metallic": 0.0, "Specular IOR Level": 0.5, "Transmission Weight": 0.0, "Coat Weight": 0.0,
               "Sheen Weight": 0.0, "Alpha": 1.0}
    sockets.update(inputs)
    return {"name": "Principled BSDF", "type": "BSDF_PRINCIPLED",
            "inputs": {name: (value if isinstance(value, dict) else {"value": None, "linked": True}
                              if value == "linked" else {"value": value, "linked": False})
                       for name, value in sockets.items()}}


def node(node_type: str, name: str = "node", linked_outputs=()) -> dict:
    return {"name": name, "type": node_type, "inputs": {}, "linked_outputs": list(linked_outputs)}


def material(*nodes) -> dict:
    return {"name": "m", "objects": ["Cube"], "nodes": list(nodes)}


def test_default_principled_is_view_dependent_through_its_specular_lobe() -> None:
    verdict = classify_material(material(principled()))
    assert verdict.view_dependent and "specular 0.5" in verdict.reasons[0] and not verdict.transparent


def test_principled_without_specular_or_metal_is_diffuse() -> None:
    verdict = classify_material(material(principled(**{"Specular IOR Level": 0.0})))
    assert not verdict.view_dependent and verdict.reasons == []


def test_blender_3_socket_names_are_understood() -> None:
    old = {"name": "p", "type": "BSDF_PRINCIPLED", "inputs": {
        "Specular": {"value": 0.0, "linked": False}, "Clearcoat": {"value": 0.3, "linked": False},
        "Sheen": {"value": 0.0, "linked": False}, "Transmission": {"value": 0.0, "linked": False},
        "Metallic": {"value": 0.0, "linked": False}, "Alpha": {"value": 1.0, "linked": False}}}
    verdict = classify_material(material(old))
    assert verdict.view_dependent and verdict.reasons == ["Principled BSDF 'p': clearcoat 0.3"]


@pytest.mark.parametrize(
    ("nodes", "view_dependent", "transparent", "reason"),
    [
        ([principled(Metallic="linked", **{"Specular IOR Level": 0.0})], True, False, "metallic driven by a link"),
        ([principled(**{"Transmission Weight": 0.5, "Specular IOR Level": 0.0})], True, True, "transmission 0.5"),
        ([principled(Alpha=0.5, **{"Specular IOR Level": 0.0})], False, True, "alpha 0.5"),
        ([principled(**{"Sheen Weight": 1.0, "Specular IOR Level": 0.0})], True, False, "sheen 1"),
        ([node("BSDF_DIFFUSE")], False, False, None),
        ([node("BSDF_DIFFUSE"), node("EMISSION")], False, False, None),
        ([node("BSDF_GLOSSY", "Gloss")], True, False, "glossy BSDF 'Gloss'"),
        ([node("BSDF_GLASS")], True, True, "glass"),
        ([node("BSDF_TRANSPARENT")], False, True, "transparent BSDF"),
        ([node("PRINCIPLED_VOLUME")], False, True, "volume"),
        ([node("BSDF_DIFFUSE"), node("LAYER_WEIGHT")], True, False, "Layer Weight"),
        ([node("BSDF_DIFFUSE"), node("NEW_GEOMETRY", "Geo", ["Position"])], False, False, None),
        ([node("BSDF_DIFFUSE"), node("NEW_GEOMETRY", "Geo", ["Incoming"])], True, False, "Incoming"),
        ([], False, False, None),
    ],
)
def test_material_classification(nodes, view_dependent, transparent, reason) -> None:
    verdict = classify_material(material(*nodes))
    assert verdict.view_dependent == view_dependent and verdict.transparent == transparent
    if reason:
        assert any(reason in text for text in verdict.reasons + verdict.transparency_reasons)
    assert verdict.record()["objects"] == ["Cube"]


def test_appearance_facts_hold_each_constant_input_and_say_why_one_varies() -> None:
    texture = {"value": None, "linked": True, "from": {"type": "TEX_NOISE", "label": "Noise Texture", "name": "N"}}
    facts = appearance_facts({"uses_nodes": True, "nodes": [
        principled(Metallic=1.0, Roughness=0.1, **{"Coat Roughness": texture}), node("BSDF_GLOSSY", "Gloss")]})
    assert facts["shader"] == "principled" and facts["other_shaders"] == ["glossy BSDF 'Gloss'"]
    inputs = facts["inputs"]
    # 0.1 as Blender's float32 holds it, read back as six digits.
    assert inputs["metallic"] == {"value": 1.0} and inputs["roughness"] == {"value": 0.1}
    assert inputs["coat_roughness"] == {"varies": "driven by the Noise Texture node 'N'"}
    assert inputs["transmission"] == {"value": 0.0} and inputs["alpha"] == {"value": 1.0}
    assert "thin_film_thickness" not in inputs  # a socket the node does not have (Blender < 4.2)


@pytest.mark.parametrize(("sockets", "fact"), [
    ([{"value": 0.2, "linked": False}, {"value": 0.2, "linked": False}], {"value": 0.2}),
    ([{"value": 0.2, "linked": False}, {"value": 0.7, "linked": False}], {"varies": "2 Principled BSDFs hold 0.2, 0.7"}),
    ([{"value": None, "linked": True}], {"varies": "driven by a link"}),
    ([{"value": None, "linked": True, "from": {"type": "GROUP_INPUT", "name": "Group Input"}}],
     {"varies": "driven by a node group's input"}),
])
def test_an_input_over_several_principled_bsdfs_is_one_value_or_varies(sockets, fact) -> None:
    nodes = [{"name": f"P{i}", "type": "BSDF_PRINCIPLED", "inputs": {"Roughness": socket}}
             for i, socket in enumerate(sockets)]
    assert appearance_facts({"uses_nodes": True, "nodes": nodes})["inputs"]["roughness"] == fact


def test_a_material_without_nodes_or_principled_bsdf_says_so() -> None:
    assert appearance_facts({"uses_nodes": False, "nodes": []}) == {"shader": "default", "inputs": {},
                                                                     "other_shaders": []}
    facts = appearance_facts({"uses_nodes": True, "nodes": [node("BSDF_DIFFUSE", "D"), node("EMISSION", "E")]})
    assert facts == {"shader": "other", "inputs": {}, "other_shaders": ["diffuse BSDF 'D'", "emission 'E'"]}
    # A Layer Weight or Fresnel node feeds a shader's input: it is no shader mixed in.
    assert appearance_facts({"uses_nodes": True, "nodes": [principled(), node("LAYER_WEIGHT", "L"),
                                                            node("FRESNEL", "F")]})["other_shaders"] == []
    assert classify_material(material(principled(Metallic=0.5))).record()["appearance"]["inputs"]["metallic"] == \
        {"value": 0.5}


@pytest.mark.parametrize(("nodes", "region", "reason"), [
    ([principled(**{"Transmission Weight": 1.0, "Metallic": 1.0})], "transmissive", "transmission 1"),
    ([principled(**{"Transmission Weight": "linked"})], "transmissive", "transmission varies (driven by a link)"),
    ([node("BSDF_GLASS", "Glass")], "transmissive", "glass BSDF 'Glass'"),
    ([principled(**{"Thin Film Thickness": 500.0, "Metallic": 1.0})], "thin_film", "thin film 500 nm"),
    ([principled(Metallic=1.0)], "metal", "metallic 1"),
    ([principled(Metallic="linked")], "metal", "metallic varies (driven by a link)"),
    ([principled(Metallic=0.3)], "glossy", "Principled BSDF 'Principled BSDF': metallic 0.3"),
    ([principled(**{"Specular IOR Level": 0.0})], "diffuse", "nothing in it depends on the view"),
    ([node("BSDF_DIFFUSE", "D")], "diffuse", "nothing in it depends on the view"),
    ([principled(**{"Specular IOR Level": 0.0, "Alpha": 0.5})], "diffuse", "nothing in it depends on the view"),
])
def test_each_material_gets_the_appearance_region_its_strongest_lobe_asks(nodes, region, reason) -> None:
    """Light through it first, then a thin film, metal, any other view dependence, none; alpha
    alone (a cut-out) is no lobe. The region is one the contract names, with why."""
    from nerf_contract.dataset_layout import APPEARANCE_REGIONS
    record = classify_material(material(*nodes)).record()
    assert (record["region"], record["region_reason"]) == (region, reason)
    assert region in APPEARANCE_REGIONS


def test_cycles_output_node_choice_follows_blender() -> None:
    assert choose_output_node([]) is None
    assert choose_output_node([{"target": "EEVEE", "is_active_output": True}]) is None
    # RobotExpressive's materials: ALL (inactive), EEVEE (active), CYCLES -> the CYCLES one.
    assert choose_output_node([{"target": "ALL"}, {"target": "EEVEE", "is_active_output": True},
                               {"target": "CYCLES"}]) == 2
    assert choose_output_node([{"target": "ALL"}, {"target": "ALL", "is_active_output": True}]) == 1
    assert choose_output_node([{"target": "CYCLES"}, {"target": "CYCLES", "is_active_output": True},
                               {"target": "ALL", "is_active_output": True}]) == 1


# --- EXR and PNG files ---------------------------------------------------------------------


def test_zip_predictor_matches_the_reference_loop() -> None:
    raw = bytes(np.random.default_rng(1).integers(0, 256, 1001, dtype=np.uint8))
    reordered = bytearray(raw[0::2] + raw[1::2])
    expected = bytearray(reordered)
    for i in range(1, len(reordered)):
        expected[i] = (reordered[i] - reordered[i - 1] + 128) & 0xFF
    assert exr._zip_predict(raw) == bytes(expected)


@pytest.mark.parametrize("size", [(1, 1), (37, 21), (64, 48)])
def test_written_exr_reads_back_with_the_openexr_library(tmp_path: Path, size) -> None:
    width, height = size
    rng = np.random.default_rng(2)
    z = rng.random((height, width), dtype=np.float32) * 5
    z[: height // 2] = 0.0  # a background half, as in real views
    a = (rng.random((height, width)) > 0.5).astype(np.float32)
    path = tmp_path / "depth.exr"
    exr.write_float_channels(str(path), width, height, {"Z": z.ravel().tolist(), "A": a.ravel().tolist()})
    with OpenEXR.File(str(path)) as image:
        channels = image.channels()
        assert sorted(channels) == ["A", "Z"]
        assert image.header()["compression"] == OpenEXR.ZIP_COMPRESSION
        np.testing.assert_array_equal(channels["Z"].pixels, z)
        np.testing.assert_array_equal(channels["A"].pixels, a)
    exr.check_file(str(path), width, height, ["Z", "A"])
    with pytest.raises(exr.ExrError, match="channels"):
        exr.check_file(str(path), width, height, ["X", "Y", "Z"])
    with pytest.raises(exr.ExrError, match="size"):
        exr.check_file(str(path), width + 1, height, ["Z", "A"])
    data = path.read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) - 5])
    with pytest.raises(exr.ExrError):
        exr.check_file(str(tmp_path / "cut.exr"), width, height, ["Z", "A"])


@pytest.mark.parametrize("multi_part", [False, True])
def test_reads_uncompressed_single_and_multi_part_files(tmp_path: Path, multi_part: bool) -> None:
    """The layouts Blender 3.x (single part) and 5.x (one part per pass) write for multilayer EXRs."""
    rng = np.random.default_rng(3)
    depth = rng.random((5, 7), dtype=np.float32)
    normal = rng.random((5, 7, 3), dtype=np.float32)
    half = rng.random((5, 7)).astype(np.float16)
    header = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = str(tmp_path / "passes.exr")
    # (The OpenEXR module ignores numpy strides: give it contiguous arrays.)
    layers = {"Layer.Depth.Z": depth, "Layer.Half.V": half,
              **{f"Layer.Normal.{axis}": np.ascontiguousarray(normal[..., i]) for i, axis in enumerate("XYZ")}}
    if multi_part:
        parts = [OpenEXR.Part(dict(header), {name: values}, name=name) for name, values in layers.items()]
        OpenEXR.File(parts).write(path)
    else:
        OpenEXR.File(header, dict(layers)).write(path)  # (the module replaces the dict's values)
    width, height, channels = exr.read_channels(path, list(layers))
    assert (width, height) == (7, 5)
    for name, values in layers.items():
        np.testing.assert_array_equal(np.asarray(channels[name]).reshape(5, 7), values.astype(np.float32))
    with pytest.raises(exr.ExrError, match="no channel"):
        exr.read_channels(path, ["Layer.Combined.A"])


def test_png_check(tmp_path: Path) -> None:
    good = tmp_path / "good.png"
    Image.fromarray(np.zeros((6, 5, 4), np.uint8)).save(good)
    check_rgba8(str(good), 5, 6)
    with pytest.raises(PngError, match="size"):
        check_rgba8(str(good), 6, 5)
    rgb = tmp_path / "rgb.png"
    Image.fromarray(np.zeros((6, 5, 3), np.uint8)).save(rgb)
    with pytest.raises(PngError, match="RGBA"):
        check_rgba8(str(rgb), 5, 6)
    data = good.read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:-20])
    with pytest.raises(PngError):
        check_rgba8(str(tmp_path / "cut.png"), 5, 6)
    corrupt = bytearray(data)
    corrupt[40] ^= 0xFF  # inside IDAT: its CRC no longer matches
    (tmp_path / "corrupt.png").write_bytes(bytes(corrupt))
    with pytest.raises(PngError):
        check_rgba8(str(tmp_path / "corrupt.png"), 5, 6)
    (tmp_path / "text.png").write_text("not a png")
    with pytest.raises(PngError, match="not a PNG"):
        check_rgba8(str(tmp_path / "text.png"), 5, 6)
    # A hand-made IHDR + IEND without pixel data is incomplete.
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    empty = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 5, 6, 8, 6, 0, 0, 0)) + chunk(b"IEND", b"")
    (tmp_path / "empty.png").write_bytes(empty)
    with pytest.raises(PngError, match="incomplete"):
        check_rgba8(str(tmp_path / "empty.png"), 5, 6)


# --- depth and normal conversion -----------------------------------------------------------


def test_depth_is_ray_distance_times_scale_with_background_zero() -> None:
    alpha = [1.0, 0.5, 0.0, 1.0]
    planar = [2.0, 3.0, 4.0, 1.0e10]  # the last: Cycles' "nothing hit"
    factors = [1.0, 1.1, 1.2, 1.3]
    channels = depth_channels(alpha, planar, factors, scale=0.5)
    assert list(channels["Z"]) == pytest.approx([1.0, 1.65, 0.0, 0.0])
    assert list(channels["A"]) == alpha


def test_normals_are_unit_or_zero() -> None:
    channels = normal_channels([1.0, 0.3, 0.0, 1.0], [0.0, 0.2, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0])
    assert list(channels["Z"]) == pytest.approx([1.0, 0.0, 0.0, 0.0])
    assert list(channels["X"]) == pytest.approx([0.0, 1.0, 0.0, 0.0])


# --- output folder, resume and shard decisions ---------------------------------------------


def options(out: Path, **overrides) -> GeneratorOptions:
    return GeneratorOptions(out_dir=str(out), demo=True, **overrides)


def test_output_folder_rules(tmp_path: Path) -> None:
    out = tmp_path / "data"
    check_output_dir(str(out), options(out))  # new folder
    out.mkdir()
    check_output_dir(str(out), options(out))  # empty folder
    (out / "notes.txt").write_text("mine")
    with pytest.raises(DatasetGenError, match="--overwrite"):
        check_output_dir(str(out), options(out))
    check_output_dir(str(out), options(out, overwrite=True))
    with pytest.raises(DatasetGenError, match="no run of datasets_gen"):
        check_output_dir(str(out), options(out, resume=True))
    (out / ".datasets_gen_progress.json").write_text("{}")
    check_output_dir(str(out), options(out, resume=True))
    # Shards share the folder with each other, but not with their own earlier run.
    check_output_dir(str(out), options(out, shard=Shard(1, 2)))
    (out / ".datasets_gen_progress.shard-1-of-2.json").write_text("{}")
    with pytest.raises(DatasetGenError, match="--resume"):
        check_output_dir(str(out), options(out, shard=Shard(1, 2)))
    check_output_dir(str(out), options(out, shard=Shard(0, 2)))
    file_path = tmp_path / "file"
    file_path.write_text("x")
    with pytest.raises(DatasetGenError, match="not a folder"):
        check_output_dir(str(file_path), options(file_path))


def test_settings_differences_are_named() -> None:
    recorded = {"samples": 16, "camera": {"lens_mm": 50.0, "sensor_fit": "AUTO"}, "seed": 0}
    current = {"samples": 8, "camera": {"lens_mm": 35.0, "sensor_fit": "AUTO"}, "seed": 0}
    assert settings_difference(recorded, current) == ["camera.lens_mm", "samples"]
    require_same_settings(recorded, dict(recorded), "x")
    with pytest.raises(DatasetGenError) as error:
        require_same_settings(recorded, current, "/out/.datasets_gen_progress.json")
    message = str(error.value)
    assert "samples 16 there vs 8 now" in message and "camera.lens_mm" in message and "\n" not in message


def test_stale_and_temporary_files_are_removed(tmp_path: Path) -> None:
    for split in ("train", "test"):
        (tmp_path / split).mkdir()
    names = ["r_0.png", "r_1.png", "r_2.png", "r_0_depth.exr", "r_0_normal.exr", "notes.txt"]
    for name in names:
        (tmp_path / "train" / name).write_text("x")
        (tmp_path / "test" / name).write_text("x")
    remove_stale_frames(str(tmp_path), {"train": 2, "test": 2}, depth_splits=["test"])
    assert sorted(os.listdir(tmp_path / "train")) == ["notes.txt", "r_0.png", "r_1.png"]
    assert sorted(os.listdir(tmp_path / "test")) == ["notes.txt", "r_0.png", "r_0_depth.exr", "r_0_normal.exr", "r_1.png"]
    for name in (".r_3.png.123.tmp", ".r_4.png.9.tmp", ".r_4_depth.exr.9.tmp", ".r_5.beauty.exr.77.tmp"):
        (tmp_path / "train" / name).write_text("x")
    remove_temporary_files(str(tmp_path), Shard(0, 2))  # shard 0 owns even views only
    assert sorted(name for name in os.listdir(tmp_path / "train") if name.endswith(".tmp")) == [
        ".r_3.png.123.tmp", ".r_5.beauty.exr.77.tmp"]
    remove_temporary_files(str(tmp_path), None)
    assert not [name for name in os.listdir(tmp_path / "train") if name.endswith(".tmp")]


def write_shard(out: Path, split: str, shard: Shard, views: int, generator: dict, profile: dict) -> None:
    frames = [{"file_path": f"./{split}/r_{i}", "rotation": 0.1, "transform_matrix": np.eye(4).tolist()}
              for i in range(views) if shard.owns(i)]
    for frame in frames:
        (out / (frame["file_path"] + ".png")).write_bytes(b"png")
    document = {"camera_angle_x": 0.69, "fl_x": 1.0, "fl_y": 1.0, "cx": 1.0, "cy": 1.0, "w": 2, "h": 2,
                "world_to_nerf": {"scale": 1.0}, "frames": frames, "generator": generator,
                "shard": {"index": shard.index, "count": shard.count, "scene_profile": profile}}
    (out / f"transforms_{split}.{shard.label}.json").write_text(json.dumps(document))


def test_merge_joins_shards_in_view_order(tmp_path: Path) -> None:
    views = {"train": 5, "val": 2, "test": 3}
    generator = {"views": views, "samples": 8}
    for split in views:
        (tmp_path / split).mkdir()
    for index in range(3):
        for split, count in views.items():
            write_shard(tmp_path, split, Shard(index, 3), count, generator, {"bounds": 1})
    with pytest.raises(DatasetGenError, match="shard-"):
        Path(tmp_path / "transforms_val.shard-2-of-3.json").rename(tmp_path / "aside.json")
        merge(str(tmp_path))
    Path(tmp_path / "aside.json").rename(tmp_path / "transforms_val.shard-2-of-3.json")
    assert merge(str(tmp_path)) == {"bounds": 1}
    for split, count in views.items():
        document = json.loads((tmp_path / f"transforms_{split}.json").read_text())
        assert [frame["file_path"] for frame in document["frames"]] == [f"./{split}/r_{i}" for i in range(count)]
        assert "shard" not in document and document["generator"] == generator
    assert not list(tmp_path.glob("*.shard-*.json"))
    assert json.loads((tmp_path / "scene_profile.json").read_text()) == {"bounds": 1}


def test_merge_refuses_shards_with_different_settings(tmp_path: Path) -> None:
    views = {"train": 2, "val": 0, "test": 0}
    (tmp_path / "train").mkdir()
    for index, samples in ((0, 8), (1, 16)):
        for split, count in views.items():
            write_shard(tmp_path, split, Shard(index, 2), count, {"views": views, "samples": samples}, {})
    with pytest.raises(DatasetGenError, match="generator.samples"):
        merge(str(tmp_path))
    with pytest.raises(DatasetGenError, match="no transforms"):
        merge(str(tmp_path / "train"))


# --- options and command line --------------------------------------------------------------


def test_shard_and_pixel_aspect_parsing() -> None:
    assert Shard.parse("1/4") == Shard(1, 4) and Shard(1, 4).owns(5) and not Shard(1, 4).owns(4)
    for bad in ("4/4", "1", "a/b", "0/0"):
        with pytest.raises(DatasetGenError, match="--shard"):
            Shard.parse(bad)
    assert parse_pixel_aspect("2:1") == (2.0, 1.0)
    with pytest.raises(DatasetGenError, match="--pixel-aspect"):
        parse_pixel_aspect("2")


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--demo", "--out", "o", "--use-scene-camera", "--lens", "35"], "--lens"),
        (["--demo", "--out", "o", "--resume", "--overwrite"], "--resume"),
        (["--demo", "--out", "o", "--shard", "2/2"], "--shard"),
        (["--demo", "--out", "o", "--pixel-aspect", "wide"], "--pixel-aspect"),
        (["--demo", "--out", "o", "--sensor-fit", "DIAGONAL"], "--sensor-fit"),
        (["--demo", "--out", "o", "--resolution-percentage", "0"], "--resolution-percentage"),
        (["--demo", "--out", "o", "--shift-x", "0.7"], "principal point"),
        (["--demo", "--merge", "o"], "--merge"),
        (["--demo"], "--out"),
        (["x.blend", "--demo-variant", "diffuse", "--out", "o"], "--demo-variant"),
    ],
)
def test_bad_flags_are_one_line(args, named, capsys, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.blend").write_bytes(b"BLENDER")
    try:
        status = cli_main(args)
    except SystemExit as exit_request:
        status = exit_request.code
    assert status == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and named in lines[0], lines


# --- the options defined once: GeneratorOptions, its flags and its keywords -------------------

# Departures from the defaults, nested camera settings, shards and switches included.
ROUND_TRIPS = {
    "demo_everything_changed": lambda blend: GeneratorOptions(
        out_dir="out dir", demo=True, demo_variant="diffuse", train_views=7, val_views=0, test_views=3,
        camera=CameraSettings(lens_mm=35.5, sensor_width_mm=30.0, sensor_height_mm=20.25, sensor_fit="VERTICAL",
                              shift_x=-0.05, shift_y=0.1, resolution_x=64, resolution_y=48,
                              resolution_percentage=50, pixel_aspect_x=2.0, pixel_aspect_y=1.5),
        samples=16, seed=12345, full_sphere=True, device="GPU", frame="fit", depth_normals="all",
        allow_missing=True, color_management="scene", resume=True, shard=Shard(1, 4), formats=("ngp",)),
    "builtin_square_check": lambda blend: GeneratorOptions(
        out_dir="", builtin="thin_structure", camera=CameraSettings(resolution_x=100, resolution_y=100),
        check_only=True, frame="blender", overwrite=True, shard=Shard(0, 1)),
    "blend_file_scene_camera": lambda blend: GeneratorOptions(
        out_dir="o", blend_path=blend, use_scene_camera=True, depth_normals="none", seed=2**31 - 1),
    "blender_open_file": lambda blend: GeneratorOptions(
        out_dir="o", blend_path=blend, open_scene=True, train_views=24, val_views=2, test_views=3,
        camera=CameraSettings(resolution_x=32, resolution_y=32), samples=8, resume=True),
    "defaults": lambda blend: GeneratorOptions(out_dir="o", demo=True),
}


@pytest.mark.parametrize("case", sorted(ROUND_TRIPS))
def test_options_to_argv_parses_back_into_the_same_options(case: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.blend").write_bytes(b"BLENDER")
    options = ROUND_TRIPS[case]("x.blend").validate()
    argv = options_to_argv(options)
    parser = build_parser()
    # An open scene is the file Blender opened (blender -b FILE --python generate.py -- ARGV): no flag.
    blender_file = options.blend_path if options.open_scene else ""
    assert options_from_args(parser.parse_args(argv), parser, blender_file) == options, argv
    if case == "defaults":
        assert argv == ["--demo", "--out", "o"]
    if case == "builtin_square_check":
        assert "--resolution" in argv and "--width" not in argv
    # The in-process keywords build the same options from the settings' own values.
    keywords = {setting.keyword: setting.value(options) for setting in SETTINGS}
    assert options_from_keywords(**keywords) == options


def test_every_option_has_one_setting_and_switches_start_off() -> None:
    fields = [field.name for field in dataclasses.fields(GeneratorOptions) if field.name != "camera"]
    fields += [f"camera.{field.name}" for field in dataclasses.fields(CameraSettings)]
    assert sorted(name for setting in SETTINGS for name in setting.targets) == sorted(fields)
    flags = [setting.flag for setting in SETTINGS if setting.flag is not None]
    assert len(flags) == len(set(flags))
    assert all(setting.default is False for setting in SETTINGS if setting.kind is bool)
    assert options_to_argv(DEFAULT_OPTIONS) == []


def test_keywords_name_an_unknown_option_and_parse_text() -> None:
    with pytest.raises(TypeError, match="'lense'.*did you mean 'lens'"):
        generate_dataset("o", demo=True, lense=35.0)
    options = options_from_keywords(out_dir="o", demo=True, shard="1/4", pixel_aspect="2:1", width=64, height=48)
    assert options.shard == Shard(1, 4) and (options.camera.pixel_aspect_x, options.camera.pixel_aspect_y) == (2, 1)
    assert (options.camera.resolution_x, options.camera.resolution_y) == (64, 48)
    with pytest.raises(DatasetGenError, match="--shard"):
        options_from_keywords(shard="4/4")
    with pytest.raises(ValueError, match="use_scene_camera"):
        options_to_argv(dataclasses.replace(options, use_scene_camera=True))


def test_formats_are_validated_and_kept_once_in_order_however_given() -> None:
    parser = build_parser()
    args = parser.parse_args(["--demo", "--out", "o", "--format", "ngp", "--format", "nerf_synthetic,ngp"])
    assert options_from_args(args, parser).formats == ("ngp",)
    assert options_from_keywords(out_dir="o", demo=True, formats=["nerf_synthetic", "ngp"]).formats == ("ngp",)
    assert options_from_keywords(out_dir="o", demo=True, formats=("ngp", "colmap")).formats == ("ngp", "colmap")
    with pytest.raises(DatasetGenError, match="--format must be one of nerf_synthetic, colmap, ngp, got gsplat"):
        options_from_keywords(out_dir="o", demo=True, formats=("gsplat",))
    assert options_to_argv(options_from_keywords(out_dir="o", demo=True, formats="ngp")) == [
        "--demo", "--out", "o", "--format", "ngp"]
