"""`displex bench`: speed and memory of the hot paths, as JSON.

Timings are medians of several runs; each target also times a baseline in the same process so that
ratios survive a noisy machine. Peak memory is the process's resident high-water mark (VmHWM),
reset before the measured phase where Linux allows it.
"""
from __future__ import annotations

import math
import platform
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from capture_sim.atomic import write_json
from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from capture_sim.geometry import pixel_rays
from capture_sim.render import render_olat
from capture_sim.simulator import LightTransport, light_transport, simulate
from patterns.families import make_patterns
from patterns.parameterization import logits_to_patterns, patterns_to_logits
from reconstruct.photometric_stereo import solve_ps
from reconstruct.unrolled_ps import solve_ps_unrolled
from train.capture import capture_scene, scene_exposure
from train.learn import TrainConfig, normal_loss
from train.scene_pixels import ScenePixels, shuffle_pixels

FULL_SIZE = (512, 612)
PUBLISHED_PS_FORWARD_S = 1.2
"""Forward solve of the published implementation, M = 4 over 108 000 pixels, on this kind of machine
(issue 3; we cannot run it here, so it is quoted, and scaled linearly to our pixel count)."""
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
    learning. The simulated captures are made once, outside the timed region.
    """
    pixels = full_frame_pixels()
    patterns = make_patterns("mono_gradient", num_patterns).float()
    with torch.no_grad():
        capture = capture_scene(pixels, patterns, 1.0, "auto", torch.Generator().manual_seed(seed))
    lights, falloff = pixels.lights(), pixels.rig.falloff

    def forward_backward():
        captures = capture.captures.clone().requires_grad_()
        emission = capture.emission.clone().requires_grad_()
        result = solve_ps(captures, emission, pixels.points, lights, falloff)
        (result.normal.sum() + result.albedo.sum()).backward()
        return result

    result = forward_backward()
    peak_reset = reset_peak_rss()
    seconds = median_seconds(forward_backward, repeats, warmup=0)
    peak_mb = peak_rss_mb()
    forward = median_seconds(lambda: solve_ps(capture.captures, capture.emission, pixels.points, lights, falloff), repeats, warmup=0)
    errors = torch.rad2deg(torch.acos((result.normal.detach() * pixels.normal).sum(-1).clamp(-1, 1)))
    return {
        "target": "ps",
        "M": num_patterns,
        "pixels": pixels.num_pixels,
        "lights": pixels.transport.num_lights,
        "full_fwd_bwd_s": seconds,
        "full_fwd_s": forward,
        "peak_rss_mb": peak_mb,
        "peak_measured": "solver phase (VmHWM reset before it)" if peak_reset else "whole process",
        "mae_deg_default_noise": float(errors.mean()),
        "published_fwd_s_108k_pixels": PUBLISHED_PS_FORWARD_S,
        "speedup_vs_published_fwd_same_pixels": PUBLISHED_PS_FORWARD_S * pixels.num_pixels / 108_000 / seconds,
        "repeats": repeats,
        "machine": machine_info(),
    }


def bench_train(num_patterns: int = 4, sampled_pixels: int = 100_000, repeats: int = 5, seed: int = 0) -> dict:
    """One learning step (simulate + unrolled reconstruction + backward), M patterns, sampled pixels.

    As in learning (``train.learn``), the scene's pixels are shuffled once when the run is prepared
    (with the per-pixel light geometry ``light_reach``), and each step takes a random window of them,
    a view with no gather; the step's auto exposure still covers every pixel of the frame.
    """
    pixels = full_frame_pixels()
    prepare_start = time.perf_counter()
    sampler = shuffle_pixels(pixels, sampled_pixels, torch.Generator().manual_seed(seed))
    prepare_s = time.perf_counter() - prepare_start
    logits = patterns_to_logits(make_patterns("tri_random", num_patterns, seed=seed)).requires_grad_()
    config = TrainConfig(num_patterns=num_patterns)
    generator = torch.Generator().manual_seed(seed)
    scene = sampler.scene

    def step():
        logits.grad = None
        part = sampler.draw(generator)
        patterns = logits_to_patterns(logits)
        capture = capture_scene(scene, patterns, 1.0, scene_exposure(pixels, patterns), generator, part)
        normal, _ = solve_ps_unrolled(capture.captures, capture.emission, scene.points[part], scene.lights(), scene.rig.falloff, reach=sampler.reach[:, part])
        normal_loss(normal, scene.normal[part], config.loss).backward()

    step()
    reset_peak_rss()
    seconds = median_seconds(step, repeats, warmup=0)
    return {
        "target": "train",
        "M": num_patterns,
        "sampled_pixels": sampled_pixels,
        "step_s": seconds,
        "prepare_once_s": prepare_s,
        "published_step_s": PUBLISHED_TRAIN_STEP_S,
        "speedup_vs_published": PUBLISHED_TRAIN_STEP_S / seconds,
        "peak_rss_mb": peak_rss_mb(),
        "repeats": repeats,
        "machine": machine_info(),
    }


def bench_invrender(repeats: int = 5) -> dict:
    """Inverse-renderer speed (see ``train.invrender_command.bench_invrender``)."""
    from train.invrender_command import bench_invrender as run

    return {"target": "invrender", **run(repeats=repeats), "machine": machine_info()}


BENCHMARKS: dict[str, Callable[..., dict]] = {"sim": bench_sim, "ps": bench_ps, "train": bench_train, "invrender": bench_invrender}


def run_bench(target: str, json_path: Path | None, repeats: int = 5) -> dict:
    """Run one benchmark target, print a summary and write JSON atomically."""
    if target not in BENCHMARKS:
        raise InputError(f"unknown benchmark {target!r}; choose from {', '.join(BENCHMARKS)}")
    result = BENCHMARKS[target](repeats=repeats)
    if json_path is not None:
        write_json(json_path, result)
    return result
