"""`displex bench`: speed and memory of the hot paths, as JSON.

Timings are medians of several runs; each target also times a baseline in the same process so that
ratios survive a noisy machine. Peak memory is the process's resident high-water mark (VmHWM),
reset before the measured phase where Linux allows it.
"""
from __future__ import annotations

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
from capture_sim.simulator import light_transport, simulate

FULL_SIZE = (512, 612)


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


BENCHMARKS: dict[str, Callable[..., dict]] = {"sim": bench_sim}


def run_bench(target: str, json_path: Path | None, repeats: int = 5) -> dict:
    """Run one benchmark target, print a summary and write JSON atomically."""
    if target not in BENCHMARKS:
        raise InputError(f"unknown benchmark {target!r}; choose from {', '.join(BENCHMARKS)}")
    result = BENCHMARKS[target](repeats=repeats)
    if json_path is not None:
        write_json(json_path, result)
    return result
