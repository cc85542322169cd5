"""The output files and figures of `displex invrender`: normals, basis weights, BRDF spheres,
held-out relighting and the model-selection chart."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from capture_sim.atomic import save_npy, write_json
from capture_sim.png import write_png
from capture_sim.shapes import Sphere, cast_camera_rays
from reconstruct.basis_render import render_under_patterns
from reconstruct.inverse_render import InverseRenderResult
from reconstruct.metrics import angular_error_deg
from reconstruct.model_selection import SelectionConfig
from reconstruct.relight import TEST_EVERY, VALIDATION_EVERY
from train.figures import ERROR_MAP_MAX_DEG, for_display, image_grid, normal_panel, normal_to_rgb, save_figure


def write_outputs(out: Path, output: dict, config, result: InverseRenderResult, relit, data, split, pixels, selection, scene) -> None:
    """Write `displex invrender`'s output files (``train.invrender_command.OUTPUT_FILES``, the
    model-selection chart with a selection, config.json and result.json) into ``out``."""
    transport = pixels.transport
    normal_image = transport.to_image(result.normal).numpy().astype(np.float32)
    save_npy(out / "normals.npy", normal_image)
    mask = scene.mask
    write_png(out / "normals.png", np.round(np.where(mask[..., None], normal_to_rgb(normal_image), 0.0) * 255).astype(np.uint8))
    box = mask_box(scene.mask)
    _normals_figure(out / "normals_figure.png", normal_image, scene, output, box)
    save_npy(out / "weights.npy", transport.to_image(result.weights).numpy().astype(np.float32))
    weight_maps = transport.to_image(result.weights, fill=math.nan).numpy()
    fig = image_grid(
        [weight_maps[box][..., j] for j in range(result.num_basis)],
        [f"basis {j}" for j in range(result.num_basis)],
        f"Basis weights of {scene.name} (J = {result.num_basis})",
        "Per-pixel weight of each basis BRDF (softmax, sums to 1); outside the mask blank.",
        # One range for all: weights lie on the simplex, and per-panel ranges drew a basis that
        # barely varies around 0.02 as boldly as one that carries the surface.
        cmap="viridis", colorbar_label="weight", limits=[(0.0, 1.0)] * result.num_basis,
    )
    save_figure(fig, out / "weights.png")
    _brdf_spheres(out / "brdf_spheres.png", result, pixels.rig)
    _relit_figure(out / "relit.png", relit, data.test_truth, split.test, transport, output, box)
    if selection is not None:  # without one, an earlier --basis auto run's chart goes (``_run``)
        _selection_chart(out / "model_selection.png", selection, config.selection)
    write_json(out / "config.json", config.to_dict())
    write_json(out / "result.json", output)


def mask_box(mask: np.ndarray, margin: int = 4) -> tuple[slice, slice]:
    """Row and column slices of the (H, W) bool ``mask``'s bounding box grown by ``margin`` pixels
    (clipped to the image): figures show the object, not the empty frame around it."""
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return slice(None), slice(None)
    height, width = mask.shape
    return (slice(max(int(rows.min()) - margin, 0), min(int(rows.max()) + margin + 1, height)),
            slice(max(int(cols.min()) - margin, 0), min(int(cols.max()) + margin + 1, width)))


def _normals_figure(path: Path, normal_image: np.ndarray, scene, output: dict, box) -> None:
    import matplotlib.pyplot as plt

    mask = scene.mask[box]
    normal_image = normal_image[box]
    panels = [("estimate", normal_panel(normal_image, mask))]
    error = None
    if scene.normal is not None:
        true_normal = scene.normal[box]
        panels.append(("ground truth", normal_panel(true_normal, mask)))
        angle = angular_error_deg(torch.as_tensor(normal_image), torch.as_tensor(true_normal, dtype=torch.float32)).numpy()
        error = np.where(mask, angle, np.nan)
    columns = len(panels) + (error is not None)
    fig, axes = plt.subplots(1, columns, figsize=(3.4 * columns, 3.4), squeeze=False)
    for ax, (title, image) in zip(axes[0], panels):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    if error is not None:
        ax = axes[0, -1]
        # The fixed scale of evaluate's error maps, so that the two commands' figures compare.
        shown = ax.imshow(error, cmap="magma", vmin=0.0, vmax=ERROR_MAP_MAX_DEG, interpolation="nearest")
        fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.04, label="angular error (deg)",
                     extend="max" if float(np.nanmax(error)) > ERROR_MAP_MAX_DEG else "neither")
        ax.set_title(f"error, MAE {output['mae']:.2f} deg", fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"Normals of {scene.name}")
    fig.text(0.5, 0.005, "Camera-frame normals as RGB (x right = red, y up = green, towards camera = blue)"
             + (f"; error colours saturate at {ERROR_MAP_MAX_DEG:g} deg." if error is not None else "."), ha="center", fontsize=8)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    save_figure(fig, path)


def sphere_pixels(size: int = 96, radius: float = 0.05, distance: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A sphere nearly filling a ``size`` x ``size`` view: (N, 3) float32 points (metres) and normals
    (camera frame) of its visible pixels, and the (size, size) bool mask."""
    focal = 0.9 * size * distance / (2.0 * radius)  # the whole sphere, with a small margin
    K_cam = np.array([[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]])
    hits = cast_camera_rays(Sphere((0.0, 0.0, distance), radius), K_cam, size, size)
    return hits.points[hits.mask].float(), hits.normals[hits.mask].float(), hits.mask


def _brdf_spheres(path: Path, result: InverseRenderResult, rig) -> None:
    """Each basis BRDF on a sphere lit by one superpixel (upper left quadrant of the display)."""
    points, normals, mask = sphere_pixels(distance=rig.working_distance)
    light = rig.lights()[(rig.rows // 4) * rig.cols + rig.cols // 4][None].float()
    distance = float((light[0] - torch.tensor([0.0, 0.0, rig.working_distance])).norm())
    # Exposure: a white Lambertian patch facing the light at the sphere's distance reads 0.8.
    exposure = 0.8 * math.pi / float(rig.falloff(torch.tensor(distance)))
    emission = torch.full((1, 1, 3), exposure)
    images = []
    for j in range(result.num_basis):
        specular = result.specular[j : j + 1] if result.specular_enabled else None
        rendered = render_under_patterns(normals, points, light, emission, torch.ones(points.shape[0], 1), result.diffuse[j : j + 1],
                                         specular, result.roughness[j : j + 1], rig.falloff)
        image = torch.ones((mask.numel(), 3))
        image[mask.reshape(-1)] = for_display_tensor(rendered[0])
        images.append(image.reshape(*mask.shape, 3).numpy())
    titles = [
        f"basis {j}: rho_d ({', '.join(f'{v:.2f}' for v in result.diffuse[j].tolist())})\n"
        + (f"rho_s {float(result.specular[j]):.3f}, r {float(result.roughness[j]):.2f}" if result.specular_enabled else "Lambertian")
        for j in range(result.num_basis)
    ]
    fig = image_grid(images, titles, "Recovered basis BRDFs",
                     f"Each basis on a sphere lit by superpixel ({rig.rows // 4}, {rig.cols // 4}); exposure {exposure:.3g} "
                     "(white Lambertian facing the light = 0.8), clipped, display gamma 1/2.2.")
    save_figure(fig, path)


def for_display_tensor(values: torch.Tensor) -> torch.Tensor:
    """Linear values to display values (clip to [0, 1], gamma 1/2.2), as a tensor."""
    return torch.as_tensor(for_display(values.detach().numpy()))


def _relit_figure(path: Path, relit, truth, test_lights, transport, output: dict, box, count: int = 4) -> None:
    """Held-out lights: truth, relit and 10x absolute error, one row per light (cropped to ``box``)."""
    import matplotlib.pyplot as plt

    chosen = np.unique(np.linspace(0, relit.shape[0] - 1, min(count, relit.shape[0])).round().astype(int))
    fig, axes = plt.subplots(len(chosen), 3, figsize=(9.0, 2.8 * len(chosen) + 0.6), squeeze=False)
    for row, index in enumerate(chosen):
        true_image = transport.to_image(truth[index].clamp(0, 1)).numpy()[box]
        relit_image = transport.to_image(relit[index].clamp(0, 1)).numpy()[box]
        error = np.abs(relit_image - true_image).mean(-1) * 10.0
        light = int(test_lights[index])
        for ax, image, title in ((axes[row, 0], for_display(true_image), f"truth, light {light}"),
                                 (axes[row, 1], for_display(relit_image), f"relit, light {light}"),
                                 (axes[row, 2], error, "|relit - truth| x 10")):
            shown = ax.imshow(image, cmap="magma" if image.ndim == 2 else None, vmin=0, vmax=1, interpolation="nearest")
            ax.set_title(title, fontsize=9)
            ax.set_axis_off()
        fig.colorbar(shown, ax=axes[row, 2], fraction=0.046, pad=0.04, extend="max" if float(np.nanmax(error)) > 1 else "neither")
    fit = output.get("fit", {})
    fig.suptitle(f"Held-out relighting: PSNR {output['psnr']:.2f} dB, SSIM {output['ssim']:.4f}")
    fig.text(0.5, 0.005, f"The final fit ({fit.get('iterations', '?')} iterations) on held-out test lights: every {_ordinal(TEST_EVERY)} superpixel; "
             "exposed OLAT images (auto exposure), display gamma 1/2.2; error is the channel-mean absolute difference times 10 "
             "(1 = 0.1 of full scale; brighter saturates).", ha="center", fontsize=8, wrap=True)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    save_figure(fig, path)


def _ordinal(number: int) -> str:
    """'5th', '6th', '2nd': the light splits' strides in figure captions."""
    suffix = "th" if 10 <= number % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(number % 10, "th")
    return f"{number}{suffix}"


def _selection_chart(path: Path, selection, selection_config: SelectionConfig) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for specular, colour, label in ((False, "tab:blue", "Lambertian bases"), (True, "tab:orange", "GGX specular bases")):
        points = sorted((c.num_basis, c.psnr) for c in selection.curve if c.specular == specular)
        ax.plot([p[0] for p in points], [p[1] for p in points], marker="o", color=colour, label=label)
    best, ceiling = selection.best.psnr, selection_config.psnr_ceiling_db
    band = f"within {selection_config.tolerance_db:g} dB of best" + (f" (PSNRs counted as at most {ceiling:g} dB)" if best > ceiling else "")
    ax.axhspan(min(best, ceiling) - selection_config.tolerance_db, best, color="0.85", label=band)
    chosen = selection.chosen
    ax.plot([chosen.num_basis], [chosen.psnr], marker="*", markersize=16, color="tab:red", linestyle="none",
            label=f"chosen: J = {chosen.num_basis}, {'specular' if chosen.specular else 'Lambertian'}")
    ax.set_xlabel("number of basis BRDFs J")
    ax.set_ylabel("validation relighting PSNR (dB)")
    ax.set_title("Model selection")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.text(0.5, 0.005, f"Each candidate fitted for {selection_config.iterations} steps, scored on every {_ordinal(VALIDATION_EVERY)} fit light "
             "(validation lights, not the test lights of relit.png, whose PSNR is the final fit's); " + selection.rule,
             ha="center", fontsize=7, wrap=True)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    save_figure(fig, path)
