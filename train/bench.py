"""`displex bench`: speed and memory of the hot paths, as JSON.

Timings are medians of several runs; each target also times a baseline in the same process so that
ratios survive a noisy machine. Peak memory is the process's resident high-water mark (VmHWM),
reset before the measured phase where Linux allows it.
"""
from __future__ import annotations

import gc
import math
import platform
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import staged_files, write_json
from capture_sim.display import display_emission
from capture_sim.errors import InputError
from capture_sim.rig import check_noise_scale, load_rig
from capture_sim.geometry import pixel_rays
from capture_sim.render import render_olat
from capture_sim.simulator import LightTransport, light_transport, simulate
from capture_sim.synth import default_scene_size
from patterns.families import make_patterns
from patterns.parameterization import logits_to_patterns, patterns_to_logits
from reconstruct.metrics import angular_error_deg
from reconstruct.photometric_stereo import solve_ps
from reconstruct.published import incident_field, solve_published
from reconstruct.unrolled_ps import solve_ps_unrolled
from train.capture import capture_scene, scene_exposure
from train.learn import EXPOSURE_PIXELS, TrainConfig, normal_loss
from train.evaluate import EvalSettings, evaluate_scene
from train.scene_pixels import ScenePixels, scene_pixels, shuffle_pixels
from train.scene_sets import default_split
from train.torch_threads import torch_threads

FULL_SIZE = (512, 612)
PUBLISHED_PS_FORWARD_S = 1.2
"""Forward solve of the published implementation, M = 4 over 108 000 pixels, on this kind of machine
(issue 3, quoted; scaled linearly to our pixel count). ``reconstruct.published`` rebuilds that
computation so the benchmarks also time it in the same process."""
PUBLISHED_PIXELS = 108_000
"""Pixels of the quoted published timing; the in-process replica is timed on this many."""
PUBLISHED_TRAIN_STEP_S = 6.0
"""One training step of the published implementation, M = 4 over 100 000 pixels (issue 4, quoted)."""


def median_seconds(work: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``work()`` over ``repeats`` runs after ``warmup`` unmeasured runs."""
    for _ in range(warmup):
        work()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def reset_peak_rss() -> bool:
    """Reset the process's peak resident set size (Linux ``clear_refs``); False where unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MB (VmHWM, or ru_maxrss as a fallback)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine_info() -> dict:
    return {"python": platform.python_version(), "torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.machine()}


def bench_sim(num_patterns: int = 4, sampled_pixels: int = 100_000, repeats: int = 5, seed: int = 0) -> dict:
    """Forward+backward of simulating ``num_patterns`` patterns on a full 512 x 612 OLAT stack.

    The stack is random (timing does not depend on content). Baseline: one plain numpy einsum
    forward over the same channels-last stack.
    """
    rig = load_rig()
    rng = np.random.default_rng(seed)
    stack = rng.random((rig.num_lights, *FULL_SIZE, 3), dtype=np.float32)
    stack_mb = stack.nbytes / 2**20
    patterns = torch.rand(num_patterns, rig.rows, rig.cols, 3, generator=torch.Generator().manual_seed(seed))
    emitted = (patterns.reshape(num_patterns, -1, 3).numpy() + rig.backlight.reshape(1, -1, 1).astype(np.float32)) ** rig.gamma
    numpy_fwd = median_seconds(lambda: np.einsum("mkc,khwc->mhwc", emitted, stack, optimize=True), repeats)
    transport = light_transport(stack)
    del stack
    generator = torch.Generator().manual_seed(seed)

    def forward_backward(target):
        values = patterns.clone().requires_grad_()
        simulate(values, target, rig, exposure="auto", generator=generator).captures.sum().backward()

    peak_reset = reset_peak_rss()
    full = median_seconds(lambda: forward_backward(transport), repeats)
    peak_mb = peak_rss_mb()
    sampled = transport.subset(torch.randint(0, transport.num_pixels, (sampled_pixels,), generator=torch.Generator().manual_seed(seed)))
    sampled_time = median_seconds(lambda: forward_backward(sampled), repeats)
    return {
        "target": "sim",
        "M": num_patterns,
        "image": list(FULL_SIZE),
        "lights": rig.num_lights,
        "full_fwd_bwd_s": full,
        "sampled_fwd_bwd_s": sampled_time,
        "sampled_pixels": sampled_pixels,
        "numpy_einsum_fwd_s": numpy_fwd,
        "full_vs_numpy_ratio": full / numpy_fwd,
        "peak_rss_mb": peak_mb,
        "peak_measured": "full-stack simulation phase (VmHWM reset before it)" if peak_reset else "whole process",
        "stack_mb": stack_mb,
        "peak_vs_stack_ratio": peak_mb / stack_mb,
        "repeats": repeats,
        "machine": machine_info(),
    }


def full_frame_pixels(height: int = FULL_SIZE[0], width: int = FULL_SIZE[1], chunk: int = 16384) -> ScenePixels:
    """A Lambertian bumpy wall filling the whole frame at the working distance (every pixel valid).

    Its normals tilt by up to ~35 degrees in smooth waves so that pixels see different lights and
    attached shadows, as an object would; used to time the solvers on all 512 x 612 pixels.
    """
    rig = load_rig().with_resolution(height, width)
    rays = pixel_rays(rig.camera.matrix(), height, width).reshape(-1, 3)
    v, u = torch.meshgrid(torch.linspace(0, 6 * math.pi, height), torch.linspace(0, 8 * math.pi, width), indexing="ij")
    depth = rig.working_distance + 0.01 * torch.sin(u).reshape(-1) * torch.cos(v).reshape(-1)
    points = depth[:, None] * rays
    normal = torch.stack([0.5 * torch.sin(u), 0.5 * torch.cos(v), -torch.ones_like(u)], dim=-1).reshape(-1, 3)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    matrix = torch.empty(3, rig.num_lights, height * width)
    albedo = torch.tensor([[0.7, 0.5, 0.4]])
    for start in range(0, height * width, chunk):
        block = slice(start, start + chunk)
        diffuse, _ = render_olat(points[block], normal[block], rig.lights(), torch.ones(points[block].shape[0], 1), albedo, torch.zeros(1), torch.ones(1), rig.falloff)
        matrix[:, :, block] = diffuse.permute(2, 0, 1)
    transport = LightTransport(matrix, torch.arange(height * width), height, width)
    return ScenePixels("full-frame-wall", rig, transport, points, normal, np.ones((height, width), dtype=bool))


def bench_ps(num_patterns: int = 4, repeats: int = 5, seed: int = 0) -> dict:
    """Forward+backward of the analytic photometric stereo on all 512 x 612 pixels, M patterns.

    Gradients flow to the patterns through the effective emission and the captures, as in
    learning. The simulated captures are made once, outside the timed region, and the scene's light
    transport is released before the solver runs. ``speedup_vs_published_fwd_same_pixels`` is the
    quoted published forward time (scaled to this pixel count) over ``full_fwd_bwd_s``, forward and
    backward: conservative. ``full_fwd_bwd_s`` uses the process's thread
    count (torch's default, one per core, unless ``--threads`` set it); ``full_fwd_bwd_s_1_thread``
    repeats it on one thread.
    """
    pixels = full_frame_pixels()
    patterns = make_patterns("mono_gradient", num_patterns).float()
    with torch.no_grad():
        capture = capture_scene(pixels, patterns, 1.0, "auto", torch.Generator().manual_seed(seed))
    lights, falloff, points, true_normal = pixels.lights(), pixels.rig.falloff, pixels.points, pixels.normal
    num_pixels, num_lights = pixels.num_pixels, pixels.transport.num_lights
    # The solver needs only the captures: release the scene's light transport (3 x K x N floats,
    # ~540 MB) so that the peak memory measures the solver, not the simulator's input.
    del pixels
    gc.collect()

    def forward_backward():
        captures = capture.captures.clone().requires_grad_()
        emission = capture.emission.clone().requires_grad_()
        result = solve_ps(captures, emission, points, lights, falloff)
        (result.normal.sum() + result.albedo.sum()).backward()
        return result

    # Keep the normals only: the result's graph would hold the solver's light field (~180 MB at
    # this size) through the timed runs and count it in their peak memory.
    estimate = forward_backward().normal.detach()
    peak_reset = reset_peak_rss()
    seconds = median_seconds(forward_backward, repeats, warmup=0)
    peak_mb = peak_rss_mb()
    forward = median_seconds(lambda: solve_ps(capture.captures, capture.emission, points, lights, falloff), repeats, warmup=0)
    # The solver is many small per-pixel operations besides the large matrix products: measure
    # whether torch's intra-op threads pay off on this machine.
    with torch_threads(1):
        single_thread = median_seconds(forward_backward, repeats, warmup=0)
    errors = angular_error_deg(estimate, true_normal)
    replica = published_ps_seconds(capture.captures, capture.emission, points, lights, falloff, repeats)
    scale = num_pixels / PUBLISHED_PIXELS
    return {
        "target": "ps",
        "M": num_patterns,
        "pixels": num_pixels,
        "lights": num_lights,
        "full_fwd_bwd_s": seconds,
        "full_fwd_s": forward,
        "threads": torch.get_num_threads(),
        "full_fwd_bwd_s_1_thread": single_thread,
        "peak_rss_mb": peak_mb,
        "peak_measured": "solver phase (VmHWM reset before it)" if peak_reset else "whole process",
        "mae_deg_default_noise": float(errors.mean()),
        "published_fwd_s_108k_pixels": PUBLISHED_PS_FORWARD_S,
        # The published forward time (the quoted figure) over our forward AND backward: a
        # conservative ratio; against our forward alone it would be full_fwd_s's.
        "speedup_vs_published_fwd_same_pixels": PUBLISHED_PS_FORWARD_S * scale / seconds,
        "replica_fwd_s_108k_pixels": replica["fwd"],
        "replica_fwd_bwd_s_108k_pixels": replica["fwd_bwd"],
        "speedup_vs_replica_fwd_bwd_same_pixels": replica["fwd_bwd"] * scale / seconds,
        "repeats": repeats,
        "machine": machine_info(),
    }


def published_ps_seconds(captures, emission, points, lights, falloff, repeats: int) -> dict:
    """Median forward and forward+backward seconds of the rebuilt published solver
    (``reconstruct.published``) on the first ``PUBLISHED_PIXELS`` pixels; its incident field is
    an input there, so it is built outside the timed region."""
    part = slice(0, PUBLISHED_PIXELS)
    incident = incident_field(points[part], lights, falloff)
    captures = captures[:, part]

    def forward_backward():
        values, emitted = captures.clone().requires_grad_(), emission.clone().requires_grad_()
        normal, albedo = solve_published(values, emitted, incident)
        (normal.sum() + albedo.sum()).backward()

    with torch.no_grad():
        forward = median_seconds(lambda: solve_published(captures, emission, incident), repeats)
    return {"fwd": forward, "fwd_bwd": median_seconds(forward_backward, repeats)}


def published_train_step_seconds(scene: ScenePixels, part: slice, logits: torch.Tensor, repeats: int, seed: int) -> float:
    """Median seconds of a training step in the published computation's layout: patterns from
    logits, captures as an einsum over the (N, K, 3) OLAT values of the sampled pixels with
    Gaussian noise and clipping, the rebuilt published solver (``reconstruct.published``), the
    angular loss and its backward. Exposure is fixed, as there."""
    rig = scene.rig
    olat = scene.transport.matrix[:, :, part].permute(2, 1, 0).contiguous()  # (N, K, 3)
    incident = incident_field(scene.points[part], scene.lights(), rig.falloff)
    truth = scene.normal[part]

    def emitted():
        return display_emission(logits_to_patterns(logits), rig.backlight_flat(olat.dtype), rig.gamma, rig.scale)

    with torch.no_grad():
        exposure = 0.9 / float(torch.einsum("mkc,nkc->mnc", emitted(), olat).max())
    generator = torch.Generator().manual_seed(seed)

    def step():
        logits.grad = None
        emission = exposure * emitted()
        clean = torch.einsum("mkc,nkc->mnc", emission, olat)
        captures = (clean + 1e-3 * torch.randn(clean.shape, generator=generator)).clamp(0, 1)
        normal, _ = solve_published(captures, emission, incident)
        normal_loss(normal, truth, "angular").backward()

    return median_seconds(step, repeats)


def bench_train(num_patterns: int = 4, sampled_pixels: int = 100_000, repeats: int = 5, seed: int = 0) -> dict:
    """One learning step (simulate + unrolled reconstruction + backward), M patterns, sampled pixels.

    As in learning (``train.learn``), the scene's pixels are shuffled once when the run is prepared
    (with the per-pixel light geometry ``light_reach``), and each step takes a random window of them,
    a view with no gather; the step's auto exposure reads a fixed sample of ``EXPOSURE_PIXELS``.
    """
    pixels = full_frame_pixels()
    prepare_start = time.perf_counter()
    sampler = shuffle_pixels(pixels, sampled_pixels, torch.Generator().manual_seed(seed))
    prepare_s = time.perf_counter() - prepare_start
    del pixels  # learning keeps only the shuffled copy
    exposure_pixels = sampler.every_pixel(EXPOSURE_PIXELS)
    logits = patterns_to_logits(make_patterns("tri_random", num_patterns, seed=seed)).requires_grad_()
    config = TrainConfig(num_patterns=num_patterns)
    generator = torch.Generator().manual_seed(seed)
    scene = sampler.scene

    def step():
        logits.grad = None
        part = sampler.draw(generator)
        patterns = logits_to_patterns(logits)
        capture = capture_scene(scene, patterns, 1.0, scene_exposure(exposure_pixels, patterns), generator, part)
        normal, _ = solve_ps_unrolled(capture.captures, capture.emission, scene.points[part], scene.lights(), scene.rig.falloff, reach=sampler.reach[:, part])
        normal_loss(normal, scene.normal[part], config.loss, config.angle_cap_deg).backward()

    step()
    reset_peak_rss()
    seconds = median_seconds(step, repeats, warmup=0)
    peak_mb = peak_rss_mb()
    replica = published_train_step_seconds(scene, slice(0, sampled_pixels), logits, repeats, seed)
    return {
        "target": "train",
        "M": num_patterns,
        "sampled_pixels": sampled_pixels,
        "step_s": seconds,
        "prepare_once_s": prepare_s,
        "published_step_s": PUBLISHED_TRAIN_STEP_S,
        "speedup_vs_published": PUBLISHED_TRAIN_STEP_S / seconds,
        "replica_step_s": replica,
        "speedup_vs_replica": replica / seconds,
        "peak_rss_mb": peak_mb,
        "repeats": repeats,
        "machine": machine_info(),
    }


def bench_invrender(repeats: int = 5) -> dict:
    """Inverse-renderer speed (see ``train.bench_invrender.bench_invrender``)."""
    from train.bench_invrender import bench_invrender as run

    return {"target": "invrender", **run(repeats=repeats), "machine": machine_info()}


SWEEP_NOISE_SCALES = (0.0, 0.25, 1.0, 4.0, 10.0)
"""Default noise levels of the sweep: multiples of the rig's noise variances (0 = ideal sensor)."""
SWEEP_METHODS = (("woodham", "olat", 0), ("ps", "mono_gradient", 4), ("ps", "tri_complementary", 2), ("ps", "tri_gradient", 2))
"""Default (method, pattern family or 'olat', M) of the sweep (issue 3, item 5)."""


def noise_sweep(scenes: list[ScenePixels], noise_scales=SWEEP_NOISE_SCALES, methods=SWEEP_METHODS, seed: int = 0, progress: bool = True) -> dict:
    """Normal error against noise level for several methods and pattern sets.

    Every (method, patterns) pair is evaluated on every scene at every noise scale with
    ``train.evaluate.evaluate_scene`` (auto exposure, the same noise seeds for every method).

    Args:
        scenes: prepared scenes with true normals.
        noise_scales: multipliers of the rig's noise variances (0 = noise-free, unquantised).
        methods: (method 'ps' or 'woodham', pattern family name or 'olat', M) triples; M is
            ignored for 'olat' (the full stack).
        seed: noise seed (scene i at noise level j uses seed (seed * 100 + j) * 1000 + i).
        progress: show a progress bar.

    Returns:
        {"noise_scales": [...], "scenes": [names], "methods": [{"label", "method", "patterns",
        "M", "mae": [...], "median": [...], "invalid_fraction": [...], "scene_mae": [[...]]}]}
        where mae, median and invalid_fraction are means over scenes per noise scale (degrees)
        and scene_mae[j][i] is scene i's MAE at noise scale j.
    """
    if not scenes:
        raise InputError("the noise sweep needs at least one scene")
    if not noise_scales:
        raise InputError("the noise sweep needs at least one noise scale")
    for scale in noise_scales:
        check_noise_scale("noise scale", scale)
    rig = scenes[0].rig
    rows = []
    bar = tqdm(total=len(methods) * len(noise_scales) * len(scenes), desc="noise sweep", unit="solve", disable=not progress)
    for method, family, num_patterns in methods:
        patterns = "olat" if family == "olat" else make_patterns(family, num_patterns, rig.rows, rig.cols).float()
        label = f"{method} / OLAT ({rig.num_lights})" if family == "olat" else f"{method} / {family} M={num_patterns}"
        row = {"label": label, "method": method, "patterns": family, "M": rig.num_lights if family == "olat" else num_patterns}
        per_scale = []
        for level, scale in enumerate(noise_scales):
            settings = EvalSettings(method=method, noise_scale=float(scale), seed=seed * 100 + level)
            metrics = []
            for index, pixels in enumerate(scenes):
                metrics.append(evaluate_scene(pixels, patterns, settings, index).metrics)
                bar.update()
            per_scale.append(metrics)
        for key in ("mae", "median", "invalid_fraction"):
            row[key] = [float(np.mean([m[key] for m in metrics])) for metrics in per_scale]
        row["scene_mae"] = [[m["mae"] for m in metrics] for metrics in per_scale]
        rows.append(row)
    bar.close()
    return {"noise_scales": [float(scale) for scale in noise_scales], "scenes": [pixels.name for pixels in scenes], "methods": rows}


def sweep_chart(document: dict, path: Path, caption: str) -> None:
    """Chart of a ``noise_sweep`` document: mean MAE (degrees) against noise scale, one line per method."""
    from train.figures import save_figure, plt

    fig, axes = plt.subplots(figsize=(7.0, 4.5))
    scales = document["noise_scales"]
    # A symmetric-log axis shows the noise-free point (0) next to the multiplicative levels.
    for row in document["methods"]:
        axes.plot(scales, row["mae"], marker="o", label=row["label"])
    axes.set_xscale("symlog", linthresh=0.25)
    axes.set_xticks(scales, labels=[f"{scale:g}" for scale in scales])
    axes.minorticks_off()
    axes.set_ylim(bottom=0)
    axes.set_xlabel("noise scale (x the rig's noise variances; 0 = ideal sensor; log scale above 0.25)")
    axes.set_ylabel("mean angular error (degrees)")
    axes.set_title(f"Normal error against noise ({len(document['scenes'])} scenes)")
    axes.grid(True, alpha=0.3)
    axes.legend()
    fig.text(0.01, -0.02, caption, fontsize=8, ha="left", va="top", wrap=True)
    save_figure(fig, path)


def run_sweep(json_path: Path | None, size: tuple[int, int] | None = None, noise_scales=SWEEP_NOISE_SCALES, methods=SWEEP_METHODS, seed: int = 0, progress: bool = True) -> dict:
    """``displex bench ps --sweep``: the noise sweep on the default synthetic test scenes.

    Writes the JSON to ``json_path`` and the chart next to it (same name, .png), moved into place
    together (a chart that fails leaves an earlier run's pair as it was).
    """
    rig = load_rig()
    size = size or default_scene_size(rig)
    scenes = [scene_pixels(scene, rig, require_normals=True) for scene in default_split("test", rig, size, seed)]
    start = time.perf_counter()
    document = noise_sweep(scenes, noise_scales, methods, seed, progress)
    document.update({"target": "ps_sweep", "size": list(size), "rig": rig.name, "seconds": time.perf_counter() - start, "machine": machine_info()})
    if json_path is not None:
        json_path = Path(json_path)
        caption = (
            f"Default synthetic test scenes at {size[0]}x{size[1]}, auto exposure; MAE averaged over the scenes' masked "
            "pixels, then over scenes. Noise scale multiplies the rig's shot and read noise variances."
        )
        with staged_files(json_path.parent, last=(json_path.name,)) as staging:
            sweep_chart(document, staging / json_path.with_suffix(".png").name, caption)
            write_json(staging / json_path.name, document)
    return document


BENCHMARKS: dict[str, Callable[..., dict]] = {"sim": bench_sim, "ps": bench_ps, "train": bench_train, "invrender": bench_invrender}


def run_bench(target: str, json_path: Path | None, repeats: int = 5) -> dict:
    """Run one benchmark target and write its JSON atomically; returns the results."""
    if target not in BENCHMARKS:
        raise InputError(f"unknown benchmark {target!r}; choose from {', '.join(BENCHMARKS)}")
    result = BENCHMARKS[target](repeats=repeats)
    if json_path is not None:
        write_json(json_path, result)
    return result
