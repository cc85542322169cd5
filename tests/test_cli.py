"""The command line end to end on tiny scenes: outputs, exit codes, one-line errors."""
import argparse
import io
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from capture_sim.errors import MAX_THREADS, DisplexWarning, InputError
from capture_sim.rig import load_rig
from capture_sim.scene import load_scene, save_scene
from capture_sim.simulator import auto_exposure
from capture_sim.synth import synthesize_scene
from patterns.io import save_patterns
from train.cli import run


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("scenes") / "blob.npz"
    save_scene(synthesize_scene("blob", "svbrdf", load_rig(), height=24, width=29, seed=3), path)
    return path


def _pattern_file(tmp_path, kind, rig):
    shape = (rig.rows, rig.cols, 3)
    values = {
        "one_hot": np.eye(rig.num_lights, dtype=np.float32)[[0, 17, 80, 143]][..., None].repeat(3, -1).reshape(4, *shape),
        "random": np.random.default_rng(2).uniform(0, 1, (3, *shape)).astype(np.float32),
        "white": np.ones((1, *shape), dtype=np.float32),
    }[kind]
    path = tmp_path / f"{kind}.npy"
    np.save(path, values)
    return path, values


@pytest.mark.parametrize("kind,exposure", [("one_hot", "auto"), ("random", "auto"), ("white", "0.05")])
def test_simulate_matches_numpy_from_meta(tmp_path, scene_file, kind, exposure):
    rig = load_rig()
    pattern_path, values = _pattern_file(tmp_path, kind, rig)
    out = tmp_path / "sim"
    assert run(["simulate", "--scene", str(scene_file), "--patterns", str(pattern_path), "--out", str(out), "--noise", "off", "--exposure", exposure]) == 0
    meta = json.loads((out / "meta.json").read_text())
    captures = np.load(out / "captures.npy")
    olat = np.load(scene_file)["olat"].astype(np.float64)
    backlight = np.asarray(meta["backlight"]).reshape(1, -1, 1)
    emitted = meta["scale"] * (values.reshape(len(values), -1, 3).astype(np.float64) + backlight) ** meta["gamma"]
    expected = np.clip(meta["exposure"] * np.einsum("mkc,khwc->mhwc", emitted, olat), 0.0, 1.0)
    assert meta["bit_depth"] is None
    np.testing.assert_allclose(captures, expected, rtol=1e-5, atol=1e-7)
    if kind == "white":
        assert (captures == 1.0).any(), "clipping must be visible"
    mask = np.load(scene_file)["mask"]
    if exposure == "auto":  # set by the object's pixels, not the background's
        radiance = np.einsum("mkc,khwc->mhwc", emitted, olat)[:, mask]
        assert meta["exposure"] == pytest.approx(auto_exposure(torch.as_tensor(radiance, dtype=torch.float32)), rel=1e-5)
    assert meta["saturated_fraction"] == pytest.approx(float((captures[:, mask] >= 1.0).mean()))  # of the object, not the background
    assert (out / "contact_sheet.png").is_file() and len(list(out.glob("capture_*.png"))) == len(values)


def test_bad_inputs_give_one_line_and_status_2(tmp_path, scene_file, capsys):
    rig = load_rig()
    good, _ = _pattern_file(tmp_path, "random", rig)
    outside = tmp_path / "outside.npy"
    np.save(outside, np.full((2, rig.rows, rig.cols, 3), 1.5, dtype=np.float32))
    wrong_grid = tmp_path / "grid.npy"
    np.save(wrong_grid, np.full((2, 4, 8, 3), 0.5, dtype=np.float32))
    nan_scene = tmp_path / "nan.npz"
    with np.load(scene_file) as data:
        arrays = dict(data)
    arrays["olat"] = arrays["olat"].copy()
    arrays["olat"][0, 0, 0, 0] = np.nan
    np.savez(nan_scene, **arrays)
    newline_scene = tmp_path / "newline.npz"
    meta = json.loads(str(arrays["meta"]))
    np.savez(newline_scene, **{**arrays, "meta": np.array(json.dumps({**meta, "name": "bad\nname"}))})
    cases = [
        ["evaluate", "--scenes", str(newline_scene), "--patterns", str(good)],  # a newline in the name, NaN in the stack
        ["simulate", "--scene", str(tmp_path / "missing.npz"), "--patterns", str(good), "--out", str(tmp_path / "a")],
        ["simulate", "--scene", str(nan_scene), "--patterns", str(good), "--out", str(tmp_path / "b")],
        ["simulate", "--scene", str(scene_file), "--patterns", str(outside), "--out", str(tmp_path / "c")],
        ["simulate", "--scene", str(scene_file), "--patterns", str(wrong_grid), "--out", str(tmp_path / "d")],
        ["simulate", "--scene", str(scene_file), "--patterns", str(good), "--out", str(tmp_path / "e"), "--exposure", "-3"],
        ["evaluate", "--scenes", str(scene_file), "--patterns", str(outside)],
        ["export", "--patterns", str(wrong_grid), "--out", str(tmp_path / "f")],
        ["train", "--init", "no_such_family", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "g.npz")],
        ["train", "--seed", "-1", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "g.npz")],
        ["search", "--seed", "-1", "--maxeval", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "h.npz")],
        ["patterns", "make", "--family", "mono_gradient", "--M", "4", "--out", str(scene_file / "inside_a_file.npz")],
        ["bench", "ps", "--size", "8x8"],
        # Numbers beyond what the generators, NLopt or torch's thread pool take.
        ["evaluate", "--scenes", str(scene_file), "--patterns", str(good), "--seed", str(2**70)],
        ["patterns", "make", "--family", "tri_random", "--M", "2", "--seed", str(2**40), "--out", str(tmp_path / "i.npz")],
        ["search", "--maxeval", str(2**40), "--scenes", str(scene_file), "--out", str(tmp_path / "j.npz")],
        ["invrender", "--scene", str(scene_file), "--threads", str(10**8)],
        # A binary file given as a config, a pattern file given as a scene.
        ["train", "--config", str(good), "--out", str(tmp_path / "k.npz")],
        ["simulate", "--scene", str(good), "--patterns", str(good), "--out", str(tmp_path / "l")],
        # A folder where a file goes; a non-finite weight.
        ["patterns", "make", "--family", "olat", "--M", "2", "--out", str(tmp_path)],
        ["train", "--rerender-weight", "nan", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "m.npz")],
        # A pattern file written among the scenes it learns from (later read as a scene).
        ["train", "--steps", "1", "--scenes", str(scene_file.parent), "--out", str(scene_file.parent / "n.npz")],
        ["search", "--maxeval", "1", "--scenes", str(scene_file.parent), "--out", str(scene_file.parent / "n.npz")],
    ]
    from train.cli import _refuse_out_among_scenes

    _refuse_out_among_scenes(scene_file.parent / "n.NPZ", [str(scene_file.parent)])  # not read as a scene (*.npz is case-sensitive)
    if Path("/proc/self").is_dir():  # a folder where no file can be created: refused before the timing
        cases.append(["bench", "sim", "--repeats", "1", "--json", "/proc/bench.json"])
    for argv in cases:
        capsys.readouterr()
        assert run(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("displex: error:") and "\n" not in err, (argv, err)
    for name in "abcdef":
        assert not (tmp_path / name).exists() or not any((tmp_path / name).iterdir()), f"half-written output in {name}"


def test_rig_exposure_is_the_default_exposure(tmp_path, scene_file):
    """--exposure defaults to the rig's setting: a fixed gain in the rig file is used as is."""
    text = (load_rig.__globals__["RIG_DIR"] / "dir-odyssey-ark.toml").read_text()
    assert 'exposure = "auto"' in text
    (tmp_path / "fixed.toml").write_text(text.replace('exposure = "auto"', "exposure = 0.5", 1))
    good, _ = _pattern_file(tmp_path, "random", load_rig())
    for rig, mode in ((str(tmp_path / "fixed.toml"), "fixed"), ("dir-odyssey-ark", "auto")):
        out = tmp_path / mode
        assert run(["simulate", "--scene", str(scene_file), "--patterns", str(good), "--out", str(out), "--rig", rig]) == 0
        meta = json.loads((out / "meta.json").read_text())
        assert meta["exposure_mode"] == mode and (meta["exposure"] == 0.5) == (mode == "fixed")


def test_evaluate_warns_when_every_pixel_is_invalid(tmp_path, scene_file, capsys):
    rig = load_rig()
    black = tmp_path / "black.npy"
    np.save(black, np.zeros((4, rig.rows, rig.cols, 3), dtype=np.float32))
    capsys.readouterr()
    assert run(["evaluate", "--patterns", str(black), "--scenes", str(scene_file)]) == 0
    assert "warning: every pixel of blob-svbrdf-s3 is flagged invalid" in capsys.readouterr().err


def test_evaluate_warns_that_woodham_solves_the_channels_of_a_colour_set_alone(tmp_path, scene_file, capsys):
    from patterns.families import make_patterns

    for family, warned in (("tri_gradient", True), ("mono_gradient", False)):
        path = tmp_path / f"{family}.npy"
        np.save(path, make_patterns(family, 4).numpy())
        capsys.readouterr()
        assert run(["evaluate", "--patterns", str(path), "--scenes", str(scene_file), "--method", "woodham"]) == 0
        assert ("warning: Woodham solves each colour channel on its own" in capsys.readouterr().err) == warned, family


def test_scene_black_inside_its_mask_is_reported(tmp_path, scene_file, capsys):
    """A scene lit only outside its mask (a wrong mask, a failed capture) is named by every command
    that prepares scenes; a lit scene is not."""
    with np.load(scene_file) as data:
        arrays = dict(data)
    for key in ("olat", "diffuse", "specular"):
        if key in arrays:
            arrays[key][:, arrays["mask"]] = 0.0
            arrays[key][:, ~arrays["mask"]] = 0.1  # the background is lit
    black = tmp_path / "black.npz"
    np.savez(black, **arrays)
    commands = {
        "evaluate": ["evaluate", "--patterns", "olat", "--scenes"],
        "train": ["train", "--steps", "1", "--fresh", "--out", str(tmp_path / "p.npz"), "--scenes"],
        "simulate": ["simulate", "--patterns", str(_pattern_file(tmp_path, "random", load_rig())[0]), "--out", str(tmp_path / "sim"), "--scene"],
    }
    for name, command in commands.items():
        for scene, warned in ((black, True), (scene_file, False)):
            capsys.readouterr()
            assert run([*command, str(scene)]) == 0, name
            err = capsys.readouterr().err
            assert (f"displex: warning: scene blob-svbrdf-s3 ({scene}) is black inside its mask" in err) == warned, (name, err)


def test_scene_lights_far_from_the_rig_are_reported(tmp_path, scene_file, capsys):
    """A scene made for another rig is reported once for all the scenes of that rig; one that
    records no rig (or the same) is reported per scene when its lights are far from the rig's."""
    import dataclasses

    text = (load_rig.__globals__["RIG_DIR"] / "panel-32in-5x10.toml").read_text()
    (tmp_path / "flat.toml").write_text(text.replace("rows = 5", "rows = 9").replace("cols = 10", "cols = 16"))
    scene = load_scene(scene_file)
    unnamed, named = tmp_path / "unnamed", tmp_path / "named"
    unnamed.mkdir()
    named.mkdir()
    for index in range(3):
        meta = {key: value for key, value in scene.meta.items() if key not in ("rig", "file")}
        save_scene(dataclasses.replace(scene, meta={**meta, "name": f"copy{index}"}), unnamed / f"copy{index}.npz")
        save_scene(dataclasses.replace(scene, meta={**meta, "name": f"copy{index}", "rig": "dir-odyssey-ark"}), named / f"copy{index}.npz")
    recorded = "displex: warning: scenes made for rig 'dir-odyssey-ark' are used with rig 'panel-32in-5x10': their own light positions"
    for rig, scenes, warning, count in ((str(tmp_path / "flat.toml"), scene_file, recorded, 1), ("dir-odyssey-ark", scene_file, recorded, 0),
                                        (str(tmp_path / "flat.toml"), named, recorded, 1),  # importing scipy between scenes reset Python's registry
                                        (str(tmp_path / "flat.toml"), unnamed, "its light positions differ from rig panel-32in-5x10's", 3)):
        capsys.readouterr()
        assert run(["evaluate", "--patterns", "olat", "--scenes", str(scenes), "--rig", rig]) == 0
        err = capsys.readouterr().err
        assert err.count(warning) == count, err


def test_unusable_inputs_are_named(tmp_path, scene_file, capsys):
    """Inputs that used to pass silently or with a misleading message: each error names the problem."""
    good, _ = _pattern_file(tmp_path, "random", load_rig())
    good_npz = tmp_path / "good.npz"
    with np.load(scene_file) as data:
        arrays = dict(data)
    variants = {"dark": {"olat": np.zeros_like(arrays["olat"])}, "bool_depth": {"depth": arrays["mask"].copy()},
                "mm_depth": {"depth": (arrays["depth"] * 1000).astype(np.uint16)}}
    for name, changes in variants.items():
        np.savez(tmp_path / f"{name}.npz", **{**arrays, **changes})
    rig_text = (load_rig.__globals__["RIG_DIR"] / "panel-55in-4x8.toml").read_text()
    for name, (old, new) in {"gamma": ("gamma = 2.2", "gamma = 22.0"), "rows": ("rows = 4", "rows = 4.5"),
                             "height": ("height = 512", "height = 0")}.items():
        (tmp_path / f"{name}.toml").write_text(rig_text.replace(old, new))
    (tmp_path / "inf_noise.toml").write_text("noise_scale = inf\n")
    simulate = ["simulate", "--patterns", str(good), "--out", str(tmp_path / "out"), "--scene"]
    cases = [
        (simulate + [str(scene_file.parent)], "is a folder, not a scene file"),
        (simulate + [str(tmp_path / "dark.npz")], "every OLAT value is 0"),
        (simulate + [str(tmp_path / "bool_depth.npz")], "depth must hold floating-point values"),
        (simulate + [str(tmp_path / "mm_depth.npz")], "depth must hold floating-point values"),
        (simulate + [str(scene_file), "--exposure", "1e300"], "exposure 1e+300 is too large"),
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), "--exposure", "1e300"], "exposure 1e+300 is too large"),
        (simulate + [str(scene_file), "--rig", str(tmp_path / "gamma.toml")], "display gamma must lie in"),
        (simulate + [str(scene_file), "--rig", str(tmp_path / "rows.toml")], "panel grid must be whole numbers"),
        (["train", "--config", str(tmp_path / "inf_noise.toml"), "--out", str(tmp_path / "t.npz")], "noise_scale must be a number in [0, 1e+06]"),
        (["scenes", "synth", "--out", str(tmp_path / "tiny"), "--size", "2x2"], "covers no pixel centre of a 2 x 2 image"),
        (simulate + [str(scene_file), "--rig", str(tmp_path / "height.toml")], "camera height and width must be whole numbers"),
        # argparse's own errors, in one line too.
        (["train", "--M", "1.5", "--out", str(tmp_path / "t.npz")], "train: argument --M: invalid int value"),
        (["evaluate", "--patterns", "olat", "--scenes", ""], "empty path"),
        (["evaluate", "--patterns", "", "--scenes", str(scene_file)], "argument --patterns: empty path"),
        (["patterns", "list", "--M", "0"], "--M must be at least 1, got 0"),
        # Outputs that would destroy an input.
        (["evaluate", "--patterns", str(good), "--scenes", str(scene_file), "--json", str(good)], "would destroy"),
        # evaluate --out: its maps and results must not replace the pattern file or --json (or the reverse).
        (["evaluate", "--patterns", str(tmp_path / "eo" / f"{scene_file.stem}_normal.npy"), "--scenes", str(scene_file), "--out",
          str(tmp_path / "eo")], "also the pattern file"),
        (["evaluate", "--patterns", str(good), "--scenes", str(scene_file), "--out", str(tmp_path / "e2"), "--json",
          str(tmp_path / "e2" / "summary.png")], "also the --json"),
        (["train", "--init", str(good_npz), "--out", str(good_npz)], "would destroy"),
        # A scene inside a --scenes or --val-scenes folder is an input too.
        (["train", "--steps", "1", "--scenes", str(tmp_path / "twin"), "--out", str(tmp_path / "twin" / scene_file.name)], "would destroy"),
        (["train", "--steps", "1", "--scenes", str(scene_file), "--val-scenes", str(tmp_path / "twin"), "--out",
          str(tmp_path / "twin" / scene_file.name)], "would destroy"),
        (["search", "--maxeval", "2", "--scenes", str(tmp_path / "twin"), "--out", str(tmp_path / "twin" / scene_file.name)], "would destroy"),
        (["train", "--out", str(good)], "pattern files are written as .npz"),  # a .npy name, refused before learning
        (["import-frames", str(tmp_path), "--out", str(tmp_path / "p.png")], "name the output *.npz"),
        # Outputs under a file, or a folder where a file goes: refused before the work, not after it.
        (["search", "--maxeval", "2", "--scenes", str(scene_file), "--out", str(good_npz / "x.npz")], "is a file, not a folder"),
        (["train", "--steps", "1", "--scenes", str(scene_file), "--out", str(good_npz / "x.npz")], "is a file, not a folder"),
        (["invrender", "--scene", str(scene_file), "--json", str(good_npz / "x.json")], "is a file, not a folder"),
        (["invrender", "--scene", str(scene_file), "--out", str(good_npz)], "is a file; invrender writes a folder"),
        (["invrender", "--scene", str(scene_file), "--patterns", "olat", "--exposure", "5"], "OLAT captures are always auto-exposed"),
        (["invrender", "--scene", str(scene_file), "--rig", str(tmp_path / "gamma.toml"), "--json", str(tmp_path / "gamma.toml")],
         "is also the --rig file"),
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), "--exposure", "1e-300"], "exposure 1e-300 is too small"),
        (["bench", "sim", "--repeats", "1", "--json", str(tmp_path / "twin")], "exists and is not a regular file"),
        (["bench", "ps", "--sweep", "--json", str(tmp_path / "sweep.png")], "the sweep writes its chart under that name"),
        # A name that can only be a folder (its chart's name was formed from it: a traceback).
        (["bench", "ps", "--sweep", "--json", "."], "names a folder, not a file"),
        (["bench", "ps", "--sweep", "--json", str(tmp_path / "missing" / "..")], "names a folder, not a file"),
        (["bench", "sim", "--repeats", "1", "--json", "/"], "names a folder, not a file"),
        # Path() drops a trailing '/' or '/.': 'x/' was written as a file x.
        (["bench", "sim", "--repeats", "1", "--json", str(tmp_path / "newdir") + "/"], "names a folder, not a file"),
        (["patterns", "make", "--family", "olat", "--M", "2", "--out", str(tmp_path / "p.npz") + "/."], "names a folder, not a file"),
        # A JSON named .PNG is its own chart on a case-insensitive file system.
        (["bench", "ps", "--sweep", "--json", str(tmp_path / "sweep.PNG")], "the sweep writes its chart under that name"),
        (["bench", "ps", "--sweep", "--repeats", "3"], "--repeats applies to the timing benchmarks"),
        # An output path that is a folder fails before any work (train used to learn first).
        (["train", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "folder.npz")], "exists and is not a regular file"),
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), str(tmp_path / "twin" / scene_file.name), "--out", str(tmp_path / "e")],
         "share the file name"),
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), str(scene_file), "--out", str(tmp_path / "e")],
         f"scene file {scene_file} is given twice"),
        # Without --out too: the scene counted twice in the mean, with another noise draw.
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), str(scene_file.parent)], "is given twice"),
        (["train", "--M", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "t.npz")], "init 'auto' starts M = 1"),
        (["import-frames", str(good), "--out", str(tmp_path / "i.npz")], "not a folder of exported frames"),
        (["search", "--family", "tri_random", "--M", "50", "--maxeval", "2", "--scenes", str(scene_file), "--out", str(tmp_path / "s.npz")],
         "grows with the square of the parameter count"),
        (["train", "--rerender-weight", "1e38", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "r.npz")], "learning diverged at step 1"),
    ]
    # Output folders that are files, and the root of a synthesised set where a split is meant.
    cases += [
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), "--out", str(good)], "is a file; evaluate writes a folder"),
        (["scenes", "synth", "--out", str(good), "--size", "8x10"], "is a file; scenes synth writes a folder"),
        (["scenes", "synth", "--out", str(tmp_path / "indexed"), "--size", "8x10"], "index.json: it exists and is not a regular file"),
        (["evaluate", "--patterns", "olat", "--scenes", str(tmp_path / "set")], f"a synthesised scene set: pass {tmp_path / 'set' / 'test'}"),
    ]
    # A file output that is a folder output, or would have to hold one: refused before the work
    # (it failed at the end, after all of it, with "it exists and is not a regular file").
    learn = ["--steps", "1", "--scenes", str(scene_file)]
    cases += [
        (["train", *learn, "--out", str(tmp_path / "c1.npz"), "--logdir", str(tmp_path / "c1.npz")], "--out " + str(tmp_path / "c1.npz") + " is also the --logdir folder"),
        (["train", *learn, "--out", str(tmp_path / "c2.npz"), "--logdir", str(tmp_path / "c2.ckpt.pt")], "checkpoint " + str(tmp_path / "c2.ckpt.pt") + " is also the --logdir folder"),
        (["train", *learn, "--out", str(tmp_path / "c3.npz"), "--logdir", str(tmp_path / "c3.npz" / "logs")], "would have to be a folder to hold the --logdir folder"),
        (["search", "--family", "mono_gradient", "--M", "2", "--maxeval", "2", "--scenes", str(scene_file), "--out", str(tmp_path / "c4.npz"),
          "--logdir", str(tmp_path / "c4.trace.csv")], "is also the --logdir folder"),
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), "--json", str(tmp_path / "c5"), "--out", str(tmp_path / "c5")], "is also the --out folder"),
        (["evaluate", "--patterns", "olat", "--scenes", str(scene_file), "--json", str(tmp_path / "c6"), "--out", str(tmp_path / "c6" / "maps")],
         "would have to be a folder to hold the --out folder"),
        (["invrender", "--scene", str(scene_file), "--json", str(tmp_path / "c7"), "--out", str(tmp_path / "c7")], "is also the --out folder"),
    ]
    (tmp_path / "set" / "test").mkdir(parents=True)
    (tmp_path / "set" / "test" / scene_file.name).write_bytes(scene_file.read_bytes())
    # simulate into a folder where one of its outputs is a folder: refused before writing any.
    cases.append((["simulate", "--scene", str(scene_file), "--patterns", str(good), "--out", str(tmp_path / "sim")],
                  "contact_sheet.png: it exists and is not a regular file"))
    (tmp_path / "sim" / "contact_sheet.png").mkdir(parents=True)
    save_patterns(good_npz, np.load(good))
    (tmp_path / "eo").mkdir()
    (tmp_path / "eo" / f"{scene_file.stem}_normal.npy").write_bytes(good.read_bytes())
    (tmp_path / "folder.npz").mkdir()
    (tmp_path / "indexed" / "index.json").mkdir(parents=True)
    (tmp_path / "twin").mkdir()
    (tmp_path / "twin" / scene_file.name).write_bytes(scene_file.read_bytes())
    for argv, message in cases:
        capsys.readouterr()
        assert run(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()[-1]  # after any progress bar's line
        assert err.startswith("displex: error:") and message in err, (argv, err)
    assert not (tmp_path / "folder.ckpt.pt").exists()  # refused before learning wrote a checkpoint
    assert not any((tmp_path / name).exists() for name in ("c1.npz", "c1.ckpt.pt", "c2.ckpt.pt", "c3.npz", "c4.trace.csv", "c4.trace.partial.csv", "c5", "c6", "c7"))
    assert sorted(path.name for path in (tmp_path / "sim").iterdir()) == ["contact_sheet.png"]


def test_a_file_output_written_as_a_folder_is_refused_with_either_separator(monkeypatch):
    """On Windows both '\\' and '/' end a folder name ('out\\' would become a file 'out')."""
    import train.cli

    monkeypatch.setattr(train.cli.os, "altsep", "\\")
    for text in ("out\\", "out\\.", "out\\..", "out/"):
        with pytest.raises(argparse.ArgumentTypeError, match="names a folder"):
            train.cli._file_output(text)
    assert train.cli._file_output("out\\p.npz") == Path("out\\p.npz")


def interrupted_move(folder: Path, moves: int = 1):
    """An ``os.replace`` that raises KeyboardInterrupt at the move into ``folder`` after ``moves``
    of them (the staged files moving into place), renaming as usual otherwise."""
    done, original = [], os.replace

    def replace(source, target):
        if Path(target).parent == folder:
            if len(done) == moves:
                raise KeyboardInterrupt
            done.append(target)
        original(source, target)

    return replace


def test_evaluate_out_is_written_all_or_nothing(tmp_path, scene_file, capsys, monkeypatch):
    """A failure after the first scene (here the second scene's) leaves --out as the last finished
    run left it: no new maps of some scenes beside an older results.json, no staging folder."""
    import train.evaluate_command as evaluate_command

    out, fresh = tmp_path / "e", tmp_path / "fresh"
    # --json naming the results.json that --out receives anyway is the same document, not a clash.
    assert run(["evaluate", "--patterns", "olat", "--scenes", str(scene_file), "--out", str(out), "--json", str(out / "results.json")]) == 0
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    other = tmp_path / "b" / "other.npz"
    other.parent.mkdir()
    other.write_bytes(scene_file.read_bytes())
    original = evaluate_command.evaluate_scene

    def second_fails(pixels, patterns, settings, index):
        if index == 1:
            raise InputError("the second scene is bad")
        return original(pixels, patterns, settings, index)

    monkeypatch.setattr(evaluate_command, "evaluate_scene", second_fails)
    for folder in (out, fresh):
        capsys.readouterr()
        assert run(["evaluate", "--patterns", "olat", "--scenes", str(scene_file), str(other), "--out", str(folder)]) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == "displex: error: the second scene is bad"
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before
    assert not fresh.exists()
    # A finished run with other scenes replaces the earlier one's maps: none of a scene it did not
    # evaluate stays beside its results.json.
    monkeypatch.setattr(evaluate_command, "evaluate_scene", original)
    assert run(["evaluate", "--patterns", "olat", "--scenes", str(other), "--out", str(out)]) == 0
    only_other = sorted(["results.json", "summary.png"] + [f"other{ending}" for ending in evaluate_command.SCENE_OUTPUT_ENDINGS])
    assert sorted(path.name for path in out.iterdir()) == only_other
    # So does one after a run interrupted while its files moved in (results.json, removed first,
    # then lists nothing).
    assert run(["evaluate", "--patterns", "olat", "--scenes", str(scene_file), str(other), "--out", str(out)]) == 0
    with monkeypatch.context() as patch:
        patch.setattr("capture_sim.atomic.os.replace", interrupted_move(out))
        assert run(["evaluate", "--patterns", "olat", "--scenes", str(other), "--out", str(out)]) == 130
    assert not (out / "results.json").exists()
    assert run(["evaluate", "--patterns", "olat", "--scenes", str(other), "--out", str(out)]) == 0
    assert sorted(path.name for path in out.iterdir()) == only_other


def test_bad_rig_files_and_out_of_memory_give_one_line(tmp_path, capsys, monkeypatch):
    text = (load_rig.__globals__["RIG_DIR"] / "panel-55in-4x8.toml").read_text()
    for name, (old, new) in {
        "aspect": ("aspect = [16.0, 9.0]", "aspect = [0.0, 0.0]"),
        "offset": ("offset = [0.03, -0.25]", "offset = [0.03]"),
        "bits": ("bit_depth = 12", "bit_depth = inf"),
        "typo": ("bit_depth = 12", "bitdepth = 8"),  # a misspelt key must not fall back to the default
        "camera_typo": ("fx = 1141.8", "fx = 1141.8\nfocal = 3.0"),
        # TOML booleans are not numbers (false == 0 used to switch quantisation off).
        "bits_bool": ("bit_depth = 12", "bit_depth = false"),
        "gamma_bool": ("gamma = 2.2", "gamma = true"),
        # A radius below width / pi bends the panel beyond a half cylinder.
        "curvature": ("curvature_radius = 0.994", "curvature_radius = 0.3"),
        "curvature_negative": ("curvature_radius = 0.994", "curvature_radius = -1.8"),
        "curvature_nan": ("curvature_radius = 0.994", "curvature_radius = nan"),
        # Misspelt keys of every table, and falloff constants of the wrong kind, are errors too.
        "panel_typo": ("tilt_deg = 15.0", "tilt_deg = 15.0\ntilt = 5.0"),
        "noise_typo": ("read_std = 5e-4", "read_std = 5e-4\nread_noise = 1e-3"),
        "fitted_without_ab": ('kind = "inverse_square"', 'kind = "fitted"\na = 1.0'),
        "square_with_ab": ('kind = "inverse_square"', 'kind = "inverse_square"\nb = 14.7'),
        # Text and booleans where numbers belong (numpy converted them), and noise far beyond full
        # scale (NaN captures, or an overflow traceback).
        "fx_text": ("fx = 1141.8", 'fx = "1141.8"'),
        "shot_bool": ("shot = 1e-4", "shot = true"),
        "backlight_bool": ("backlight = 0.025", "backlight = true"),
        "name_number": ('name = "panel-55in-4x8"', "name = 5"),
        "shot_huge": ("shot = 1e-4", "shot = 1e308"),
        "read_huge": ("read_std = 5e-4", "read_std = 1e308"),
        "panel_pixels_huge": ("panel_pixels = [2160, 3840]", "panel_pixels = [1000000000, 3840]"),
        "tilt_bool": ("tilt_deg = 15.0", "tilt_deg = true"),
        "tilt_inf": ("tilt_deg = 15.0", "tilt_deg = inf"),
        "tilt_120": ("tilt_deg = 15.0", "tilt_deg = 120.0"),
        "distance_text": ("distance = 0.0", 'distance = "x"'),
        "curvature_table": ("curvature_radius = 0.994", "curvature_radius = {}"),
        "offset_bool": ("offset = [0.03, -0.25]", "offset = [true, -0.25]"),
    }.items():
        assert old in text, (name, old)
        (tmp_path / f"{name}.toml").write_text(text.replace(old, new))
        capsys.readouterr()
        assert run(["patterns", "make", "--family", "olat", "--M", "2", "--rig", str(tmp_path / f"{name}.toml"), "--out", str(tmp_path / "p.npz")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("displex: error: rig") and "\n" not in err, err
        if name.endswith("_bool"):
            assert "got False" in err or "got True" in err, err
        if name.endswith("_typo"):
            assert "unknown key(s)" in err and "known: " in err, err
        expected = {"tilt_inf": "tilt_deg must be a number of degrees in [-90, 90]", "tilt_120": "tilt_deg must be a number of degrees",
                    "distance_text": "panel distance must be a number of metres", "curvature_table": "curvature_radius must be a number of metres"}
        assert expected.get(name, "") in err, err

    def exhausted(*args, **kwargs):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] DefaultCPUAllocator: can't allocate memory: you tried to allocate 80000000000 bytes.")

    monkeypatch.setattr("patterns.families.make_patterns", exhausted)
    capsys.readouterr()
    assert run(["patterns", "make", "--family", "olat", "--M", "2", "--out", str(tmp_path / "p.npz")]) == 2
    assert capsys.readouterr().err.strip().startswith("displex: error: out of memory")


def test_ctrl_c_gives_one_line_with_the_resume_hint(tmp_path, scene_file, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("train.learn.train_patterns", interrupted)
    command = ["train", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "k.npz")]
    assert run(command) == 130
    err = capsys.readouterr().err.strip()
    assert err == "displex: interrupted; no checkpoint was written yet; rerun the same command to start again", err
    (tmp_path / "k.ckpt.pt").write_bytes(b"")  # as if a checkpoint had been written before the interrupt
    assert run(command) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith("displex: interrupted; rerun the same command") and err.endswith("k.ckpt.pt") and "\n" not in err, err
    # With --fresh the same command starts again: an earlier run's checkpoint is not resumed by it,
    # and one this run wrote is resumed without --fresh.
    assert run([*command, "--fresh"]) == 130
    assert capsys.readouterr().err.strip() == "displex: interrupted; no checkpoint was written yet; rerun the same command to start again"

    def writes_a_checkpoint(*args, **kwargs):
        (tmp_path / "k.ckpt.pt").write_bytes(b"new")
        raise KeyboardInterrupt

    monkeypatch.setattr("train.learn.train_patterns", writes_a_checkpoint)
    assert run([*command, "--fresh"]) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith("displex: interrupted; rerun it without --fresh to resume") and err.endswith("k.ckpt.pt"), err
    # A Ctrl-C before the command starts (while the parser is built) is the same one line.
    monkeypatch.setattr("train.cli.build_parser", interrupted)
    assert run(command) == 130
    assert capsys.readouterr().err.strip() == "displex: interrupted"


TERMINATED_TRAINING = """
import os, signal, sys, time
import train.learn
from train.cli import run

def terminated(config, out, **kwargs):
    staging = out.parent / ".staging.test"
    staging.mkdir()
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(30)
    finally:
        staging.rmdir()  # the clean-up a Ctrl-C runs, which SIGTERM used to skip
train.learn.train_patterns = terminated
sys.exit(run(sys.argv[1:]))
"""


def test_sigterm_is_an_interruption_with_its_clean_up_and_hint(tmp_path, scene_file):
    """``kill``, ``timeout`` and job schedulers send SIGTERM: the command cleans up as on a Ctrl-C
    and says how to resume, with the shell's status for SIGTERM (143). It used to die at once,
    leaving staging folders, temporary files and a search's partial trace short."""
    import subprocess

    command = ["train", "--steps", "1", "--scenes", str(scene_file), "--out", str(tmp_path / "k.npz")]
    done = subprocess.run([sys.executable, "-c", TERMINATED_TRAINING, *command], cwd=Path(__file__).parent.parent,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 143, done.stderr
    assert done.stderr.strip().splitlines()[-1] == "displex: terminated; no checkpoint was written yet; rerun the same command to start again"
    assert not (tmp_path / ".staging.test").exists()


def test_ctrl_c_in_search_points_to_the_partial_trace(tmp_path, scene_file, capsys, monkeypatch):
    from train.search import partial_trace_path

    out = tmp_path / "s.npz"

    def interrupted(config, path, **kwargs):
        if flushed:
            (tmp_path / "s.trace.partial.csv").write_text("index,mae\n")
        raise KeyboardInterrupt

    monkeypatch.setattr("train.search.run_search", interrupted)
    command = ["search", "--family", "tri_complementary", "--M", "2", "--maxeval", "20", "--scenes", str(scene_file), "--out", str(out)]
    for flushed, hint in ((False, "no evaluation was made yet"), (True, f"are in {tmp_path / 's.trace.partial.csv'}")):
        assert run(command) == 130
        err = capsys.readouterr().err.strip()
        assert err.startswith("displex: interrupted; ") and err.endswith(hint) and "\n" not in err, err
    # An interruption before the first evaluation does not pass off an earlier run's partial
    # trace as this run's; a newline in the output's name is escaped: the message stays one line.
    odd = tmp_path / "s\nt.npz"
    partial_trace_path(odd).write_text("index,mae\n")
    flushed = False
    assert run(command[:-1] + [str(odd)]) == 130
    err = capsys.readouterr().err.strip()
    assert "no evaluation was made yet; an earlier run's" in err and err.endswith("s\\nt.trace.partial.csv"), err
    # Interrupted before the search looked at the partial trace (while importing): an earlier run's too.
    from train.cli import _search_interrupted

    assert _search_interrupted(argparse.Namespace(out=odd)).startswith("no evaluation was made yet; an earlier run's")


def test_symbolic_link_loops_and_non_utf8_logdirs_give_one_line(tmp_path, scene_file, capsys, monkeypatch):
    from capture_sim.atomic import staged_files
    from train.learn import summary_writer

    (tmp_path / "loop.npz").symlink_to(tmp_path / "loop.npz")
    assert run(["patterns", "make", "--family", "olat", "--M", "2", "--out", str(tmp_path / "loop.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("displex: error:") and "\n" not in err, err
    with pytest.raises(InputError, match="--logdir .*valid UTF-8"):
        summary_writer(tmp_path / os.fsdecode(b"logs\xff"))
    assert run(["invrender", "--scene", str(scene_file), "--iterations", "2", "--out", str(tmp_path / os.fsdecode(b"inv\xff"))]) == 2
    assert capsys.readouterr().err.startswith("displex: error: --out ")
    # A staged output whose destination is a symbolic link replaces the link, whatever it points to.
    (tmp_path / "staged").mkdir()
    (tmp_path / "staged" / "a.txt").symlink_to("/dev/null")
    with staged_files(tmp_path / "staged") as staging:
        (staging / "a.txt").write_text("new")
    assert not (tmp_path / "staged" / "a.txt").is_symlink() and (tmp_path / "staged" / "a.txt").read_text() == "new"
    # Under a strict stdout, a path that is not valid UTF-8 is reported escaped, not after a crash.
    strict = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors="strict")
    monkeypatch.setattr(sys, "stdout", strict)
    assert run(["patterns", "make", "--family", "olat", "--M", "2", "--out", str(tmp_path / os.fsdecode(b"p\xff.npz"))]) == 0
    strict.flush()
    assert b"p\\udcff.npz" in strict.buffer.getvalue() and strict.errors == "strict"  # restored afterwards
    # A subfolder that is a broken link is refused before anything moves.
    (tmp_path / "staged" / "sub").symlink_to(tmp_path / "missing")
    with pytest.raises(InputError, match="broken symbolic link"):
        with staged_files(tmp_path / "staged", last=("a.txt",)) as staging:
            (staging / "sub").mkdir()
            (staging / "sub" / "b.txt").write_text("x")
            (staging / "a.txt").write_text("newer")
    assert (tmp_path / "staged" / "a.txt").read_text() == "new"
    # An output under a broken link says so, not 'File exists' (a file, a folder, a lock).
    for args in (["patterns", "make", "--family", "olat", "--M", "2", "--out", str(tmp_path / "staged" / "sub" / "p.npz")],
                 ["scenes", "synth", "--size", "8x9", "--out", str(tmp_path / "staged" / "sub" / "deeper")],
                 ["train", "--M", "2", "--steps", "1", "--out", str(tmp_path / "staged" / "sub" / "t.npz")],
                 ["train", "--M", "2", "--steps", "1", "--out", str(tmp_path / "t.npz"), "--logdir", str(tmp_path / "staged" / "sub" / "log")]):
        assert run(args) == 2
        err = capsys.readouterr().err.strip()
        assert err.endswith(f"{tmp_path / 'staged' / 'sub'} is a broken symbolic link (to {tmp_path / 'missing'})"), err


def test_patterns_make_records_a_seed_only_where_it_draws_the_values(tmp_path, capsys):
    def meta(name):
        return json.loads(np.load(tmp_path / name)["meta"].item())

    assert run(["patterns", "make", "--family", "tri_random", "--M", "2", "--seed", "5", "--out", str(tmp_path / "r5.npz")]) == 0
    assert run(["patterns", "make", "--family", "tri_random", "--M", "2", "--out", str(tmp_path / "r0.npz")]) == 0
    assert meta("r5.npz")["seed"] == 5 and meta("r0.npz")["seed"] == 0
    assert not np.array_equal(np.load(tmp_path / "r5.npz")["patterns"], np.load(tmp_path / "r0.npz")["patterns"])
    capsys.readouterr()
    assert run(["patterns", "make", "--family", "olat", "--M", "4", "--seed", "5", "--out", str(tmp_path / "o.npz")]) == 0
    assert "warning: --seed has no effect on family olat" in capsys.readouterr().err
    assert "seed" not in meta("o.npz") and meta("o.npz")["parameters"]["row_2"] == 8.0
    assert run(["patterns", "make", "--family", "olat", "--M", "4", "--out", str(tmp_path / "o0.npz")]) == 0
    assert "warning" not in capsys.readouterr().err and "seed" not in meta("o0.npz")


def test_patterns_make_and_export_round_trip(tmp_path):
    patterns = tmp_path / "p.npz"
    assert run(["patterns", "make", "--family", "tri_complementary", "--M", "2", "--out", str(patterns)]) == 0
    small_rig = tmp_path / "small.toml"
    text = (load_rig.__globals__["RIG_DIR"] / "dir-odyssey-ark.toml").read_text().replace("panel_pixels = [2160, 3840]", "panel_pixels = [90, 160]")
    small_rig.write_text(text)
    frames = tmp_path / "frames"
    assert run(["export", "--patterns", str(patterns), "--rig", str(small_rig), "--out", str(frames)]) == 0
    recovered = tmp_path / "back.npz"
    assert run(["import-frames", str(frames), "--out", str(recovered)]) == 0
    original, back = np.load(patterns)["patterns"], np.load(recovered)["patterns"]
    assert np.abs(original - back).max() <= 1 / 255


def test_evaluate_refuses_bad_outputs_before_reading_scenes(tmp_path, capsys, monkeypatch):
    """--json and --out's fixed files are checked before the scenes are read (the default scenes
    take seconds to synthesise); the scene maps' names need the scenes and are checked after."""
    import train.evaluate_command as evaluate_command

    def no_scenes(*args, **kwargs):
        raise AssertionError("scenes were read before the outputs were checked")

    monkeypatch.setattr(evaluate_command, "resolve_scenes", no_scenes)
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    patterns = tmp_path / "mono.npz"
    assert run(["patterns", "make", "--family", "mono_gradient", "--M", "4", "--out", str(patterns)]) == 0
    capsys.readouterr()
    for extra, message in (
        (["--json", str(blocker / "r.json")], "is a file, not a folder"),
        (["--json", str(patterns)], "is also the pattern file"),
        (["--out", str(tmp_path / "o"), "--json", str(tmp_path / "o" / "summary.png")], "summary.png"),
    ):
        assert run(["evaluate", "--patterns", str(patterns), *extra]) == 2
        error = capsys.readouterr().err.strip()
        assert message in error and len(error.splitlines()) == 1, error


def test_evaluate_json_matches_saved_normal_maps(tmp_path, scene_file):
    patterns = tmp_path / "mono.npz"
    assert run(["patterns", "make", "--family", "mono_gradient", "--M", "4", "--out", str(patterns)]) == 0
    out, report = tmp_path / "eval", tmp_path / "eval.json"
    assert run(["evaluate", "--scenes", str(scene_file), "--patterns", str(patterns), "--json", str(report), "--out", str(out)]) == 0
    document = json.loads(report.read_text())
    assert document["seed"] == 0 and document["exposure"] == "rig" and document["scene_files"] == [str(scene_file)]
    row = document["scenes"][0]
    assert {"name", "mae", "median", "under_5", "under_10", "under_20", "under_30", "invalid_fraction", "seconds"} <= set(row)
    assert {"poor_fit", "grazing", "ill_conditioned"} <= set(row["flagged"]) and all(0 <= share <= 1 for share in row["flagged"].values())
    with np.load(scene_file) as data:
        truth, mask = data["normal"].astype(np.float64), data["mask"]
    estimate = np.load(out / "blob_normal.npy").astype(np.float64)
    assert np.load(out / "blob_valid.npy").shape == mask.shape
    residual = np.load(out / "blob_residual.npy")
    assert residual.shape == mask.shape and residual.dtype == np.float32 and ((residual >= 0) & (residual <= 1)).all()
    cosine = np.clip((estimate[mask] * truth[mask]).sum(-1) / np.linalg.norm(estimate[mask], axis=-1) / np.linalg.norm(truth[mask], axis=-1), -1, 1)
    assert abs(np.degrees(np.arccos(cosine)).mean() - row["mae"]) < 0.01
    assert abs(document["mean_mae"] - row["mae"]) < 1e-9
    assert (out / "summary.png").is_file() and (out / "blob_normals.png").is_file()


@pytest.mark.parametrize(
    "body,message",
    [
        ("heuristics = ['checkerboard']\n", "unknown pattern family"),
        ("[[external]]\nname = 'gone'\npath = 'patterns/data/ddps/no_such_file.npy'\n", "not found"),
        ("[[external]]\npath = 'patterns/data/ddps/optimized_tri_random_2.npy'\n", "missing key(s) name"),
        ("pattern_counts = [2, 0]\n", "positive integers"),
        ("pattern_counts = [2]\n[[search]]\nfamily = 'tri_complementary'\nM = 4\n", "not in pattern_counts"),
        ("pattern_counts = [2]\nlearned_counts = [3]\n", "not in pattern_counts"),
        ("noise_scales = [1.0]\n[solver]\nrestart_condition = -1.0\n", "restart_condition"),
        ("train_scenes = 3\n", "list of scene files"),
        ("test_scenes = [1, 2]\n", "list of scene files"),
        ("[learned_seeds_at]\n4 = 7\n", "list of integer seeds"),
        ("learned_seeds = [4294967296]\n", "seed"),
        ("scene_size = [128]\n", "list of 2 values"),
        ("heuristics = []\nlearned_counts = []\ninclude_olat_woodham = false\n", "nothing to compare"),
        ("noise_scales = [1.0, nan]\n", "noise_scales value must be a number in [0, 1e+06]"),
        ("noise_scales = [1.0, 1e300]\n", "noise_scales value must be a number in [0, 1e+06]"),
        ("pattern_counts = [2, 2]\n", "lists a value twice"),
        ("[[external]]\nname = ''\npath = 'patterns/data/ddps/optimized_tri_random_2.npy'\n", "non-empty and distinct"),
        ("[solver]\nmin_distance = 1e30\n", "min_distance must lie in"),
        # Learned runs are the normal-only ones; seeds and counts once each; overrides where something is learned.
        ("[learned]\nrerender_weight = 0.5\n", "may not set rerender_weight"),
        ("[learned_seeds_at]\n4 = [0, 0]\n", "learned_seeds_at.4 lists a value twice"),
        ("rerender_counts = [4, 4]\n", "rerender_counts lists a value twice"),
        ("learned_counts = [2]\n[learned_seeds_at]\n4 = [0, 1]\n", "M = 4, where nothing is learned"),
        ("[learned_at]\n4 = 5\n", "learned_at.4 must be a table"),
        ("[learned]\ninit = 'nowhere.npz'\n", "learned init pattern file not found"),
    ],
)
def test_compare_refuses_bad_configs(tmp_path, capsys, body, message):
    config = tmp_path / "configs" / "compare" / "bad.toml"
    config.parent.mkdir(parents=True)
    config.write_text(body)
    assert run(["compare", "--config", str(config), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("displex: error:") and "\n" not in err and message in err, err
    assert not (tmp_path / "out").exists()


def test_search_command_writes_trace_and_tensorboard_log(tmp_path, scene_file, capsys):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out, logdir = tmp_path / "best.npz", tmp_path / "logs"
    argv = ["search", "--family", "tri_complementary", "--M", "2", "--algorithm", "LN_SBPLX", "--maxeval", "4", "--seed", "1",
            "--scenes", str(scene_file), "--logdir", str(logdir), "--out", str(out)]
    assert run(argv) == 0
    assert "->" in capsys.readouterr().out
    rows = (tmp_path / "best.trace.csv").read_text().splitlines()[1:]
    events = EventAccumulator(str(logdir))
    events.Reload()
    values = [event.value for event in events.Scalars("search/mae_deg")]
    bests = [event.value for event in events.Scalars("search/best_mae_deg")]
    assert len(values) == len(rows) == len(bests) >= 2
    assert np.allclose(values, [float(row.split(",")[-2]) for row in rows], rtol=1e-5)
    assert np.allclose(bests, np.minimum.accumulate(values), rtol=1e-6)
    assert run(argv[:-1] + [str(tmp_path / "other.npz"), "--maxeval", "0"]) == 2


def test_review_fixes_rig_values_stale_captures_and_logdir(tmp_path, scene_file, capsys, monkeypatch):
    """A rig whose camera.exposure_ms is not a number or whose working distance is not positive is
    refused; a second simulate with fewer patterns removes the first one's extra captures; an
    unusable --logdir is one error line; non-finite config values are written as strings."""
    import math

    from capture_sim.rig import RIG_DIR
    from train.config_io import config_to_dict
    from train.learn import TrainConfig

    text = (RIG_DIR / "dir-odyssey-ark.toml").read_text()
    for old, new, message in (("exposure_ms = 440.0", 'exposure_ms = "fast"', "exposure_ms"),
                              ("exposure_ms = 440.0", "exposure_ms = nan", "exposure_ms"),
                              ("working_distance = 0.5", "working_distance = 0.0", "working_distance")):
        assert old in text
        bad = tmp_path / "bad_rig.toml"
        bad.write_text(text.replace(old, new))
        with pytest.raises(InputError, match=message):
            load_rig(bad)
    rig = load_rig()
    many, _ = _pattern_file(tmp_path, "random", rig)
    few, _ = _pattern_file(tmp_path, "white", rig)
    out = tmp_path / "sim"
    for patterns in (many, few):
        assert run(["simulate", "--scene", str(scene_file), "--patterns", str(patterns), "--out", str(out), "--noise", "off"]) == 0
    assert sorted(p.name for p in out.glob("capture_*.png")) == ["capture_000.png"]
    # An interrupted rerun leaves the last run's files whole (they are staged, then moved in).
    finished = {path.name: path.read_bytes() for path in out.iterdir()}

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr("train.simulate_command.save_figure", interrupted)
        assert run(["simulate", "--scene", str(scene_file), "--patterns", str(many), "--out", str(out), "--noise", "off"]) == 130
    assert {path.name: path.read_bytes() for path in out.iterdir()} == finished
    # Interrupted while its files move in (meta.json, removed first, then lists nothing), a run
    # with fewer patterns leaves extra captures; the next finished run still removes them.
    assert run(["simulate", "--scene", str(scene_file), "--patterns", str(many), "--out", str(out), "--noise", "off"]) == 0
    with monkeypatch.context() as patch:
        patch.setattr("capture_sim.atomic.os.replace", interrupted_move(out))
        assert run(["simulate", "--scene", str(scene_file), "--patterns", str(few), "--out", str(out), "--noise", "off"]) == 130
    assert not (out / "meta.json").exists() and len(list(out.glob("capture_*.png"))) > 1
    assert run(["simulate", "--scene", str(scene_file), "--patterns", str(few), "--out", str(out), "--noise", "off"]) == 0
    assert sorted(p.name for p in out.glob("capture_*.png")) == ["capture_000.png"]
    # A folder of someone's own capture_NNN.png (no meta.json, no captures.npy) is refused, not overwritten or pruned.
    own = tmp_path / "own"
    own.mkdir()
    for index in (0, 1, 10):
        (own / f"capture_{index:03d}.png").write_bytes(b"mine")
    capsys.readouterr()
    assert run(["simulate", "--scene", str(scene_file), "--patterns", str(few), "--out", str(own), "--noise", "off"]) == 2
    assert "no meta.json of a simulate run" in capsys.readouterr().err
    assert sorted((path.name, path.read_bytes()) for path in own.iterdir()) == [(f"capture_{i:03d}.png", b"mine") for i in (0, 1, 10)]
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    capsys.readouterr()
    assert run(["train", "--scenes", str(scene_file), "--steps", "1", "--out", str(tmp_path / "t.npz"), "--logdir", str(blocker / "logs")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--logdir" in err and "Traceback" not in err
    assert config_to_dict(TrainConfig(angle_cap_deg=math.inf))["angle_cap_deg"] == "inf"


def test_errors_about_flag_values_name_the_flag(tmp_path, capsys):
    for command, flag in ((["train", "--steps", "-1"], "--steps"), (["train", "--M", "0"], "--M"), (["search", "--maxeval", "0"], "--maxeval")):
        capsys.readouterr()
        assert run([*command, "--out", str(tmp_path / "p.npz")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("displex: error:") and f"(set by {flag})" in err and err.count("\n") == 1, err


def test_version_names_the_installed_package(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as stop:
        run(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"displex {version('displex')}"


def test_documented_flags_reach_their_commands(tmp_path, scene_file, capsys):
    """Flags of the README's command table change what the commands write."""
    from capture_sim.png import read_png
    from train.config_io import config_to_dict
    from train.learn import TrainConfig

    # patterns list names every family; --preset ddps gives the published initial patterns.
    # The rig's grid decides the supported M: grouped_olat reaches M = 20 on 9 x 16, not on 4 x 8.
    assert run(["patterns", "list", "--M", "20", "--rig", "panel-55in-4x8"]) == 0
    assert "grouped_olat         (not defined for M=20 on 4 x 8)" in capsys.readouterr().out
    # On a single row, top/bottom halves would be flat (every cell at the half level): listed as
    # such; on two rows, five splits of a 2 x 8 grid repeat one.
    one_row = tmp_path / "one_row.toml"
    from capture_sim.rig import rig_source

    one_row.write_text(rig_source("panel-55in-4x8").read_text().replace("rows = 4", "rows = 1"))
    assert run(["patterns", "list", "--M", "4", "--rig", str(one_row)]) == 0
    assert "mono_complementary   (flat patterns: a single row or column across a direction for M=4 on 1 x 8)" in capsys.readouterr().out
    one_row.write_text(rig_source("panel-55in-4x8").read_text().replace("rows = 4", "rows = 2"))
    assert run(["patterns", "list", "--M", "9", "--rig", str(one_row)]) == 0
    assert "mono_complementary   (identical patterns for M=9 on 2 x 8)" in capsys.readouterr().out
    assert run(["patterns", "list", "--M", "4"]) == 0
    listing = capsys.readouterr().out
    from patterns.families import FAMILIES

    assert all(name in listing for name in FAMILIES)
    published = tmp_path / "ddps.npz"
    assert run(["patterns", "make", "--family", "mono_gradient", "--M", "4", "--preset", "ddps", "--out", str(published)]) == 0
    assert np.abs(np.load(published)["patterns"] - np.load("patterns/data/ddps/initial_mono_gradient.npy")).max() < 1e-6
    # export: --olat adds the OLAT sequence, --bit-depth 16 writes 16-bit frames.
    frames = tmp_path / "frames"
    assert run(["export", "--patterns", str(published), "--out", str(frames), "--olat", "--bit-depth", "16"]) == 0
    manifest = json.loads((frames / "manifest.json").read_text())
    assert manifest["bit_depth"] == 16 and read_png(frames / "pattern_000.png").dtype == np.uint16
    assert len(list(frames.glob("olat_*.png"))) == load_rig().num_lights
    # simulate: the noise follows --seed; the PNGs hold the captures at 16 bits.
    captures = {}
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        assert run(["simulate", "--scene", str(scene_file), "--patterns", str(published), "--out", str(tmp_path / name), "--seed", str(seed)]) == 0
        captures[name] = np.load(tmp_path / name / "captures.npy")
    assert np.array_equal(captures["a"], captures["b"]) and not np.array_equal(captures["a"], captures["c"])
    assert np.array_equal(read_png(tmp_path / "a" / "capture_002.png"), np.round(captures["a"][2] * 65535).astype(np.uint16))
    # evaluate --method woodham runs Woodham (it differs from ps on the same captures).
    maes = {}
    for method in ("ps", "woodham"):
        assert run(["evaluate", "--patterns", str(published), "--scenes", str(scene_file), "--method", method, "--json", str(tmp_path / f"{method}.json")]) == 0
        document = json.loads((tmp_path / f"{method}.json").read_text())
        assert document["method"] == method
        maes[method] = document["mean_mae"]
    assert maes["ps"] != maes["woodham"]
    # train records its resolved config beside the patterns.
    learned = tmp_path / "learned.npz"
    assert run(["train", "--steps", "1", "--M", "2", "--scenes", str(scene_file), "--out", str(learned)]) == 0
    record = json.loads((tmp_path / "learned.config.json").read_text())
    assert record == json.loads(json.dumps(config_to_dict(TrainConfig(num_patterns=2, steps=1, scenes=(str(scene_file),)))))


def test_threads_option_sets_torch_threads_for_the_command_only(monkeypatch, capsys):
    import torch

    import train.cli as cli

    seen = []
    monkeypatch.setattr(cli, "_patterns_list", lambda args: seen.append(torch.get_num_threads()))
    before = torch.get_num_threads()
    assert run(["--threads", "1", "patterns", "list"]) == 0 and seen == [1]
    assert torch.get_num_threads() == before
    assert run(["--threads", "-1", "patterns", "list"]) == 2
    assert "thread count must be 0" in capsys.readouterr().err


def test_unknown_config_keys_are_not_blamed_on_flags(tmp_path, scene_file, capsys):
    """A training config given to search: its keys are unknown there, whatever --scenes says."""
    assert run(["search", "--config", "configs/train/default.toml", "--scenes", str(scene_file), "--out", str(tmp_path / "s.npz")]) == 2
    err = capsys.readouterr().err
    assert "unknown key(s)" in err and "set by" not in err, err


def test_invrender_threads_is_the_global_threads_option(tmp_path, scene_file, monkeypatch, capsys):
    """`invrender --threads T` (kept for older command lines) and `displex --threads T invrender`: one
    option, one range check, one error line, and the config records the count."""
    import torch

    import train.invrender_command as command

    seen = []

    def fake_run(config):
        seen.append((config.threads, torch.get_num_threads()))
        return {}

    monkeypatch.setattr(command, "run_invrender", fake_run)
    before = torch.get_num_threads()
    base = ["invrender", "--scene", str(scene_file)]
    for argv in (["--threads", "1", *base], [*base, "--threads", "1"], ["--threads", "2", *base, "--threads", "1"]):
        assert run(argv) == 0, argv
        assert seen.pop() == (1, 1), argv
        assert torch.get_num_threads() == before
    assert run(base) == 0 and seen.pop() == (0, before)
    for argv in ([*base, "--threads", "-1"], ["--threads", "-1", *base], [*base, "--threads", str(MAX_THREADS + 1)]):
        capsys.readouterr()
        assert run(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.startswith("displex: error:") and "thread count must be 0 (torch's default) or 1..1024" in err and "\n" not in err, err
    assert not seen


def test_scenes_synth_cast_shadows_traces_shadows_that_darken_scenes_and_captures(tmp_path, capsys, monkeypatch):
    """``--cast-shadows`` (only ``scenes synth`` has it) reaches the shadow tracer of
    ``capture_sim.synth``: without it no shadow ray is traced and the OLAT stacks hold attached
    shadows only; with it the concave scenes get darker (never brighter), convex ones are unchanged,
    the geometry is the same, the flag is recorded, and simulated captures are darker too."""
    import capture_sim.synth as synth
    from capture_sim.scene import load_scene
    from capture_sim.shapes import make_shape

    traced = []
    trace = synth.shadow_visibility
    monkeypatch.setattr(synth, "shadow_visibility", lambda *args: traced.append(args[0].name) or trace(*args))
    indexes, traced_shapes = {}, {}
    for name, flags in (("lit", []), ("shadowed", ["--cast-shadows"])):
        traced.clear()
        assert run(["scenes", "synth", "--out", str(tmp_path / name), "--size", "8x10", *flags]) == 0
        indexes[name] = json.loads((tmp_path / name / "index.json").read_text())
        traced_shapes[name] = set(traced)
    entries = [entry for split in indexes["lit"]["splits"].values() for entry in split]
    assert traced_shapes == {"lit": set(), "shadowed": {entry["shape"] for entry in entries}}
    assert (indexes["lit"]["cast_shadows"], indexes["shadowed"]["cast_shadows"]) == (False, True)

    darkened = {}
    for entry in entries:
        lit, shadowed = (load_scene(tmp_path / name / entry["file"]) for name in ("lit", "shadowed"))
        assert (lit.meta["cast_shadows"], shadowed.meta["cast_shadows"]) == (False, True)
        for key in ("mask", "normal", "depth"):
            assert np.array_equal(getattr(lit, key), getattr(shadowed, key)), (entry["name"], key)
        for key in ("olat", "diffuse", "specular"):
            assert bool((getattr(shadowed, key) <= getattr(lit, key)).all()), (entry["name"], key)
        if make_shape(entry["shape"]).convex:
            assert np.array_equal(lit.olat, shadowed.olat), entry["name"]
        darkened[entry["shape"]] = int((shadowed.olat < 0.5 * lit.olat)[..., 0].sum())
    assert darkened["torus"] > 50 and darkened["bowl"] > 50, darkened

    # The shadows reach the captures: same patterns, fixed exposure, no noise, nothing saturated.
    bowl = next(entry["file"] for entry in entries if entry["shape"] == "bowl")
    pattern_path, _ = _pattern_file(tmp_path, "random", load_rig())
    captures = {}
    for name in ("lit", "shadowed"):
        out = tmp_path / f"captures-{name}"
        assert run(["simulate", "--scene", str(tmp_path / name / bowl), "--patterns", str(pattern_path), "--out", str(out),
                    "--noise", "off", "--exposure", "0.01"]) == 0
        captures[name] = np.load(out / "captures.npy")
    assert captures["lit"].max() < 1.0
    assert bool((captures["shadowed"] <= captures["lit"]).all())
    assert int((captures["shadowed"] < captures["lit"]).sum()) > 50  # of 3 patterns x 21 masked pixels x 3 channels

    # The flag is a switch of scenes synth alone: a value or another command is refused in one line.
    for argv, message in (
        (["scenes", "synth", "--out", str(tmp_path / "a"), "--cast-shadows=yes"], "argument --cast-shadows: ignored explicit argument 'yes'"),
        (["simulate", "--scene", str(tmp_path / "lit" / bowl), "--patterns", str(pattern_path), "--out", str(tmp_path / "b"), "--cast-shadows"],
         "unrecognized arguments: --cast-shadows"),
        (["evaluate", "--patterns", "olat", "--scenes", str(tmp_path / "lit" / "test"), "--cast-shadows"], "unrecognized arguments: --cast-shadows"),
    ):
        capsys.readouterr()
        assert run(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("displex: error:") and message in err and err.count("\n") == 1, (argv, err)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_inputs_made_for_another_rig_need_rig(tmp_path, scene_file, capsys):
    """Without --rig, a pattern or scene file that records another rig is refused (the default rig's
    display would silently be used for it); --rig, or a config's `rig`, chooses."""
    from capture_sim.rig import RIG_DIR
    from train.rig_choice import recorded_rig

    other = tmp_path / "twin.toml"  # the reference display under another name: same grid and lights
    other.write_text((RIG_DIR / "dir-odyssey-ark.toml").read_text().replace('name = "dir-odyssey-ark"', 'name = "twin"'))
    assert load_rig(other).name == "twin"
    patterns = tmp_path / "p.npz"
    assert run(["patterns", "make", "--family", "mono_gradient", "--M", "4", "--rig", str(other), "--out", str(patterns)]) == 0
    scene = tmp_path / "twin_scene.npz"
    save_scene(synthesize_scene("sphere", "lambertian", load_rig(other), height=12, width=14, seed=0), scene)
    assert recorded_rig(patterns, "pattern") == "twin" and recorded_rig(scene_file, "scene") == "dir-odyssey-ark"
    assert recorded_rig(_pattern_file(tmp_path, "white", load_rig())[0], "pattern") is None  # a plain .npy records none
    capsys.readouterr()
    refused = [["export", "--patterns", str(patterns), "--out", str(tmp_path / "frames")],
               ["evaluate", "--scenes", str(tmp_path), "--patterns", "olat", "--noise", "off"],
               ["simulate", "--scene", str(scene_file), "--patterns", str(patterns), "--out", str(tmp_path / "sim")],
               ["invrender", "--scene", str(scene), "--iterations", "1"],
               ["train", "--M", "2", "--steps", "1", "--scenes", str(scene), "--out", str(tmp_path / "t.npz")],
               ["search", "--family", "tri_complementary", "--M", "2", "--maxeval", "1", "--scenes", str(scene), "--out", str(tmp_path / "s.npz")]]
    for args in refused:
        assert run(args) == 2, args
        err = capsys.readouterr().err.strip()
        assert "was made for rig 'twin', but the command uses the default rig dir-odyssey-ark (" in err and "\n" not in err, err
    assert not (tmp_path / "frames").exists() and not (tmp_path / "t.npz").exists()
    assert run(["export", "--patterns", str(patterns), "--rig", str(other), "--out", str(tmp_path / "frames")]) == 0
    assert json.loads((tmp_path / "frames" / "manifest.json").read_text())["rig"] == "twin"
    config = tmp_path / "train.toml"
    config.write_text(f'rig = "{other}"\nval_every = 0\npixels_per_scene = 64\n')
    assert run(["train", "--config", str(config), "--M", "2", "--steps", "1", "--scenes", str(scene), "--out", str(tmp_path / "t.npz")]) == 0
    assert run(["train", "--rig", str(other), "--M", "2", "--steps", "1", "--scenes", str(scene), "--out", str(tmp_path / "t2.npz")]) == 0
    # A chosen rig other than the inputs' is used, with one warning line per recorded rig.
    capsys.readouterr()
    assert run(["export", "--patterns", str(patterns), "--rig", "dir-odyssey-ark", "--out", str(tmp_path / "frames3")]) == 0
    err = capsys.readouterr().err.strip()
    assert err == "displex: warning: pattern file p.npz was made for rig 'twin'; shown on the display of rig 'dir-odyssey-ark', as chosen", err
    # ... and none for a file on another grid, which the command refuses.
    assert run(["export", "--patterns", str(patterns), "--rig", "panel-32in-5x10", "--out", str(tmp_path / "frames4")]) == 2
    assert "warning" not in capsys.readouterr().err
    # compare: scenes made for another rig need the config's `rig`.
    from train.compare import run_compare
    from train.compare_config import compare_config_from_dict

    config = compare_config_from_dict({"pattern_counts": [2], "noise_scales": [1.0], "heuristics": ["tri_complementary"], "learned_counts": [],
                                       "include_olat_woodham": False, "train_scenes": [str(scene)], "test_scenes": [str(scene)]})
    with pytest.raises(InputError, match=r"twin_scene.npz was made for rig 'twin', but the command uses the default rig .*set `rig` in the config"):
        run_compare(config, tmp_path / "cmp", progress=False)
    # A grid mismatch names the rig and says what to do.
    assert run(["export", "--patterns", str(patterns), "--rig", "panel-32in-5x10", "--out", str(tmp_path / "frames2")]) == 2
    assert "rig panel-32in-5x10's display grid is 5 x 10" in capsys.readouterr().err
    assert run(["evaluate", "--patterns", str(patterns), "--rig", "panel-32in-5x10", "--scenes", str(scene)]) == 2
    assert f"patterns of {patterns} have shape" in capsys.readouterr().err  # the file is named


def test_own_scene_files_from_the_user_scenario(tmp_path, scene_file, capsys, monkeypatch):
    """From a user bringing their own scene files: a misspelt optional array is warned, not silently
    dropped; NaN in the background of the ground truth is accepted (as the DIR loader does) and
    inside the mask counted; a depth at or below 1 mm is refused on loading; every error names the
    file; evaluate refuses a scene without normals before solving any; the all-invalid warning
    names the flags raised."""
    with np.load(scene_file) as data:
        arrays = dict(data)
    meta = json.loads(str(arrays["meta"]))
    typo = {**{k: v for k, v in arrays.items() if k != "depth"}, "Depth": arrays["depth"]}
    np.savez(tmp_path / "typo.npz", **typo)
    with pytest.warns(DisplexWarning, match="unknown arrays 'Depth' are ignored"):
        load_scene(tmp_path / "typo.npz")
    background = ~arrays["mask"]
    normal, depth = arrays["normal"].copy(), arrays["depth"].copy()
    normal[background], depth[background] = np.nan, np.nan
    np.savez(tmp_path / "nan_background.npz", **{**arrays, "normal": normal, "depth": depth})
    loaded = load_scene(tmp_path / "nan_background.npz")
    assert np.isfinite(loaded.normal).all() and np.isfinite(loaded.depth).all()
    assert np.array_equal(loaded.normal[arrays["mask"]], arrays["normal"][arrays["mask"]])
    inside = normal.copy()
    inside[np.argwhere(arrays["mask"])[0][0], np.argwhere(arrays["mask"])[0][1]] = np.nan
    np.savez(tmp_path / "nan_inside.npz", **{**arrays, "normal": inside})
    np.savez(tmp_path / "tiny_depth.npz", **{**arrays, "depth": np.full_like(arrays["depth"], 1e-9)})
    np.savez(tmp_path / "no_normals.npz", **{k: v for k, v in arrays.items() if k != "normal"})
    black = tmp_path / "black.npy"
    np.save(black, np.zeros((4, *arrays["light_positions"].shape[:2], 3), dtype=np.float32))
    evaluate = ["evaluate", "--patterns", "olat", "--method", "woodham", "--scenes"]
    cases = [
        ("nan_inside.npz", f"scene {meta['name']} ({tmp_path / 'nan_inside.npz'}): normal has NaN or infinite values at 1 pixels inside the mask"),
        ("tiny_depth.npz", "depth must exceed 1 mm inside the mask, got 1e-09 m (depth is in metres"),
    ]
    for name, message in cases:
        capsys.readouterr()
        assert run(evaluate + [str(tmp_path / name)]) == 2
        assert message in capsys.readouterr().err
    solved = []
    monkeypatch.setattr("train.evaluate_command.evaluate_scene", lambda *args: solved.append(args))
    assert run(evaluate + [str(scene_file), str(tmp_path / "no_normals.npz")]) == 2
    assert f"({tmp_path / 'no_normals.npz'}) has no ground-truth normals" in capsys.readouterr().err and not solved
    monkeypatch.undo()
    assert run(["evaluate", "--patterns", str(black), "--scenes", str(scene_file)]) == 0
    # Black patterns still show the backlight, which auto exposure lifts: four identical captures.
    assert "flagged invalid (ill_conditioned (too few or too similar captures) on 100% of the pixels)" in capsys.readouterr().err


def test_every_option_of_every_command_has_help_text():
    """`demo --out`, `export --patterns` / `--bit-depth` and `evaluate --method` had none: their
    defaults were in the README only."""
    import argparse

    from train.cli import build_parser

    missing = []

    def walk(parser, name):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for command, sub in action.choices.items():
                    walk(sub, f"{name} {command}")
            elif not action.help and "-h" not in action.option_strings:
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}")

    walk(build_parser(), "displex")
    assert missing == []
