"""`displex bench invrender`: the inverse renderer's speed on a full-resolution object against
the published figure and a naive implementation, and its acceptance fits at 128 x 153."""
from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import torch

from capture_sim.errors import InputError, check_thread_count
from capture_sim.rig import load_rig
from capture_sim.simulator import auto_exposure, sensor
from reconstruct.basis_render import render_under_patterns
from reconstruct.inverse_render import FitConfig, FitProblem
from reconstruct.relight import olat_emission, split_lights
from train.invrender_command import InvRenderConfig, normal_error_stats, run_invrender
from train.torch_threads import torch_threads


PUBLISHED_INVRENDER_1000_ITER_S = 150.0
"""The published baseline inverse renderer on one object, on a GPU (Choi et al., ICCV 2025): DESIGN
section 5 quotes "about 150 s per object"; the iteration count, 1000, is issue 5's reading of it
(its bar: 1000 iterations in 150 s), not a published figure. We cannot run it here; the implied
per-iteration time, 0.15 s, is compared with one full-object iteration of ours on this CPU. The published code
would be slower on a 2-core CPU than on its GPU, so the ratio understates our speedup."""
PUBLISHED_M4_PATTERNS = Path(__file__).resolve().parent.parent / "patterns" / "data" / "ddps" / "optimized_tri_random_4.npy"
"""The published learned M = 4 pattern set (DDPS), fitted in the acceptance part for reference."""


def bench_invrender(repeats: int = 3, iterations: int = 50, family: str = "mono_gradient", num_patterns: int = 4,
                    num_basis: int = 3, seed: int = 0, threads: int = 0, acceptance: bool = True) -> dict:
    """Speed of the inverse renderer on a full 512 x 612 object, and its acceptance runs at 128 x 153.

    Speed (``displex bench invrender``). The object is the svbrdf sphere of ``capture_sim`` at full
    resolution; its captures under ``num_patterns`` patterns of ``family`` are rendered from the true
    parameters (auto exposure, rig noise), which is the image model the fit uses, without building
    the 540 MB OLAT stack. Timed (medians over ``repeats``, wall and process CPU time): the initial
    estimate (photometric stereo on every pixel); the fit's setup (clusters, least-squares albedos,
    shading constants); ``iterations`` Adam steps without normal search at the default batch and
    at a batch of every object pixel; one normal-search round; the full-image evaluation (24
    held-out OLAT images). ``full_1000_iter_s`` is *extrapolated*:
        initial + setup + 1000 * per_iter + (search rounds of the default schedule) * search_round + evaluation
    Baselines: (a) the published implementation's quoted 0.15 s per iteration
    (``PUBLISHED_INVRENDER_1000_ITER_S``), against our full-object iteration; (b) timed in this
    process, one step of a naive implementation that shades every (pixel, light) pair with
    ``capture_sim.render.render_olat`` (broadcast (B, K, 3) geometry) and contracts with einsum.

    Acceptance (``acceptance=True``): ``run_invrender`` on a noise-free 128 x 153 svbrdf sphere
    (three GGX bases), J = 3, from the OLAT fit lights, from M = 4 patterns learned here with the
    default ``displex train`` settings (trained inside the benchmark, a few minutes) and from the
    published learned M = 4 set (``PUBLISHED_M4_PATTERNS``); held-out PSNR, MAE, wall and CPU
    seconds of each.

    Args:
        threads: torch intra-op threads for the whole benchmark (restored afterwards); 0 keeps
            torch's default.

    Returns:
        ``{"full_1000_iter_s", "per_iter_s", "pixels", "peak_rss_mb", ...}`` with the parts above.
    """
    if repeats < 1 or iterations < 1:
        raise InputError("repeats and iterations must be at least 1")
    check_thread_count(threads)
    with torch_threads(threads) as used:
        speed = _bench_speed(repeats, iterations, family, num_patterns, num_basis, seed)
        if acceptance:
            speed["acceptance"] = _bench_acceptance(seed)
        speed["threads"] = used
        return speed


def _timed(work, repeats: int) -> tuple[float, float, object]:
    """Median wall and CPU seconds of ``work()`` over ``repeats`` runs, and the last result."""
    walls, cpus, value = [], [], None
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        value = work()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return statistics.median(walls), statistics.median(cpus), value


def _bench_speed(repeats, iterations, family, num_patterns, num_basis, seed) -> dict:
    from capture_sim.materials import make_material
    from capture_sim.render import render_olat
    from capture_sim.shapes import cast_camera_rays, make_shape
    from capture_sim.simulator import display_emission
    from patterns.families import make_patterns
    from reconstruct.basis_render import EmissionPlan, shading_geometry
    from reconstruct.inverse_render import BasisModel, search_round
    from train.bench import FULL_SIZE, machine_info, peak_rss_mb, reset_peak_rss

    peak_reset = reset_peak_rss()
    height, width = FULL_SIZE
    rig = load_rig()
    camera_rig = rig.with_resolution(height, width)
    hits = cast_camera_rays(make_shape("sphere", seed=seed, distance=rig.working_distance), camera_rig.camera.matrix(), height, width)
    material = make_material("svbrdf", hits.points, seed=seed)
    pixel_index = torch.nonzero(hits.mask.reshape(-1)).squeeze(1)
    points = hits.points.reshape(-1, 3)[pixel_index].float()
    true_normals = hits.normals.reshape(-1, 3)[pixel_index].float()
    weights = material.weights.reshape(-1, material.num_basis)[pixel_index].float()
    lights = rig.lights()
    patterns = make_patterns(family, num_patterns, rig.rows, rig.cols, seed=seed)
    emitted = display_emission(patterns, rig.backlight_flat(), rig.gamma, rig.scale)
    with torch.no_grad():
        radiance = render_under_patterns(true_normals, points, lights, emitted, weights, material.diffuse_albedo.float(),
                                         material.specular_albedo.float(), material.roughness.float(), rig.falloff)
        exposure = auto_exposure(radiance)
        captures = sensor(exposure * radiance, rig.noise, rig.bit_depth, torch.Generator().manual_seed(seed))
    emission = exposure * emitted
    count = int(pixel_index.numel())
    problem = FitProblem(captures, emission, points, lights, rig.falloff, pixel_index, height, width)

    initial_s, initial_cpu_s, initial = _timed(problem.initial_estimate, repeats)

    def steps(batch_pixels, iterations):
        config = FitConfig(num_basis=num_basis, iterations=iterations, normal_search_at=(), seed=seed, batch_pixels=batch_pixels)
        walls, cpus, setups, result = [], [], [], None
        for _ in range(repeats):
            cpu = time.process_time()
            result = problem.fit(config, initial)
            cpus.append(time.process_time() - cpu)
            walls.append(result.seconds - result.setup_seconds)
            setups.append(result.setup_seconds)
        # CPU time of the steps alone: the fit's CPU time minus its setup's share (setup is timed in wall
        # seconds only, and is nearly all single-threaded compute, so the two agree closely).
        step_cpu = statistics.median(cpu - setup for cpu, setup in zip(cpus, setups))
        return statistics.median(walls) / iterations, step_cpu / iterations, statistics.median(setups), result, config

    # The timed fits' config: the default batch, no normal search (timed separately below).
    per_iter, per_iter_cpu, setup_s, result, fit_config = steps(FitConfig().batch_pixels, iterations)
    full_iterations = max(2, iterations // 10)  # a full-object step costs about pixels / batch_pixels default steps
    per_iter_full, per_iter_full_cpu, _, _, _ = steps(count, full_iterations)

    model = BasisModel.from_result(result, fit_config)
    plan = EmissionPlan(emission)
    geometry = shading_geometry(points, lights[plan.light_index], rig.falloff)
    pixels_first = captures.permute(1, 0, 2).contiguous()
    saturated = pixels_first >= fit_config.saturation_threshold
    search_s, search_cpu_s, _ = _timed(lambda: search_round(model, geometry, plan, pixels_first, saturated, fit_config), repeats)
    test_lights = split_lights(rig.num_lights).test
    eval_s, eval_cpu_s, _ = _timed(
        lambda: problem.relight(result, olat_emission(test_lights, rig.num_lights, exposure)), repeats)

    # Naive baseline: broadcast shading of every (pixel, light) pair, then an einsum with the emission.
    batch = torch.randperm(count, generator=torch.Generator().manual_seed(seed))[: min(fit_config.batch_pixels, count)]
    parameters = [initial.normal[batch].clone().requires_grad_(), torch.zeros(batch.numel(), num_basis, requires_grad=True),
                  torch.full((num_basis, 3), 0.5, requires_grad=True), torch.full((num_basis,), 0.5, requires_grad=True),
                  torch.full((num_basis,), 0.5, requires_grad=True)]

    def naive_step():
        normals = parameters[0] / parameters[0].norm(dim=-1, keepdim=True)
        diffuse, specular = render_olat(points[batch], normals, lights, torch.softmax(parameters[1], -1), parameters[2],
                                        parameters[3], parameters[4], rig.falloff)
        images = torch.einsum("mkc,knc->mnc", emission, diffuse + specular)
        torch.sqrt(((images - captures[:, batch]) ** 2).mean()).backward()

    naive_step()
    naive_per_iter, naive_per_iter_cpu, _ = _timed(naive_step, repeats)
    search_rounds = len(FitConfig().normal_search_at)
    published_per_iter = PUBLISHED_INVRENDER_1000_ITER_S / 1000.0
    return {
        "target": "invrender",
        "full_1000_iter_s": initial_s + setup_s + 1000 * per_iter + search_rounds * search_s + eval_s,
        "full_1000_iter_cpu_s": initial_cpu_s + setup_s + 1000 * per_iter_cpu + search_rounds * search_cpu_s + eval_cpu_s,
        "full_1000_iter_extrapolated": True,
        "extrapolation": f"initial estimate + fit setup + 1000 * per_iter + {search_rounds} search rounds + evaluation, "
                         f"each timed separately ({iterations} timed steps per repeat, {full_iterations} at the full "
                         "object); the _cpu_ variant uses process "
                         "CPU time (the quiet-machine equivalent), except for the setup (wall)",
        "per_iter_s": per_iter,
        "per_iter_cpu_s": per_iter_cpu,
        "batch_pixels": fit_config.batch_pixels,
        "per_iter_full_object_s": per_iter_full,
        "per_iter_full_object_cpu_s": per_iter_full_cpu,
        "published_1000_iter_s": PUBLISHED_INVRENDER_1000_ITER_S,
        "published_per_iter_s": published_per_iter,
        "published_source": "Choi et al., ICCV 2025: about 150 s per object on a GPU (DESIGN section 5), taken as "
                            "1000 iterations as issue 5 does; quoted, not run here",
        "speedup_vs_published_per_iter_same_pixels": published_per_iter / per_iter_full,
        "speedup_vs_published_per_iter_same_pixels_cpu": published_per_iter / per_iter_full_cpu,
        "pixels": count,
        "peak_rss_mb": peak_rss_mb(),
        "peak_measured": "speed part (VmHWM reset at its start)" if peak_reset else "whole process",
        "initial_estimate_s": initial_s,
        "fit_setup_s": setup_s,
        "search_round_s": search_s,
        "evaluation_s": eval_s,
        "naive_per_iter_s": naive_per_iter,
        "naive_vs_fast_ratio": naive_per_iter / per_iter,
        "naive_per_iter_cpu_s": naive_per_iter_cpu,
        "naive_vs_fast_ratio_cpu": naive_per_iter_cpu / per_iter_cpu,
        "naive_batch_pixels": int(batch.numel()),
        "image": [height, width],
        "lights": rig.num_lights,
        "patterns": {"family": family, "M": num_patterns},
        "J": num_basis,
        "mae_after_timed_steps": normal_error_stats(result.normal, true_normals)["mae"],
        "repeats": repeats,
        "machine": machine_info(),
    }


def _bench_acceptance(seed: int) -> dict:
    """``run_invrender`` at 128 x 153 on a noise-free svbrdf sphere, from OLAT and from the learned M = 4 set."""
    from capture_sim.scene import save_scene
    from capture_sim.synth import synthesize_scene

    from train.learn import TrainConfig, train_patterns

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "sphere-svbrdf.npz"
        save_scene(synthesize_scene("sphere", "svbrdf", load_rig(), 128, 153, seed=seed + 1), path)
        learned = Path(folder) / "learned_m4.npz"
        train_patterns(TrainConfig(num_patterns=4, seed=seed, val_every=0), learned, progress=False)
        runs = {}
        sources = (("olat", "olat", "olat"), ("learned_m4", str(learned), "learned here (displex train defaults, M = 4, seed " + str(seed) + ")"),
                   ("published_learned_m4", str(PUBLISHED_M4_PATTERNS), PUBLISHED_M4_PATTERNS.name))
        for name, patterns, label in sources:
            output = run_invrender(InvRenderConfig(scene=path, patterns=patterns, basis="3", noise="off", seed=seed))
            runs[name] = {key: output[key] for key in ("psnr", "ssim", "mae", "seconds", "cpu_seconds", "J")}
            runs[name]["patterns"] = label
    return {"scene": "sphere, svbrdf (3 GGX bases), 128 x 153, noise off, seed " + str(seed + 1), "iterations": InvRenderConfig.iterations,
            **runs}
