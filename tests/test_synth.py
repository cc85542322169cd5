"""Shapes, materials and synthetic OLAT scenes (capture_sim.shapes / materials / synth)."""
from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.geometry import pixel_rays
from capture_sim.materials import MATERIALS, make_material
from capture_sim.rig import Falloff, load_rig
from capture_sim.scene import load_scene, save_scene
from capture_sim.shapes import (
    GRAZING_COS, SHAPES, Shape, cast_camera_rays, make_shape, shadow_visibility,
)
from capture_sim.synth import (
    default_scene_set, default_scene_specs, lambertian_sphere, synthesize_scene, write_scene_set,
)

TOL = {"closed_form_rel": 1e-5, "surface_m": 1e-8, "unit": 1e-12}


@pytest.fixture(scope="module")
def rig():
    return load_rig()


def _camera(rig, height, width):
    return rig.with_resolution(height, width).camera.matrix()


# ------------------------------------------------------------------------------------------
# Shapes
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SHAPES)
def test_shape_hits_are_unit_camera_facing_surface_points(rig, name):
    height, width = 40, 48
    K_cam = _camera(rig, height, width)
    shape = make_shape(name, seed=3)
    hits = cast_camera_rays(shape, K_cam, height, width)
    mask = hits.mask
    assert mask.shape == (height, width) and hits.normals.shape == (height, width, 3)
    assert hits.points.shape == (height, width, 3) and hits.depth.shape == (height, width)
    assert 0.1 < mask.float().mean() < 0.9, "shape should fill a good part of the image"
    normals, points = hits.normals[mask], hits.points[mask]
    view = -points / points.norm(dim=-1, keepdim=True)
    assert torch.allclose(normals.norm(dim=-1), torch.ones(len(normals), dtype=torch.float64), atol=TOL["unit"])
    assert bool((normals[:, 2] < 0).all())
    assert bool(((normals * view).sum(-1) >= GRAZING_COS).all())
    # Points lie on their pixel's ray, on the surface, at the stored depth.
    rays = pixel_rays(K_cam, height, width, dtype=torch.float64)[mask]
    assert torch.allclose(points, hits.depth[mask][:, None] * rays, atol=1e-12)
    assert float(shape.sdf(points).abs().max()) < TOL["surface_m"] * shape.lipschitz
    assert bool((hits.depth[mask] > 0.3).all()) and bool((hits.depth[mask] < 0.7).all())
    assert not bool(hits.normals[~mask].any()) and not bool(hits.depth[~mask].any())


def test_sphere_tracing_matches_analytic_sphere_and_ellipsoid(rig):
    height, width = 30, 36
    rays = pixel_rays(_camera(rig, height, width), height, width, dtype=torch.float64).reshape(-1, 3)
    dirs = rays / rays.norm(dim=-1, keepdim=True)
    for name in ("sphere", "ellipsoid"):
        shape = make_shape(name, seed=1)
        exact = shape.camera_hits(dirs)
        traced = Shape.camera_hits(shape, dirs)  # the generic SDF sphere tracer
        both = torch.isfinite(exact) & torch.isfinite(traced)
        assert int(both.sum()) > 0.95 * int(torch.isfinite(exact).sum())
        assert float((exact[both] - traced[both]).abs().max()) < 1e-7
        points = exact[both, None] * dirs[both]
        # The ellipsoid's analytic normal equals the autograd normal of its SDF bound.
        assert torch.allclose(shape.outward_normals(points), Shape.outward_normals(shape, points), atol=1e-10)


def test_shape_seeds_reproduce_and_vary():
    first, again, other = (make_shape("blob", seed=s) for s in (4, 4, 5))
    probe = torch.tensor([[0.01, -0.02, 0.45], [0.05, 0.03, 0.5]], dtype=torch.float64)
    assert torch.equal(first.sdf(probe), again.sdf(probe))
    assert not torch.equal(first.sdf(probe), other.sdf(probe))


def test_shape_bad_input_raises():
    with pytest.raises(InputError, match="unknown shape"):
        make_shape("teapot")
    with pytest.raises(InputError, match="seed"):
        make_shape("sphere", seed=-1)
    with pytest.raises(InputError, match="distance"):
        make_shape("sphere", distance=0.0)


def _min_sdf_on_segments(shape, origins, targets, samples=2000):
    """Plain reference: minimum SDF over dense samples of each segment origin -> target, (N,)."""
    t = torch.linspace(0.0, 1.0, samples, dtype=torch.float64)[None, :, None]
    return shape.sdf(origins[:, None] + t * (targets - origins)[:, None]).amin(dim=1)


def test_shadow_visibility_matches_dense_segment_sampling(rig):
    shape = make_shape("bowl", seed=0)
    hits = cast_camera_rays(shape, _camera(rig, 24, 29), 24, 29)
    points, normals = hits.points[hits.mask], hits.normals[hits.mask]
    lights = rig.lights(dtype=torch.float64)
    visibility = shadow_visibility(shape, points, normals, lights)
    assert visibility.shape == (len(points), rig.num_lights)
    assert set(visibility.unique().tolist()) <= {0.0, 1.0}
    generator = torch.Generator().manual_seed(0)
    pixel = torch.randint(len(points), (400,), generator=generator)
    light = torch.randint(rig.num_lights, (400,), generator=generator)
    facing = ((lights[light] - points[pixel]) * normals[pixel]).sum(-1) > 0
    pixel, light = pixel[facing], light[facing]
    min_sdf = _min_sdf_on_segments(shape, points[pixel] + 1e-4 * normals[pixel], lights[light])
    clearly_blocked, clearly_clear = min_sdf < -1e-4, min_sdf > 1e-4
    assert int(clearly_blocked.sum()) > 5 and int(clearly_clear.sum()) > 5
    assert bool((visibility[pixel[clearly_blocked], light[clearly_blocked]] == 0).all())
    assert bool((visibility[pixel[clearly_clear], light[clearly_clear]] == 1).all())


# ------------------------------------------------------------------------------------------
# Materials
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", MATERIALS)
def test_material_weights_on_simplex(rig, kind):
    hits = cast_camera_rays(make_shape("torus", seed=0), _camera(rig, 32, 38), 32, 38)
    material = make_material(kind, hits.points, seed=2)
    count = material.num_basis
    assert material.diffuse_albedo.shape == (count, 3)
    assert material.specular_albedo.shape == (count,) and material.roughness.shape == (count,)
    assert material.weights.shape == (32, 38, count)
    assert bool((material.weights >= 0).all())
    assert torch.allclose(material.weights.sum(-1), torch.ones(32, 38, dtype=torch.float64), atol=1e-12)
    assert bool(((material.diffuse_albedo >= 0) & (material.diffuse_albedo <= 1)).all())
    assert bool(((material.roughness > 0) & (material.roughness <= 1)).all())
    json.dumps(material.describe())


def test_material_kinds_have_their_character(rig):
    hits = cast_camera_rays(make_shape("relief", seed=0), _camera(rig, 32, 38), 32, 38)
    mask = hits.mask
    textured = make_material("textured", hits.points, seed=1)
    assert float(textured.specular_albedo.abs().max()) == 0.0
    assert float(textured.albedo_map()[mask].std(0).min()) > 0.02, "textured albedo must vary over the surface"
    svbrdf = make_material("svbrdf", hits.points, seed=1)
    assert len(set(svbrdf.roughness.tolist())) == 3 and float(svbrdf.specular_albedo.min()) > 0
    glossy = make_material("glossy", hits.points, seed=1)
    assert float(glossy.roughness.max()) <= 0.25 and float(glossy.specular_albedo.min()) >= 0.6
    regions = make_material("regions", hits.points, seed=1)
    assert float(regions.specular_albedo.min()) == 0.0
    # Near-piecewise regions: most pixels are dominated by one basis.
    assert float((regions.weights[mask].max(-1).values > 0.8).float().mean()) > 0.6
    uniform = make_material("lambertian", hits.points, albedo=0.25)
    assert torch.equal(uniform.diffuse_albedo, torch.full((1, 3), 0.25, dtype=torch.float64))


def test_material_bad_input_raises(rig):
    points = torch.zeros(4, 5, 3, dtype=torch.float64)
    with pytest.raises(InputError, match="unknown material"):
        make_material("velvet", points)
    with pytest.raises(InputError, match="only to material 'lambertian'"):
        make_material("glossy", points, albedo=0.5)
    with pytest.raises(InputError, match="albedo"):
        make_material("lambertian", points, albedo=(0.5, 1.5, 0.2))
    with pytest.raises(InputError, match="points"):
        make_material("textured", torch.zeros(4, 5, 2))


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------


def test_lambertian_sphere_matches_closed_form(rig):
    albedo = np.array([0.2, 0.5, 0.8])
    scene = lambertian_sphere(rig, albedo=albedo, height=64, width=77)
    shape_info = scene.meta["shape"]
    center, radius = np.array(shape_info["center_m"]), shape_info["radius_m"]
    K_cam = scene.K_cam
    lights = rig.light_positions.reshape(-1, 3)
    rows, cols = np.nonzero(scene.mask)
    picks = np.random.default_rng(0).choice(len(rows), 12, replace=False)
    for v, u in zip(rows[picks], cols[picks]):
        # Independent float64 closed form: ray-sphere intersection, normal, albedo/pi cos / d^2.
        ray = np.array([(u - K_cam[0, 2]) / K_cam[0, 0], (v - K_cam[1, 2]) / K_cam[1, 1], 1.0])
        ray /= np.linalg.norm(ray)
        b = ray @ center
        t = b - math.sqrt(b * b - center @ center + radius**2)
        point = t * ray
        normal = (point - center) / radius
        for k in range(len(lights)):
            offset = lights[k] - point
            distance = np.linalg.norm(offset)
            expected = albedo / math.pi * max(0.0, normal @ offset / distance) / distance**2
            got = scene.olat[k, v, u].astype(np.float64)
            assert np.allclose(got, expected, rtol=TOL["closed_form_rel"], atol=1e-12), (v, u, k, got, expected)
        assert np.allclose(scene.normal[v, u], normal, atol=1e-6)
        assert abs(scene.depth[v, u] - point[2]) < 1e-6
    assert float(np.abs(scene.specular).max()) == 0.0


def test_glossy_sphere_specular_matches_hand_written_ggx(rig):
    height, width, seed = 40, 48, 5
    scene = synthesize_scene("sphere", "glossy", rig, height=height, width=width, seed=seed)
    hits = cast_camera_rays(make_shape("sphere", seed=seed), scene.K_cam, height, width)
    material = make_material("glossy", hits.points, seed=seed)
    rho_s, roughness = material.specular_albedo.numpy(), material.roughness.numpy()
    lights = rig.light_positions.reshape(-1, 3)
    rows, cols = np.nonzero(scene.mask)
    checked = 0
    for v, u in zip(rows[::37], cols[::37]):
        point, normal = hits.points[v, u].numpy(), hits.normals[v, u].numpy()
        weights = material.weights[v, u].numpy()
        view = -point / np.linalg.norm(point)
        for k in range(0, len(lights), 7):
            offset = lights[k] - point
            distance = np.linalg.norm(offset)
            light = offset / distance
            n_l, n_v = normal @ light, normal @ view
            if n_l <= 1e-3 or n_v <= 1e-3:
                continue
            half = (light + view) / np.linalg.norm(light + view)
            alpha = roughness**2
            ggx = alpha**2 / (math.pi * ((normal @ half) ** 2 * (alpha**2 - 1) + 1) ** 2)
            k_mask = alpha / 2
            smith = n_l / (n_l * (1 - k_mask) + k_mask) * n_v / (n_v * (1 - k_mask) + k_mask)
            lobe = np.sum(weights * rho_s * ggx * smith / (4 * n_l * n_v))
            expected = lobe * n_l / distance**2
            assert np.allclose(scene.specular[k, v, u], expected, rtol=1e-5, atol=1e-9), (v, u, k)
            checked += 1
    assert checked > 50


def test_scene_arrays_are_consistent(rig):
    scene = synthesize_scene("torus", "svbrdf", rig, height=24, width=29, seed=1)
    num_lights = rig.num_lights
    assert scene.olat.shape == scene.diffuse.shape == scene.specular.shape == (num_lights, 24, 29, 3)
    for stack in (scene.olat, scene.diffuse, scene.specular, scene.normal, scene.depth):
        assert stack.dtype == np.float32 and np.isfinite(stack).all()
    assert scene.light_positions.dtype == np.float32 and scene.light_positions.shape == (rig.rows, rig.cols, 3)
    assert np.array_equal(scene.olat, scene.diffuse + scene.specular)
    assert float(scene.specular.max()) > 0 and float(scene.diffuse.min()) >= 0
    assert float(np.abs(scene.olat[:, ~scene.mask]).max()) == 0.0
    assert float(np.abs(scene.normal[~scene.mask]).max()) == 0.0
    assert bool((scene.depth[scene.mask] > 0).all())
    assert np.allclose(np.linalg.norm(scene.normal[scene.mask], axis=-1), 1.0, atol=1e-6)
    assert np.allclose(scene.K_cam, rig.with_resolution(24, 29).camera.matrix())
    meta = scene.meta
    assert meta["generator"] == "displex.synth" and meta["name"] == "torus-svbrdf-s1"
    assert meta["shape"]["name"] == "torus" and meta["material"]["kind"] == "svbrdf"
    json.dumps(meta)


def test_typical_diffuse_values_are_order_one_tenth_to_one(rig):
    scene = lambertian_sphere(rig, albedo=0.8, height=32, width=38)
    lit = scene.olat[:, scene.mask]
    assert 0.05 < float(np.median(lit[lit > 0])) < 1.0


def test_scenes_reproduce_with_seed_and_differ_across_seeds(rig):
    first = synthesize_scene("blob", "regions", rig, height=16, width=19, seed=7)
    again = synthesize_scene("blob", "regions", rig, height=16, width=19, seed=7)
    other = synthesize_scene("blob", "regions", rig, height=16, width=19, seed=8)
    for key in ("olat", "mask", "normal", "depth", "diffuse", "specular"):
        assert np.array_equal(getattr(first, key), getattr(again, key))
    assert not np.array_equal(first.olat, other.olat)


@pytest.mark.parametrize("shape", ["torus", "bowl"])
def test_cast_shadows_darken_and_never_brighten(rig, shape):
    lit = synthesize_scene(shape, "textured", rig, height=24, width=29, seed=0)
    shadowed = synthesize_scene(shape, "textured", rig, height=24, width=29, seed=0, cast_shadows=True)
    assert np.array_equal(lit.mask, shadowed.mask)
    assert bool((shadowed.olat <= lit.olat).all())
    darker = shadowed.olat < lit.olat * 0.5
    assert int(darker[..., 0].sum()) > 50
    assert shadowed.meta["cast_shadows"] is True


def test_convex_shapes_have_no_cast_shadows(rig):
    sphere = make_shape("sphere")
    hits = cast_camera_rays(sphere, _camera(rig, 16, 19), 16, 19)
    visibility = shadow_visibility(sphere, hits.points[hits.mask], hits.normals[hits.mask], rig.lights(torch.float64))
    assert bool((visibility == 1).all())


def test_synthesis_bad_input_raises(rig):
    with pytest.raises(InputError, match="unknown shape"):
        synthesize_scene("cube", "lambertian", rig)
    with pytest.raises(InputError, match="unknown material"):
        synthesize_scene("sphere", "chrome", rig)
    with pytest.raises(InputError, match="image size"):
        synthesize_scene("sphere", "lambertian", rig, height=0)
    # The reference rig's fitted falloff has a pole at 0.608 m, inside this scene's light distances.
    fitted = rig.replace(falloff=Falloff(kind="fitted", a=-5.4580, b=14.7449))
    with pytest.raises(InputError, match="falloff"):
        synthesize_scene("sphere", "lambertian", fitted, height=12, width=14)


def test_default_specs_split_disjoint_and_cover_material_kinds():
    specs = default_scene_specs(seed=0)
    train_names = {s.name for s in specs["train"]}
    test_names = {s.name for s in specs["test"]}
    assert len(specs["train"]) == 6 and len(specs["test"]) == 4
    assert not train_names & test_names
    train_pairs = {(s.shape, s.material) for s in specs["train"]}
    assert not train_pairs & {(s.shape, s.material) for s in specs["test"]}
    kinds = {s.material for split in specs.values() for s in split}
    assert {"lambertian", "textured", "svbrdf", "glossy"} <= kinds
    assert [s.seed for s in default_scene_specs(seed=1)["train"]] != [s.seed for s in specs["train"]]
    with pytest.raises(InputError):
        default_scene_specs(seed=-2)
    largest = (2**32 - 1 - 9) // 100  # every scene seed 100 * seed + i must be a valid seed
    assert default_scene_specs(seed=largest)["test"][-1].seed == 100 * largest + 9
    with pytest.raises(InputError, match=rf"scene set seed must be a whole number in \[0, {largest}\]"):
        default_scene_specs(seed=largest + 1)


def test_default_scene_set_reproducible(rig):
    first = default_scene_set(rig, height=12, width=14, seed=2)
    again = default_scene_set(rig, height=12, width=14, seed=2)
    other = default_scene_set(rig, height=12, width=14, seed=3)
    assert [s.name for s in first["train"]] == [s.name for s in again["train"]]
    for split in ("train", "test"):
        for a, b in zip(first[split], again[split]):
            assert np.array_equal(a.olat, b.olat) and np.array_equal(a.mask, b.mask)
    assert any(not np.array_equal(a.olat, b.olat) for a, b in zip(first["train"], other["train"]))


def test_write_scene_set_writes_loadable_scenes_and_index(rig, tmp_path):
    index_path = write_scene_set(tmp_path / "set", rig, height=12, width=14, seed=0, progress=False)
    index = json.loads(index_path.read_text())
    assert index["generator"] == "displex.synth" and index["height"] == 12 and index["width"] == 14
    assert len(index["splits"]["train"]) == 6 and len(index["splits"]["test"]) == 4
    entry = index["splits"]["test"][0]
    scene = load_scene(tmp_path / "set" / entry["file"])
    assert scene.name == entry["name"] and scene.olat.shape == (rig.num_lights, 12, 14, 3)
    assert scene.diffuse is not None and scene.normal is not None and scene.depth is not None
    # Commands that use the OLAT stack alone leave the separated stacks unread (2 of 3 stacks' memory).
    olat_only = load_scene(tmp_path / "set" / entry["file"], separated=False)
    assert olat_only.diffuse is None and olat_only.specular is None and np.array_equal(olat_only.olat, scene.olat)
    from train.scene_sets import resolve_scenes

    assert all(s.diffuse is None for s in resolve_scenes([tmp_path / "set" / "test"], "test", rig, separated=False))
    assert all(s.diffuse is None for s in resolve_scenes([], "test", rig, (8, 10), separated=False))
    assert sorted(p.name for p in (tmp_path / "set" / "train").iterdir()) == sorted(
        f"{e['name']}.npz" for e in index["splits"]["train"])


def test_interrupted_scene_set_leaves_the_earlier_set_intact(rig, tmp_path, monkeypatch):
    """New scenes are written into a staging folder and renamed into place at the end, index
    last: an interrupted run leaves an earlier set as it was, index included (it used to
    overwrite the earlier set's files and remove its index), and the staging folder is removed."""
    out = tmp_path / "set"
    write_scene_set(out, rig, height=12, width=14, seed=0, progress=False)
    before = {path.relative_to(out): path.read_bytes() for path in out.rglob("*") if path.is_file()}
    calls = []

    def interrupted_save(scene, path):
        if calls:
            raise KeyboardInterrupt
        calls.append(path)
        save_scene(scene, path)

    monkeypatch.setitem(write_scene_set.__globals__, "save_scene", interrupted_save)
    with pytest.raises(KeyboardInterrupt):
        write_scene_set(out, rig, height=12, width=14, seed=1, progress=False)
    assert len(calls) == 1 and not calls[0].exists()
    assert {path.relative_to(out): path.read_bytes() for path in out.rglob("*") if path.is_file()} == before
    assert sorted(path.name for path in out.iterdir()) == ["index.json", "test", "train"]  # no staging left
    calls.clear()
    with pytest.raises(KeyboardInterrupt):
        write_scene_set(tmp_path / "fresh" / "nested" / "set", rig, height=12, width=14, seed=1, progress=False)
    assert not (tmp_path / "fresh").exists()  # the folders the failed run made are removed with its scenes
    # A finished rewrite replaces the set (same names, other seed) and leaves other files alone.
    monkeypatch.setitem(write_scene_set.__globals__, "save_scene", save_scene)
    (out / "train" / "notes.txt").write_text("mine")
    index = json.loads(write_scene_set(out, rig, height=12, width=14, seed=1, progress=False).read_text())
    assert index["seed"] == 1 and (out / "train" / "notes.txt").read_text() == "mine"
    assert all((out / entry["file"]).is_file() for split in index["splits"].values() for entry in split)


def test_a_blocked_scene_path_is_refused_before_the_synthesis(rig, tmp_path, monkeypatch):
    """A file where a split's folder goes, or a folder where a scene file goes, failed only after
    every scene was synthesised."""
    monkeypatch.setitem(write_scene_set.__globals__, "_synthesised", lambda *args: pytest.fail("the synthesis started"))
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "test").write_text("")
    with pytest.raises(InputError, match="a/test is a file, not a folder"):
        write_scene_set(tmp_path / "a", rig, height=12, width=14, seed=0, progress=False)
    name = default_scene_specs(0)["train"][0].name
    (tmp_path / "b" / "train" / f"{name}.npz").mkdir(parents=True)
    with pytest.raises(InputError, match=f"{name}.npz: it exists and is not a regular file"):
        write_scene_set(tmp_path / "b", rig, height=12, width=14, seed=0, progress=False)


def test_scene_validation_refuses_flipped_normals_bad_intrinsics_and_bad_meta(tmp_path):
    import dataclasses
    import json

    from capture_sim.errors import DisplexWarning, InputError
    from capture_sim.scene import save_scene, validate_scene

    scene = synthesize_scene("sphere", "lambertian", load_rig(), height=16, width=20, seed=0)
    validate_scene(scene)
    with pytest.raises(InputError, match=r"olat must be a numpy array .*convert a tensor with \.numpy\(\)"):
        dataclasses.replace(scene, olat=torch.from_numpy(scene.olat))
    # numpy numbers in the meta are written as JSON numbers
    save_scene(dataclasses.replace(scene, meta={**scene.meta, "scale": np.float32(0.5), "count": np.int64(3)}), tmp_path / "numbers.npz")
    assert json.loads(str(np.load(tmp_path / "numbers.npz")["meta"]))["scale"] == 0.5
    with pytest.raises(InputError, match="face away"):
        validate_scene(dataclasses.replace(scene, normal=-scene.normal))
    with pytest.raises(InputError, match="unit"):
        validate_scene(dataclasses.replace(scene, normal=2 * scene.normal))
    # Huge finite values: one error, no overflow warning (turned into an error here).
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(InputError, match="unit"):
            validate_scene(dataclasses.replace(scene, normal=np.full_like(scene.normal, 1e300, dtype=np.float64)))
        with pytest.raises(InputError, match="coordinates within 1e\\+06 m of the camera"):
            validate_scene(dataclasses.replace(scene, light_positions=np.full_like(scene.light_positions, 1e300, dtype=np.float64)))
    with pytest.raises(InputError, match="K_cam"):
        validate_scene(dataclasses.replace(scene, K_cam=np.zeros((3, 3))))
    sheared = scene.K_cam.copy()
    sheared[1, 0] = sheared[0, 0]  # with the same skew, singular; pixel_rays would ignore it
    sheared[0, 1] = sheared[0, 0]
    with pytest.raises(InputError, match="K_cam must be upper triangular"):
        validate_scene(dataclasses.replace(scene, K_cam=sheared))
    elsewhere = scene.K_cam.copy()
    elsewhere[:2, 2] *= 5  # the intrinsics of a larger image
    with pytest.warns(DisplexWarning, match=rf"principal point \({elsewhere[0, 2]:g}, {elsewhere[1, 2]:g}\) lies outside the {scene.height} x {scene.width} image"):
        validate_scene(dataclasses.replace(scene, K_cam=elsewhere))
    with pytest.raises(InputError, match="depth must be in metres, but its median inside the mask is 4.*millimetres"):
        validate_scene(dataclasses.replace(scene, depth=scene.depth * 1000))
    far = scene.depth.copy()
    far[np.nonzero(scene.mask)[0][0], np.nonzero(scene.mask)[1][0]] = 1e30  # one unset pixel: the falloff was blamed
    with pytest.raises(InputError, match="depth must be at most 20 m inside the mask, but 1 pixel reaches 1e\\+30 m"):
        validate_scene(dataclasses.replace(scene, depth=far))
    from capture_sim.scene import rig_for_scene

    with pytest.raises(InputError, match="its light positions are rig .*'s in millimetres; scene files use metres"):
        rig_for_scene(load_rig(), dataclasses.replace(scene, light_positions=scene.light_positions * 1000))
    recalibrated = scene.light_positions + np.float32(0.1)  # another calibration of the display, ~0.17 m off
    with pytest.raises(InputError, match="in millimetres"):
        rig_for_scene(load_rig(), dataclasses.replace(scene, light_positions=recalibrated * 1000))
    with pytest.warns(DisplexWarning, match="differ from rig"):
        rig_for_scene(load_rig(), dataclasses.replace(scene, light_positions=recalibrated))  # in metres: used, with a warning
    # A small display near the camera: any grid divided by 1000 lies within 0.2 m of its lights,
    # but its own scenes, in metres, match it exactly and are accepted.
    from capture_sim.rig import panel_positions

    small = load_rig().replace(light_positions=panel_positions(3, 4, diagonal_inch=12.0), backlight=np.zeros((3, 4)))
    own = synthesize_scene("sphere", "lambertian", small, height=16, width=20, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.array_equal(rig_for_scene(small, own).light_positions, own.light_positions)
    with pytest.raises(InputError, match="in millimetres"):
        rig_for_scene(small, dataclasses.replace(own, light_positions=own.light_positions * 1000))
    negative = scene.diffuse.copy()
    negative[0, 0, 0, 0] = -0.01  # a noisy polarisation split
    with pytest.raises(InputError, match="diffuse has negative radiance"):
        validate_scene(dataclasses.replace(scene, diffuse=negative))
    with pytest.raises(InputError, match="specular must be float16 or float32, got float64"):
        validate_scene(dataclasses.replace(scene, specular=scene.specular.astype(np.float64)))
    path = tmp_path / "s.npz"
    save_scene(scene, path)
    with np.load(path) as data:
        arrays = dict(data)
    arrays["meta"] = np.array(json.dumps([1, 2]))
    np.savez(path, **arrays)
    with pytest.raises(InputError, match="meta"):
        load_scene(path)


def test_damaged_or_wrong_scene_files_give_one_clear_error(tmp_path):
    import dataclasses

    from capture_sim.scene import save_scene, validate_scene

    scene = synthesize_scene("sphere", "lambertian", load_rig(), height=16, width=20, seed=0)
    with pytest.raises(InputError, match="mask selects no pixels"):
        validate_scene(dataclasses.replace(scene, mask=np.zeros_like(scene.mask)))
    good = tmp_path / "good.npz"
    save_scene(scene, good)  # compressed
    content = good.read_bytes()
    damaged = bytearray(content)
    damaged[len(content) // 3 : len(content) // 3 + 64] = bytes(64)  # inside the compressed OLAT stack
    cases = {
        "empty.npz": (b"", "not a scene file"),
        "text.npz": (b"olat, mask\n", "not a scene file"),
        "truncated.npz": (content[: len(content) // 2], "not a readable scene file"),
        "damaged.npz": (bytes(damaged), "not a readable scene file"),
    }
    for name, (data, message) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match=message):
            load_scene(tmp_path / name)
    np.save(tmp_path / "stack.npy", scene.olat)
    with pytest.raises(InputError, match="plain .npy"):
        load_scene(tmp_path / "stack.npy")
    with np.load(good) as data:
        swapped = {key: value.astype(value.dtype.newbyteorder(">")) if value.dtype.kind == "f" else value for key, value in data.items()}
    np.savez(tmp_path / "big_endian.npz", **swapped)
    assert np.array_equal(load_scene(tmp_path / "big_endian.npz").olat, scene.olat)  # same values, native order
    with np.load(good) as data:
        arrays = dict(data)
    arrays["K_cam"] = np.array([["a", "b", "c"]] * 3)
    np.savez(tmp_path / "strings.npz", **arrays)
    with pytest.raises(InputError, match="K_cam must hold numbers"):
        load_scene(tmp_path / "strings.npz")


def test_default_scene_size_follows_the_rig_camera_and_odd_aspects_are_warned(rig, tmp_path):
    """Default scenes are a quarter of the rig camera (128 x 153 on the reference rig); a size of
    another aspect ratio than the camera's, whose pixels would not be square, is warned."""
    from capture_sim.errors import DisplexWarning
    from capture_sim.rig import Camera
    from capture_sim.synth import check_scene_aspect, default_scene_size

    assert default_scene_size(rig) == (128, 153)
    wide = rig.replace(camera=Camera(K_cam=((90.0, 0.0, 31.5), (0.0, 90.0, 23.5), (0.0, 0.0, 1.0)), height=48, width=64))
    assert default_scene_size(wide) == (12, 16)
    scene = synthesize_scene("sphere", "lambertian", wide)
    assert (scene.height, scene.width) == (12, 16) and scene.K_cam[0, 0] == scene.K_cam[1, 1] == pytest.approx(22.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_scene_aspect(wide, 12, 16)
        check_scene_aspect(wide, 12, 17)  # a pixel's rounding
        check_scene_aspect(rig, 12, 14)
    with pytest.warns(DisplexWarning, match=r"12 x 24 scenes have another aspect ratio than rig .*48 x 64 camera.*12 x 16 would keep them square"):
        check_scene_aspect(wide, 12, 24)
    with pytest.warns(DisplexWarning, match="not square"):
        write_scene_set(tmp_path / "squashed", wide, height=12, width=24, progress=False)
    index = json.loads(write_scene_set(tmp_path / "set", wide, progress=False).read_text())
    assert (index["height"], index["width"]) == (12, 16)
    for height, width in ((None, 14), (0, 14), (-4, 14), (12, 2.5)):  # checked before anything else (a zero divided)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(InputError, match="image size must be positive integers"):
                default_scene_set(wide, height, width, progress=False)
    # Settings resolve an unset size on construction: records name the size the scenes have.
    from train.compare_config import compare_config_from_dict
    from train.learn import TrainConfig
    from train.search import SearchConfig

    assert TrainConfig().scene_size == SearchConfig().scene_size == (128, 153)
    for build in (lambda size: TrainConfig(scene_size=size), lambda size: SearchConfig(scene_size=size),
                  lambda size: compare_config_from_dict({"scene_size": size, "learned_counts": []})):
        assert build((24, 29)).scene_size == (24, 29)
        for bad in ((0, 14), (1, 14), (12,), (12, 14, 3)):
            with pytest.raises(InputError, match="scene_size must be (two whole numbers of at least 2|a list of 2 values)"):
                build(bad)


def test_a_working_distance_synthesis_cannot_place_objects_at_is_named_as_the_rigs(rig):
    """The rig loads (its working distance only needs to be positive), but the shapes are made for
    0.2..5 m: the error named a 'shape distance' the user never set."""
    import dataclasses

    for distance in (0.1, 10.0):
        with pytest.raises(InputError, match=f"rig {rig.name}: synthetic objects are placed at the rig's working_distance, {distance:g} m, which must be 0.2..5 m"):
            synthesize_scene("sphere", "lambertian", dataclasses.replace(rig, working_distance=distance), height=12, width=14)
