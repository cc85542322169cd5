"""Shared fixtures and the tolerance table (one place for all tolerances, keyed by dtype)."""
import multiprocessing
import signal
import traceback

import numpy as np
import pytest
import torch

# Two OpenMP threads slow tiny tensors down badly when the machine is shared; one is plenty here.
torch.set_num_threads(1)

TOLERANCE = {
    torch.float32: dict(rtol=1e-5, atol=1e-6),
    torch.float64: dict(rtol=1e-10, atol=1e-12),
}


@pytest.fixture(autouse=True)
def fresh_warnings():
    """Every test sees the warnings ``capture_sim.errors.warn_once`` would give a new command."""
    from capture_sim.errors import forget_warnings

    forget_warnings()


def arrays_from_forked_process(work) -> list:
    """The tensors that ``work()`` returns (a list), computed without gradient in a forked child
    process on one thread (as compare's evaluation workers), as numpy arrays. An exception in the
    child is raised here, with the child's traceback in its message."""
    context = multiprocessing.get_context("fork")
    receiver, sender = context.Pipe(duplex=False)

    def child_main():
        torch.set_num_threads(1)  # a forked child must not enter torch's OpenMP pool
        try:
            with torch.no_grad():
                sender.send(("values", [value.numpy() for value in work()]))
        except BaseException:
            sender.send(("error", traceback.format_exc()))
        sender.close()

    child = context.Process(target=child_main, daemon=True)
    child.start()
    sender.close()
    try:
        assert receiver.poll(120), "the forked process gave no result"
        kind, payload = receiver.recv()
        child.join(30)
    finally:
        child.kill()
    if kind == "error":
        raise AssertionError(f"in the forked process:\n{payload}")
    assert child.exitcode == 0
    return payload


@pytest.fixture
def python_sigint():
    """Python's SIGINT handler (KeyboardInterrupt) for the test. A shell starts a background job
    (``pytest &``) with SIGINT ignored, and Python then leaves it ignored: a Ctrl-C test would
    wait for an interrupt that never comes."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)  # None: not set from Python


@pytest.fixture
def reference_rig():
    from capture_sim.rig import load_rig

    return load_rig()


@pytest.fixture
def tiny_rig():
    """A 2 x 3 panel rig imaging 4 x 5 pixels: small enough for gradcheck and loops."""
    from capture_sim.rig import Camera, Rig, panel_positions

    return Rig(
        name="tiny",
        light_positions=panel_positions(2, 3, diagonal_inch=40.0),
        backlight=np.full((2, 3), 0.02),
        camera=Camera(K_cam=((50.0, 0.0, 2.5), (0.0, 50.0, 2.0), (0.0, 0.0, 1.0)), height=4, width=5),
    )
