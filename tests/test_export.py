"""After training: ``ns-export`` without the water, ``seathru-restore``, ``seathru-medium`` and
``seathru-trim-mesh``, on one tiny model trained once for this module.

The model: a 32x24, 6-view ``seathru-synth`` water scene, supervised with its true range (the
dataset's ``gt_depth``; ``research.depth_source ground-truth``, weight 1), so that in a few seconds its
object field holds the scene's surfaces and leaves the open water empty; these tests are about
what the exports make of such a model. Every export is checked against the scene's truth: no
vertex lies in its open water (where the true range is infinite), and colours are the model's
``clean_display``, not the in-water colour.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import pytest
import torch

from tiny_training import make_scene, tiny_config

ITERATIONS = 200
"""Enough for the supervised range to give opaque surfaces and empty open water at 32x24."""
TSDF_RESOLUTION = 64
"""Voxels along the TSDF box's longest side; a 64th of the surfaces' extent is also the distance
within which a mesh vertex counts as on a surface."""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Dict[str, Path]:
    root = tmp_path_factory.mktemp("export_run")
    scene = make_scene(root)
    config = tiny_config(scene, root / "out", ITERATIONS)
    config.pipeline.model.medium_model = "seathru"
    config.pipeline.model.research.depth_source = "ground-truth"
    config.pipeline.model.depth_loss_mult = 1.0  # 1e-2 leaves a wall in the open water after 200 steps
    from nerfstudio.scripts.train import train_loop

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        config.save_config()
        train_loop(local_rank=0, world_size=1, config=config)  # as ns-train: seeded by machine.seed, whatever ran before
    finally:
        torch.set_num_threads(threads)
    return {"root": root, "scene": scene, "config": config.get_base_dir() / "config.yml"}


@pytest.fixture(scope="module")
def pipeline(run):
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(run["config"], test_mode="test")
    return pipeline


def cli(entrypoint, name: str, *args) -> None:
    """A console script's entry point in this process, with one math thread."""
    argv, threads = sys.argv, torch.get_num_threads()
    sys.argv = [name, *[str(a) for a in args]]
    torch.set_num_threads(1)
    try:
        entrypoint()
    except SystemExit as exit:
        assert not exit.code, f"{name} exited with {exit.code}"
    finally:
        sys.argv = argv
        torch.set_num_threads(threads)


def ns_export(*args) -> None:
    from nerfstudio.scripts import exporter

    cli(exporter.entrypoint, "ns-export", *args)


# ------------------------------------------------------------------ the scene's truth


def views(pipeline, scene: Path) -> List[Tuple[torch.Tensor, np.ndarray]]:
    """``(camera, true range in metres, inf in open water)`` of every training and test view."""
    found = []
    for dataset in (pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset):
        for i, filename in enumerate(dataset.image_filenames):
            truth = np.load(scene / "ground_truth" / "depth" / (Path(filename).stem + ".npy"))
            found.append((dataset.cameras[i], truth))
    return found


def project(camera, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates ``(u, v)`` (pixel centres at ``+0.5``), whether in front, and the distance
    to the camera centre (scene units) of scene-space ``points`` (nerfstudio's OpenGL camera)."""
    c2w = camera.camera_to_worlds.reshape(3, 4).double().numpy()
    local = (points - c2w[:, 3]) @ c2w[:, :3]  # camera frame: x right, y up, looks along -z
    depth = -local[:, 2]
    safe = np.where(depth > 1e-9, depth, 1.0)
    u = float(camera.cx) + float(camera.fx) * local[:, 0] / safe
    v = float(camera.cy) - float(camera.fy) * local[:, 1] / safe
    return np.stack([u, v], axis=-1), depth > 1e-9, np.linalg.norm(points - c2w[:, 3], axis=-1)


def in_open_water(pipeline, scene: Path, points: np.ndarray) -> np.ndarray:
    """Points that some view sees in open water: they project inside its image onto a pixel whose
    true range, and that of all 8 neighbours, is infinite (the ray passes no surface)."""
    hit = np.zeros(len(points), dtype=bool)
    for camera, truth in views(pipeline, scene):
        height, width = truth.shape
        water = np.isinf(truth)
        padded = np.pad(water, 1, constant_values=True)
        open_block = np.ones_like(water)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                open_block &= padded[dy : dy + height, dx : dx + width]
        uv, front, _ = project(camera, points)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        hit[inside] |= open_block[row[inside], col[inside]]
    return hit


def true_surface_points(pipeline, scene: Path) -> torch.Tensor:
    """``(N, 3)``: every view's true surface points (scene units), one per pixel that meets a surface."""
    points = []
    for camera, truth in views(pipeline, scene):
        rays = camera.generate_rays(camera_indices=0)
        scale = float(pipeline.datamanager.train_dataparser_outputs.dataparser_scale)
        surface = torch.from_numpy(np.isfinite(truth))
        ranges = torch.from_numpy(np.where(np.isfinite(truth), truth, 0.0)).float()[..., None] * scale
        points.append((rays.origins + rays.directions * ranges)[surface])
    return torch.cat(points)


def surface_box(pipeline, scene: Path) -> Tuple[List[float], List[float]]:
    """The box (scene units) around every view's true surface points, with a tenth of its size
    as margin: where a TSDF must look (nerfstudio's default box, -1..1, holds the cameras only)."""
    points = true_surface_points(pipeline, scene)
    low, high = points.min(dim=0).values, points.max(dim=0).values
    margin = 0.1 * (high - low)
    return (low - margin).tolist(), (high + margin).tolist()


def camera_images(pipeline, camera) -> Dict[str, np.ndarray]:
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(camera.reshape((1,)))
        return {name: outputs[name].cpu().numpy() for name in ("clean_display", "rgb_display", "accumulation")}


def pixel_of_origin(pipeline, points: np.ndarray):
    """For each point, the training view and pixel whose centre ray it lies on (``-1`` where none):
    nerfstudio's point cloud puts each point on the pixel-centre ray of a training pixel."""
    view = np.full(len(points), -1)
    pixel = np.zeros((len(points), 2), dtype=int)
    cameras = pipeline.datamanager.train_dataset.cameras
    for index in range(len(cameras)):
        uv, front, _ = project(cameras[index], points)
        nearest = np.floor(uv) + 0.5
        on_centre = front & (np.abs(uv - nearest).max(axis=-1) < 1e-3) & (view < 0)
        view[on_centre] = index
        pixel[on_centre] = np.floor(uv[on_centre]).astype(int)[:, ::-1]  # (row, col)
    return view, pixel


# ------------------------------------------------------------------ the exports


def test_pointcloud_is_the_clean_scene_without_open_water(run, pipeline, tmp_path):
    import open3d as o3d

    ns_export(
        "pointcloud", "--load-config", run["config"], "--output-dir", tmp_path,
        "--normal-method", "open3d", "--num-points", 3000, "--num-rays-per-batch", 2048,
    )  # fmt: skip
    cloud = o3d.io.read_point_cloud(str(tmp_path / "point_cloud.ply"))
    points, colours = np.asarray(cloud.points), np.asarray(cloud.colors)
    assert len(points) > 1000 and cloud.has_normals()
    assert np.isfinite(points).all()
    assert not in_open_water(pipeline, run["scene"], points).any()

    view, pixel = pixel_of_origin(pipeline, points)
    assert (view >= 0).mean() > 0.9  # the point cloud's own rays, every one traced back to its pixel
    cameras = pipeline.datamanager.train_dataset.cameras
    compared = 0
    for index in np.unique(view[view >= 0]):
        images = camera_images(pipeline, cameras[int(index)])
        mine = view == index
        rows, cols = pixel[mine, 0], pixel[mine, 1]
        opaque = images["accumulation"][rows, cols, 0] > 0.99  # where straight = premultiplied colour
        clean = images["clean_display"][rows, cols][opaque]
        water = images["rgb_display"][rows, cols][opaque]
        exported = colours[mine][opaque]
        # 8-bit colours of the same ray: within one code (plus round-off) of clean_display ...
        assert np.abs(exported - clean).max() <= 1.01 / 255
        # ... which the in-water colour is not
        assert np.median(np.abs(water - clean).max(axis=-1)) > 4 / 255
        compared += int(opaque.sum())
    assert compared > 100


def test_tsdf_mesh_has_faces_and_clean_colours(run, pipeline, tmp_path):
    import open3d as o3d

    low, high = surface_box(pipeline, run["scene"])
    ns_export(
        "tsdf", "--load-config", run["config"], "--output-dir", tmp_path,
        "--bounding-box-min", *low, "--bounding-box-max", *high,
        "--depth-output-name", "surface_depth", "--downscale-factor", 1, "--resolution", TSDF_RESOLUTION,
        "--texture-method", "nerf", "--num-pixels-per-side", 64, "--target-num-faces", 2000,
    )  # fmt: skip
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "tsdf_mesh.ply"))
    vertices, colours = np.asarray(mesh.vertices), np.asarray(mesh.vertex_colors)
    assert len(mesh.triangles) > 100
    assert (tmp_path / "mesh.obj").is_file() and (tmp_path / "material_0.png").is_file()
    check_mesh_colours(pipeline, vertices, colours)
    # nerfstudio's TSDF meshes the border between carved water and voxels no view sees, some of it
    # in open water (docs/export.md); seathru-trim-mesh removes what a view looks through
    check_trimmed(run, pipeline, tmp_path / "tsdf_mesh.ply")


def test_poisson_mesh_has_faces_and_clean_colours(run, pipeline, tmp_path):
    import open3d as o3d

    ns_export(
        "poisson", "--load-config", run["config"], "--output-dir", tmp_path,
        "--normal-method", "open3d", "--num-points", 3000, "--num-rays-per-batch", 2048,
        "--texture-method", "point_cloud",
    )  # fmt: skip
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "poisson_mesh.ply"))
    vertices, colours = np.asarray(mesh.vertices), np.asarray(mesh.vertex_colors)
    assert len(mesh.triangles) > 100
    check_mesh_colours(pipeline, vertices, colours)
    # a Poisson surface closes around the points and bulges past them into the water
    check_trimmed(run, pipeline, tmp_path / "poisson_mesh.ply")


def check_trimmed(run, pipeline, mesh_path: Path) -> None:
    """``seathru-trim-mesh`` leaves no vertex in the scene's open water, keeps most of the mesh's
    faces and its colours, and leaves the input file as it was."""
    import open3d as o3d

    from seathru_nerfstudio import mesh_trim

    before = mesh_path.read_bytes()
    mesh = o3d.io.read_triangle_mesh(str(mesh_path))
    trimmed_path = mesh_path.with_name("trimmed.ply")
    cli(mesh_trim.entrypoint, "seathru-trim-mesh", "--load-config", run["config"], "--mesh", mesh_path, "--output", trimmed_path)
    trimmed = o3d.io.read_triangle_mesh(str(trimmed_path))
    vertices = np.asarray(trimmed.vertices)
    assert mesh_path.read_bytes() == before
    assert not in_open_water(pipeline, run["scene"], vertices).any()
    # the surfaces stay: the true surface points that have a mesh vertex within a TSDF voxel have one after the trim too
    from scipy.spatial import cKDTree

    surface = true_surface_points(pipeline, run["scene"]).numpy()
    voxel = float((surface.max(axis=0) - surface.min(axis=0)).max()) / TSDF_RESOLUTION
    covered_before = cKDTree(np.asarray(mesh.vertices)).query(surface)[0] < voxel
    covered_after = cKDTree(vertices).query(surface)[0] < voxel
    print(f"trim: {len(vertices)} of {len(mesh.vertices)} vertices kept; surface covered {covered_before.mean():.3f} -> {covered_after.mean():.3f}")
    assert covered_before.mean() > 0.5 and covered_after.mean() > 0.9 * covered_before.mean()
    kept = {tuple(v) for v in np.round(np.asarray(mesh.vertices), 6)}
    assert all(tuple(v) in kept for v in np.round(vertices, 6))  # a subset, nothing moved
    check_mesh_colours(pipeline, vertices, np.asarray(trimmed.vertex_colors))


def test_a_vertex_is_water_where_a_view_looks_through_it_and_a_silhouette_stays():
    """``seen_through``: a camera at the origin looking along -z at a 4x4 image whose left half meets
    a surface at range 2 and whose right half meets nothing. Points nearer than the surface, or
    anywhere on the open side, are water; a point at or behind the surface (within the margin),
    outside the image, or on the surface's outline short of the halfway line between an opaque and
    an open pixel centre (where the bilinear opacity is 0.5), is not."""
    from seathru_nerfstudio.mesh_trim import seen_through

    opacity = np.zeros((4, 4))
    opacity[:, :2] = 1.0
    depth = np.where(opacity > 0, 2.0, 7.0)  # the depth of an open pixel is never read
    c2w = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    intrinsics = (4.0, 4.0, 2.0, 2.0)  # u = 2 + 4 x / depth

    def at(u: float, distance: float) -> np.ndarray:  # on the pixel-centre row 1 (v = 1.5)
        direction = np.array([(u - 2.0) / 4.0, (2.0 - 1.5) / 4.0, -1.0])
        return distance * direction / np.linalg.norm(direction)

    points = np.stack([
        at(0.5, 1.0), at(0.5, 1.95), at(0.5, 3.0), at(1.5, 1.85), at(2.5, 2.0), at(3.5, 50.0),
        at(1.9, 2.0), at(2.1, 2.0), np.array([0.0, 0.0, 5.0]),
    ])  # fmt: skip
    looked = seen_through(points, c2w, intrinsics, opacity, depth, margin=0.1)
    np.testing.assert_array_equal(looked, [True, False, False, True, True, True, False, True, False])


def check_mesh_colours(pipeline, vertices: np.ndarray, colours: np.ndarray) -> None:
    """A mesh's vertex colours, where a training view sees the vertex on an opaque surface pixel at
    its rendered depth, are nearer to that pixel's ``clean_display`` than to its ``rgb_display``
    (a mesh's colours are averages over its vertices' neighbourhood, so no tighter bound)."""
    cameras = pipeline.datamanager.train_dataset.cameras
    nearer_clean = nearer_water = 0
    for index in range(len(cameras)):
        camera = cameras[index]
        images = camera_images(pipeline, camera)
        with torch.no_grad():
            depth = pipeline.model.get_outputs_for_camera(camera.reshape((1,)))["depth"].cpu().numpy()
        uv, front, distance = project(camera, vertices)
        height, width = depth.shape[:2]
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        seen = inside.copy()
        seen[inside] = (images["accumulation"][row[inside], col[inside], 0] > 0.99) & (
            np.abs(distance[inside] - depth[row[inside], col[inside], 0]) < 0.02 * depth[row[inside], col[inside], 0]
        )
        clean = np.abs(colours[seen] - images["clean_display"][row[seen], col[seen]]).sum(axis=-1)
        water = np.abs(colours[seen] - images["rgb_display"][row[seen], col[seen]]).sum(axis=-1)
        nearer_clean += int((clean < water).sum())
        nearer_water += int((water <= clean).sum())
    assert nearer_clean > 20 and nearer_clean > 4 * nearer_water


# ------------------------------------------------------------------ the rgba hook itself


def test_rgba_defaults_to_the_clean_display_colour_with_object_opacity(pipeline):
    """Unit: ``get_rgba_image`` on a camera render of the trained model; its alpha is the object
    opacity, so nerfstudio's ``alpha > 0.5`` filter drops open water."""
    from seathru_nerfstudio import export

    model = pipeline.model
    from nerfstudio.models.base_model import Model

    assert type(model).get_rgba_image is not Model.get_rgba_image, "SeathruModel binds export.get_rgba_image"
    camera = pipeline.datamanager.train_dataset.cameras[0]
    with torch.no_grad():
        outputs = model.get_outputs_for_camera(camera.reshape((1,)))
        rgba = model.get_rgba_image(outputs, "rgb")
        acc = outputs["accumulation"]
        straight = outputs["clean"] / acc.clamp_min(export.OPACITY_THRESHOLD)
        expected = model.viewer_controls.display_output("clean_display", {"clean": straight})
        assert torch.equal(rgba[..., 3:], acc)
        assert torch.allclose(rgba[..., :3], expected)
        opaque = acc[..., 0] > 0.999
        assert opaque.any()
        assert torch.allclose(rgba[..., :3][opaque], outputs["clean_display"][opaque], atol=2e-3)
        water = model.get_rgba_image(outputs, "rgb_display")
        assert torch.equal(water[..., :3], outputs["rgb_display"])
        depth = outputs[export.SURFACE_DEPTH]
        assert torch.equal(depth[acc > 0.5], outputs["depth"][acc > 0.5])
        assert (depth[acc <= 0.5] == torch.finfo(depth.dtype).max).all()


def test_rgba_names_a_bad_colour(pipeline):
    with pytest.raises(ValueError, match="--rgb-output-name depth: not a colour"):
        pipeline.model.get_rgba_image({"accumulation": torch.ones(1, 1), "depth": torch.ones(1, 1)}, "depth")


# ------------------------------------------------------------------ restored photos


def test_restore_writes_every_photo_under_its_input_name(run, pipeline, tmp_path):
    import cv2

    from seathru_nerfstudio import restore

    out = tmp_path / "restored"
    cli(restore.entrypoint, "seathru-restore", "--load-config", run["config"], "--output-dir", out)
    datasets = (pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset)
    inputs = sorted(Path(f).name for dataset in datasets for f in dataset.image_filenames)
    for name in ("clean_display", "clean"):
        assert sorted(p.name for p in (out / name).iterdir()) == inputs
    camera = pipeline.datamanager.eval_dataset.cameras[0]
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(camera.reshape((1,)))
    stem = Path(pipeline.datamanager.eval_dataset.image_filenames[0]).name
    shown = cv2.imread(str(out / "clean_display" / stem), cv2.IMREAD_UNCHANGED)[..., ::-1]
    linear = cv2.imread(str(out / "clean" / stem), cv2.IMREAD_UNCHANGED)[..., ::-1]
    assert shown.dtype == np.uint8 and linear.dtype == np.uint16
    expected_shown = np.round(outputs["clean_display"].numpy() * 255)
    expected_linear = np.round(outputs["clean"].clamp(0, 1).numpy() * 65535)
    assert np.abs(shown - expected_shown).max() <= 1
    assert np.abs(linear.astype(float) - expected_linear).max() <= 1


def test_restore_names_a_bad_output(run, capsys):
    from seathru_nerfstudio.restore import RestoreCommand

    assert RestoreCommand(load_config=run["config"], outputs=["depth"]).main() == 2
    assert "--outputs depth: not an image output" in capsys.readouterr().err


# ------------------------------------------------------------------ the medium as data


def test_checkpoints_write_the_medium_beside_config(run, pipeline):
    from seathru_nerfstudio import medium_report

    written = json.loads((run["config"].parent / medium_report.REPORT_NAME).read_text())
    assert written["step"] == ITERATIONS - 1 and written["unit"] == medium_report.METRE
    model = pipeline.model
    per_metre = torch.nn.functional.softplus(model.medium_field.density_raw.detach().double()) * model.world_scale
    assert np.allclose(written["beta_D"], per_metre[:3].numpy(), rtol=1e-6)
    assert np.allclose(written["beta_B"], per_metre[3:].numpy(), rtol=1e-6)
    assert np.allclose(written["B_inf"], torch.sigmoid(model.medium_field.rgb_logit.detach().double()).numpy(), rtol=1e-6)
    assert written["medium_model"] == "seathru" and written["fit"] is None  # no SfM fit at 200 steps
    assert written["summary"].startswith("medium seathru (step 199): beta_D ")


def test_seathru_medium_command(run, tmp_path, capsys):
    from seathru_nerfstudio import medium_report

    output = tmp_path / "m.json"
    cli(medium_report.entrypoint, "seathru-medium", "--load-config", run["config"], "--output-path", output)
    again = json.loads(output.read_text())
    beside = json.loads((run["config"].parent / medium_report.REPORT_NAME).read_text())
    assert again["beta_D"] == pytest.approx(beside["beta_D"]) and again["B_inf"] == pytest.approx(beside["B_inf"])
    assert again["summary"] in capsys.readouterr().out
    assert medium_report.MediumCommand(load_config=tmp_path / "missing.yml").main() == 2
    assert "missing.yml: no such file" in capsys.readouterr().err


def test_trim_mesh_names_a_missing_or_unusable_input(run, tmp_path, capsys):
    """Bad input to ``seathru-trim-mesh`` gets one line naming the file, and exit status 2."""
    from seathru_nerfstudio.mesh_trim import TrimMeshCommand

    text_mesh = tmp_path / "mesh.obj"
    text_mesh.write_text("v 0 0 0\n")
    cases = [
        (TrimMeshCommand(load_config=tmp_path / "missing.yml", mesh=text_mesh), "missing.yml"),
        (TrimMeshCommand(load_config=run["config"], mesh=tmp_path / "missing.ply"), "missing.ply"),
        (TrimMeshCommand(load_config=run["config"], mesh=text_mesh), "mesh.obj"),
        (TrimMeshCommand(load_config=run["config"], mesh=text_mesh.with_suffix(".ply"), margin=-1.0), "--margin"),
    ]
    text_mesh.with_suffix(".ply").write_text("ply\n")
    for command, named in cases:
        assert command.main() == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and named in lines[0], lines
