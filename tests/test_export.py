import hashlib
import json

import matplotlib.image as mpimg
import numpy as np
import pytest

from capture_sim.errors import InputError
from capture_sim.png import read_png, write_png
from capture_sim.rig import available_rigs, load_rig
from patterns.export import columns_mirrored, export_frames, frame_digits, import_frames, render_frame, superpixel_boundaries
from patterns.families import make_patterns


@pytest.fixture
def small_rig():
    """The reference rig with a 90 x 160 pixel panel: 10 x 10 pixel superpixels, fast to export."""
    return load_rig("dir-odyssey-ark").replace(panel_pixels=(90, 160))


def _patterns(rig, num_patterns=3, seed=0):
    return np.random.default_rng(seed).uniform(0, 1, (num_patterns, rig.rows, rig.cols, 3)).astype(np.float32)


def test_boundaries_split_pixels_evenly():
    np.testing.assert_array_equal(superpixel_boundaries(9, 2160), np.arange(10) * 240)
    bounds = superpixel_boundaries(16, 37)
    sizes = np.diff(bounds)
    assert bounds[0] == 0 and bounds[-1] == 37
    assert sizes.max() - sizes.min() <= 1
    np.testing.assert_array_equal(bounds, [int(np.floor(i * 37 / 16 + 0.5)) for i in range(17)])
    with pytest.raises(InputError):
        superpixel_boundaries(16, 15)


def test_every_preset_mirrors_columns():
    for name in available_rigs():
        assert columns_mirrored(load_rig(name))
    rig = load_rig()
    flipped = rig.replace(light_positions=rig.light_positions[:, ::-1].copy())
    assert not columns_mirrored(flipped)


def test_frame_matches_plain_pixel_loop():
    rows, cols, height, width = 3, 5, 8, 13  # not multiples: uneven blocks
    pattern = np.random.default_rng(2).uniform(0, 1, (rows, cols, 3))
    frame = render_frame(pattern, (height, width), bit_depth=8, mirrored=True)
    assert frame.shape == (height, width, 3) and frame.dtype == np.uint8
    for y in range(height):
        for x in range(width):
            row = min(i for i in range(rows) if y < np.floor((i + 1) * height / rows + 0.5))
            block = min(j for j in range(cols) if x < np.floor((j + 1) * width / cols + 0.5))
            expected = np.round(pattern[row, cols - 1 - block] * 255)
            np.testing.assert_array_equal(frame[y, x], expected)


def test_export_writes_frames_manifest_and_contact_sheet(tmp_path, small_rig):
    patterns = _patterns(small_rig)
    manifest = export_frames(patterns, small_rig, tmp_path / "out", rig_name="lab rig")
    out = tmp_path / "out"
    on_disk = json.loads((out / "manifest.json").read_text())
    assert on_disk == manifest
    assert manifest["rig"] == "lab rig"
    assert (manifest["rows"], manifest["cols"], manifest["num_patterns"]) == (9, 16, 3)
    assert manifest["bit_depth"] == 8 and manifest["exposure"] == "auto" and manifest["gamma"] == 2.2
    assert manifest["capture_order"] == ["pattern_000.png", "pattern_001.png", "pattern_002.png"]
    np.testing.assert_array_equal(np.asarray(manifest["patterns"], dtype=np.float32), patterns)
    for frame in manifest["frames"]:
        data = (out / frame["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == frame["sha256"]
        image = read_png(out / frame["file"])
        assert image.shape == (90, 160, 3) and image.dtype == np.uint8
    first = read_png(out / "pattern_000.png")
    # Superpixel (0, 0) sits at the frame's top-right block because columns are mirrored.
    np.testing.assert_array_equal(first[:10, -10:], np.broadcast_to(np.round(patterns[0, 0, 0] * 255), (10, 10, 3)))
    sheet = mpimg.imread(out / "contact_sheet.png")
    assert sheet.ndim == 3 and sheet.shape[0] > 100


def test_fixed_exposure_is_recorded(tmp_path, small_rig):
    manifest = export_frames(_patterns(small_rig, 1), small_rig.replace(exposure=0.25), tmp_path)
    assert manifest["exposure"] == 0.25


def test_olat_sequence(tmp_path, small_rig):
    manifest = export_frames(_patterns(small_rig, 1), small_rig, tmp_path, include_olat=True)
    names = manifest["capture_order"]
    assert names[:3] == ["pattern_000.png", "black.png", "white.png"]
    assert names[3:] == [f"olat_{k:03d}.png" for k in range(small_rig.num_lights)]
    assert read_png(tmp_path / "black.png").max() == 0
    assert read_png(tmp_path / "white.png").min() == 255
    olat = next(f for f in manifest["frames"] if f["file"] == "olat_017.png")
    assert (olat["light"], olat["row"], olat["col"]) == (17, 1, 1)
    image = read_png(tmp_path / "olat_017.png")
    lit = np.argwhere(image[..., 0] == 255)
    # Row 1 -> pixels 10..19; pattern column 1 -> frame block 14 -> pixels 140..149.
    assert lit.min(axis=0).tolist() == [10, 140] and lit.max(axis=0).tolist() == [19, 149]
    assert len(lit) == 100


@pytest.mark.parametrize("bit_depth, step", [(8, 1 / 255), (16, 1 / 65535)])
def test_round_trip_within_one_step(tmp_path, small_rig, bit_depth, step):
    patterns = _patterns(small_rig, 4, seed=bit_depth)
    export_frames(patterns, small_rig, tmp_path, bit_depth=bit_depth)
    recovered, meta = import_frames(tmp_path, rig=small_rig)
    assert recovered.shape == patterns.shape and recovered.dtype == np.float32
    assert np.abs(recovered - patterns).max() <= 0.5 * step + 1e-6
    assert meta["bit_depth"] == bit_depth
    if bit_depth == 16:
        assert read_png(tmp_path / "pattern_000.png").dtype == np.uint16


def test_round_trip_on_uneven_panel(tmp_path):
    rig = load_rig("panel-32in-5x10").replace(panel_pixels=(23, 47))
    patterns = make_patterns("tri_gradient", 3, rig.rows, rig.cols).numpy()
    export_frames(patterns, rig, tmp_path)
    recovered, _ = import_frames(tmp_path)
    assert np.abs(recovered - patterns).max() <= 0.5 / 255 + 1e-6


def test_full_resolution_frame(tmp_path):
    rig = load_rig()
    patterns = make_patterns("olat", 1, preset="ddps")  # lit superpixel (0, 15)
    export_frames(patterns, rig, tmp_path)
    frame = read_png(tmp_path / "pattern_000.png")
    assert frame.shape == (2160, 3840, 3) and frame.dtype == np.uint8
    on_level, off_level = (int(np.round(float(np.float32(v)) * 255)) for v in (0.9, 0.1))  # 229, 26
    lit = np.argwhere(frame[..., 0] == on_level)
    # Pattern column 15 is the frame's leftmost 240 x 240 block.
    assert lit.min(axis=0).tolist() == [0, 0] and lit.max(axis=0).tolist() == [239, 239]
    assert len(lit) == 240 * 240
    assert np.all(frame[frame[..., 0] != on_level] == off_level)


def test_export_refuses_bad_patterns(tmp_path, small_rig):
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        export_frames(np.full((1, 9, 16, 3), 1.2, np.float32), small_rig, tmp_path)
    with pytest.raises(InputError, match="9 x 16"):
        export_frames(np.zeros((1, 4, 8, 3), np.float32), small_rig, tmp_path)
    with pytest.raises(InputError, match="bit depth"):
        export_frames(_patterns(small_rig, 1), small_rig, tmp_path, bit_depth=12)
    with pytest.raises(InputError, match="split"):
        export_frames(_patterns(small_rig, 1), small_rig.replace(panel_pixels=(8, 160)), tmp_path)
    assert not (tmp_path / "manifest.json").exists()


def test_import_refuses_tampered_or_incomplete_folders(tmp_path, small_rig):
    with pytest.raises(InputError, match="not a folder of exported frames"):
        import_frames(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no manifest.json"):
        import_frames(tmp_path / "empty")
    export_frames(_patterns(small_rig, 2), small_rig, tmp_path)
    other = load_rig("panel-55in-4x8")
    with pytest.raises(InputError, match="4 x 8"):
        import_frames(tmp_path, rig=other)

    frame = read_png(tmp_path / "pattern_001.png")
    frame[0, 0] = 0 if frame[0, 0, 0] else 255
    write_png(tmp_path / "pattern_001.png", frame)
    with pytest.raises(InputError, match="SHA-256"):
        import_frames(tmp_path)

    (tmp_path / "pattern_001.png").unlink()
    with pytest.raises(InputError, match="missing"):
        import_frames(tmp_path)

    export_frames(_patterns(small_rig, 2), small_rig, tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["patterns"][0][0][0] = [0.0, 0.0, 0.0] if manifest["patterns"][0][0][0][0] > 0.5 else [1.0, 1.0, 1.0]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="do not show"):
        import_frames(tmp_path)
    manifest["patterns"][0][0][0] = [float("nan")] * 3  # NaN compares false with every tolerance
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="not a finite 2 x 9 x 16 x 3 array"):
        import_frames(tmp_path)
    uneven = json.loads(json.dumps(manifest))
    uneven["patterns"][0].pop()  # lists of uneven lengths: numpy raises a bare ValueError
    (tmp_path / "manifest.json").write_text(json.dumps(uneven))
    with pytest.raises(InputError, match="not a finite 2 x 9 x 16 x 3 array"):
        import_frames(tmp_path)
    manifest["patterns"][0][0][0] = ["1", "1", "1"]  # numpy would read text as numbers
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="not a finite 2 x 9 x 16 x 3 array"):
        import_frames(tmp_path)
    # A forged grid is refused before anything that size is built (it used to hang or crash).
    for rows, panel in ((10**9, [10**9, 160]), (10**30, [10**30, 160]), (91, [90, 160])):
        forged = {**manifest, "rows": rows, "panel_pixels": panel}
        forged.pop("row_boundaries", None)
        (tmp_path / "manifest.json").write_text(json.dumps(forged))
        with pytest.raises(InputError, match="panel_pixels|more superpixels"):
            import_frames(tmp_path)
    forged = json.loads(json.dumps(manifest))
    next(frame for frame in forged["frames"] if frame.get("kind") == "pattern")["index"] = False
    (tmp_path / "manifest.json").write_text(json.dumps(forged))
    with pytest.raises(InputError, match="no whole-number index"):
        import_frames(tmp_path)
    # Fields that restate one another must agree.
    for key, change, message in (("capture_order", lambda order: order[::-1], "capture_order"),
                                 ("row_boundaries", lambda bounds: [0] * len(bounds), "row_boundaries"),
                                 ("frames", lambda frames: frames + frames[:1], "twice")):
        edited = dict(manifest, **{key: change(manifest[key])})
        (tmp_path / "manifest.json").write_text(json.dumps(edited))
        with pytest.raises(InputError, match=message):
            import_frames(tmp_path)

    del manifest["frames"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="missing frames"):
        import_frames(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(InputError, match="not a readable manifest"):
        import_frames(tmp_path)
    (tmp_path / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)  # nested past Python's recursion limit
    with pytest.raises(InputError, match="not a readable manifest"):
        import_frames(tmp_path)


def test_import_refuses_a_manifest_whose_play_order_or_numbering_was_edited(tmp_path, small_rig):
    """Captures are taken in play order: a manifest whose pattern indices, kinds or OLAT numbering
    disagree with that order would pair captures with the wrong lighting."""
    values = _patterns(small_rig, 2)
    manifest = export_frames(values, small_rig, tmp_path, include_olat=True)
    assert np.abs(import_frames(tmp_path)[0] - values).max() <= 0.5 / 255 + 1e-6

    def edited(change):
        copy = json.loads(json.dumps(manifest))
        change(copy)
        copy["capture_order"] = [frame["file"] for frame in copy["frames"]]
        (tmp_path / "manifest.json").write_text(json.dumps(copy))
        return copy

    def swap_indices(copy):  # the listed values follow, so only the play order tells
        first, second = copy["frames"][0], copy["frames"][1]
        first["index"], second["index"] = 1, 0
        copy["patterns"] = copy["patterns"][::-1]

    def relabel_olat(copy):
        copy["frames"][5].update(light=999, row=50, col=7)

    def white_as_olat(copy):
        next(frame for frame in copy["frames"] if frame["kind"] == "white")["kind"] = "olat"

    def unknown_kind(copy):
        copy["frames"][2]["kind"] = "foo"

    def olat_before_patterns(copy):
        copy["frames"] = copy["frames"][-1:] + copy["frames"][:-1]

    def forged_grid(copy):  # compared light by light: the grid's 4e8 lights are never listed
        copy.update(rows=20_000, cols=20_000, panel_pixels=[20_000, 20_000])

    cases = ((swap_indices, "pattern frames \\[1, 0\\] in play order"), (relabel_olat, "OLAT frames do not list"),
             (forged_grid, "OLAT frames do not list the 20000 x 20000 grid's lights"),
             (white_as_olat, "no whole-number light"), (unknown_kind, "kind 'foo'"), (olat_before_patterns, "play order"))
    for change, message in cases:
        edited(change)
        with pytest.raises(InputError, match=message):
            import_frames(tmp_path)
    edited(lambda copy: None)  # the same manifest with the capture order rebuilt still imports
    assert np.abs(import_frames(tmp_path)[0] - values).max() <= 0.5 / 255 + 1e-6


def test_png_with_a_short_header_chunk_is_refused(tmp_path):
    import struct
    import zlib

    from capture_sim.png import decode_png

    short = b"IHDR" + struct.pack(">II", 4, 4)  # 8 of the 13 header bytes
    data = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 8) + short + struct.pack(">I", zlib.crc32(short) & 0xFFFFFFFF)
    with pytest.raises(InputError, match="corrupt PNG header"):
        decode_png(data, "frame.png")


def test_import_refuses_frame_names_outside_the_folder(tmp_path, small_rig):
    export_frames(_patterns(small_rig, 1), small_rig, tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    manifest["frames"][0]["file"] = "../pattern_000.png"
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="plain file name"):
        import_frames(tmp_path)


def test_reexport_removes_stale_frames_and_bad_inputs_are_refused(tmp_path, small_rig):
    import dataclasses

    out = tmp_path / "frames"
    export_frames(_patterns(small_rig, 3), small_rig, out, include_olat=True)
    export_frames(_patterns(small_rig, 1), small_rig, out)
    assert sorted(p.name for p in out.glob("*.png")) == ["contact_sheet.png", "pattern_000.png"]
    import_frames(out)
    with pytest.raises(InputError):
        render_frame(np.full((small_rig.rows, small_rig.cols, 3), 1.5), (20, 40))
    with pytest.raises(InputError):
        render_frame(np.full((small_rig.rows, small_rig.cols), 0.5), (20, 40))
    with pytest.raises(InputError):
        dataclasses.replace(small_rig, panel_pixels=(2160,))
    manifest = json.loads((out / "manifest.json").read_text())
    for key, bad in (("panel_pixels", 5), ("columns_mirrored", "false"), ("rows", True), ("patterns", "abc")):
        broken = dict(manifest, **{key: bad})
        (out / "manifest.json").write_text(json.dumps(broken))
        with pytest.raises(InputError):
            import_frames(out)


def test_export_keeps_frame_files_it_did_not_write(tmp_path, small_rig, monkeypatch):
    from patterns.export import EXPORT_MARKER

    for name in ("olat_000.png", "contact_sheet.png"):  # either marks a folder as the user's
        mine = tmp_path / f"user_{name}"
        mine.mkdir()
        (mine / name).write_bytes(b"the user's own image")
        with pytest.raises(InputError, match="not an export folder"):
            export_frames(_patterns(small_rig, 1), small_rig, mine)
        assert (mine / name).read_bytes() == b"the user's own image"
    interrupted = tmp_path / "interrupted"  # an export stopped before its manifest: frames and the marker
    interrupted.mkdir()
    (interrupted / EXPORT_MARKER).write_text("export in progress\n")
    (interrupted / "pattern_007.png").write_bytes(b"stale")
    export_frames(_patterns(small_rig, 1), small_rig, interrupted)
    assert sorted(p.name for p in interrupted.iterdir()) == ["contact_sheet.png", "manifest.json", "pattern_000.png"]
    # An export folder with frame files its manifest does not list: those are the user's.
    for name in ("pattern_042.png", "olat_mine.png"):
        (interrupted / name).write_bytes(b"the user's own image")
        with pytest.raises(InputError, match=f"frame files its manifest.json does not list \\({name}\\)"):
            export_frames(_patterns(small_rig, 2), small_rig, interrupted)
        assert (interrupted / name).read_bytes() == b"the user's own image"
        (interrupted / name).unlink()
    # Its frames are those import_frames reads (``frames``; ``capture_order`` is optional there).
    manifest = json.loads((interrupted / "manifest.json").read_text())
    del manifest["capture_order"]
    (interrupted / "manifest.json").write_text(json.dumps(manifest))
    export_frames(_patterns(small_rig, 2), small_rig, interrupted)
    # A manifest.json of the user's own does not make a folder an export folder.
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "manifest.json").write_text('{"my": "own manifest"}')
    (theirs / "black.png").write_bytes(b"precious")
    with pytest.raises(InputError, match="manifest.json was not written by displex export"):
        export_frames(_patterns(small_rig, 1), small_rig, theirs)
    assert sorted(p.name for p in theirs.iterdir()) == ["black.png", "manifest.json"]
    (theirs / "manifest.json").write_text("[" * 100000 + "]" * 100000)  # too deep for the JSON reader: not an export's
    with pytest.raises(InputError, match="manifest.json was not written by displex export"):
        export_frames(_patterns(small_rig, 1), small_rig, theirs)
    # A folder where a frame goes is refused before anything moves: the earlier export stays whole.
    (interrupted / "pattern_001.png").unlink()
    (interrupted / "pattern_001.png").mkdir()
    before = {path.name: path.read_bytes() for path in interrupted.iterdir() if path.is_file()}
    with pytest.raises(InputError, match="pattern_001.png: it exists and is not a regular file"):
        export_frames(_patterns(small_rig, 3), small_rig, interrupted)
    assert {path.name: path.read_bytes() for path in interrupted.iterdir() if path.is_file()} == before
    (interrupted / "pattern_001.png").rmdir()
    (interrupted / "contact_sheet.png").unlink()
    (interrupted / "contact_sheet.png").mkdir()  # refused before the frames are rendered, not after
    with monkeypatch.context() as patch:
        patch.setattr("patterns.export._write_export", lambda *args, **kwargs: pytest.fail("the frames were rendered"))
        with pytest.raises(InputError, match="contact_sheet.png: it exists and is not a regular file"):
            export_frames(_patterns(small_rig, 3), small_rig, interrupted)
    with pytest.raises(InputError, match="cannot write into .*black.png/inside: .*black.png is a file, not a folder"):
        export_frames(_patterns(small_rig, 1), small_rig, theirs / "black.png" / "inside")


def test_export_and_pattern_commands_never_destroy_their_inputs(tmp_path, small_rig, capsys):
    from capture_sim.rig import RIG_DIR
    from train.cli import run

    out = tmp_path / "frames"
    export_frames(_patterns(small_rig, 2), small_rig, out)
    cases = [
        # A pattern output over the export's contact sheet or the rig file (refused by name: pattern files are .npz);
        # an export whose --patterns file lies in the export folder.
        (["import-frames", str(out), "--out", str(out / "contact_sheet.png")], "name the output *.npz"),
        (["export", "--patterns", str(out / "pattern_009.png"), "--out", str(out)], "lies in the export folder"),
        (["patterns", "make", "--family", "olat", "--M", "2", "--rig", str(tmp_path / "rig.toml"), "--out", str(tmp_path / "rig.toml")],
         "name the output *.npz"),
    ]
    (out / "pattern_009.png").write_bytes(b"patterns saved under a frame name")
    (tmp_path / "rig.toml").write_text((RIG_DIR / "panel-55in-4x8.toml").read_text())
    for argv, message in cases:
        capsys.readouterr()
        assert run(argv) == 2, argv
        assert message in capsys.readouterr().err, argv
    assert (out / "pattern_009.png").read_bytes() == b"patterns saved under a frame name"
    assert (tmp_path / "rig.toml").read_text() == (RIG_DIR / "panel-55in-4x8.toml").read_text()
    manifest = json.loads((out / "manifest.json").read_text())
    (out / "manifest.json").write_text(json.dumps(dict(manifest, num_patterns=10**12)))
    (out / "pattern_009.png").unlink()  # a frame the manifest does not list is refused first
    with pytest.raises(InputError, match="manifest lists 2 pattern frames, but num_patterns is 1000000000000"):
        import_frames(out)


def test_contact_sheet_of_a_large_set_draws_the_first_panels():
    from patterns.contact_sheet import MAX_PANELS, contact_sheet_figure

    values = np.random.default_rng(0).uniform(0, 1, (MAX_PANELS + 5, 3, 4, 3))
    fig = contact_sheet_figure(values, "many")
    drawn = [ax for ax in fig.axes if ax.images]
    assert len(drawn) == MAX_PANELS and f"the first {MAX_PANELS} of {MAX_PANELS + 5} shown" in fig._suptitle.get_text()


def test_a_failed_re_export_leaves_the_earlier_export_whole(tmp_path, small_rig, monkeypatch):
    """A re-export that fails part-way (a full disk, Ctrl-C) leaves the earlier export as it was,
    importable, with no partial frames; one that succeeds replaces it completely."""
    import patterns.export as export

    out = tmp_path / "frames"
    export_frames(_patterns(small_rig, 2), small_rig, out)
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    encode, written = export.encode_png, []

    def fails_on_the_third_frame(image, level):
        if len(written) == 2:
            raise OSError(28, "No space left on device")
        written.append(1)
        return encode(image, level)

    monkeypatch.setattr(export, "encode_png", fails_on_the_third_frame)
    with pytest.raises(OSError):
        export_frames(_patterns(small_rig, 3), small_rig, out, include_olat=True)
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before
    assert import_frames(out)[0].shape[0] == 2
    monkeypatch.setattr(export, "encode_png", encode)
    export_frames(_patterns(small_rig, 1), small_rig, out)
    assert sorted(path.name for path in out.iterdir()) == ["contact_sheet.png", "manifest.json", "pattern_000.png"]


def test_export_refusals_and_unlisted_frames(tmp_path, small_rig):
    """A rig without panel_pixels, a float bit depth and a bad compression level are refused;
    import refuses frame files the manifest does not list (a rig playing the folder would show them)."""
    with pytest.raises(InputError, match="gives no display panel_pixels"):
        export_frames(_patterns(small_rig, 1), small_rig.replace(panel_pixels=None), tmp_path / "a")
    with pytest.raises(InputError, match="bit depth must be 8 or 16, got 8.0"):
        export_frames(_patterns(small_rig, 1), small_rig, tmp_path / "b", bit_depth=8.0)
    with pytest.raises(InputError, match="compression level"):
        export_frames(_patterns(small_rig, 1), small_rig, tmp_path / "c", compression_level=10)
    assert not any((tmp_path / name).exists() for name in "abc")
    out = tmp_path / "frames"
    export_frames(_patterns(small_rig, 2), small_rig, out)
    (out / "pattern_002.png").write_bytes((out / "pattern_000.png").read_bytes())
    with pytest.raises(InputError, match="frame files not listed in the manifest: pattern_002.png"):
        import_frames(out)


def test_contact_sheet_of_one_pattern_has_room_for_its_title():
    from patterns.contact_sheet import contact_sheet_figure

    fig = contact_sheet_figure(np.zeros((1, 9, 16, 3), np.float32), "1 patterns for rig dir-odyssey-ark (pattern grid order)")
    assert fig.get_size_inches()[0] >= 6.4  # a 3.2-inch sheet cut the title off on both sides


def test_export_import_fixes_from_the_rig_builder_run(tmp_path, small_rig):
    """Every listed frame's size and bit depth is checked, OLAT frames included; names sort in
    capture order past 999 frames; bit depths must be whole numbers and are quoted as found; a killed command's staging folder is
    reported on the next write into its folder."""
    import warnings

    from capture_sim.atomic import staged_files
    from capture_sim.errors import DisplexWarning

    export_frames(_patterns(small_rig, 2), small_rig, tmp_path / "olat", include_olat=True)
    manifest_path = tmp_path / "olat" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    small = np.zeros((9, 16, 3), np.uint8)  # a forged OLAT frame, its checksum updated to match
    write_png(tmp_path / "olat" / "olat_003.png", small)
    entry = next(frame for frame in manifest["frames"] if frame["file"] == "olat_003.png")
    entry["sha256"] = hashlib.sha256((tmp_path / "olat" / "olat_003.png").read_bytes()).hexdigest()
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="olat_003.png is 9 x 16 at 8 bits.*90 x 160 RGB at 8 bits"):
        import_frames(tmp_path / "olat")

    assert [frame_digits(m, k) for m, k in ((2, 0), (1000, 144), (1001, 0), (4, 1200), (12000, 0))] == [3, 3, 4, 4, 5]
    names = [f"pattern_{m:0{frame_digits(1001, 0)}d}.png" for m in range(1001)]
    assert names == sorted(names)

    export_frames(_patterns(small_rig, 2), small_rig, tmp_path / "renamed")
    manifest_path = tmp_path / "renamed" / "manifest.json"
    manifest_path.write_text(manifest_path.read_text().replace('"bit_depth": 8', '"bit_depth": "8"'))
    with pytest.raises(InputError, match="bit_depth must be 8 or 16, got '8'"):
        import_frames(tmp_path / "renamed")
    with pytest.raises(InputError, match="bit depth must be 8 or 16, got 8.0"):
        render_frame(_patterns(small_rig, 1)[0], (90, 160), bit_depth=8.0)

    (tmp_path / "renamed" / ".staging.killed").mkdir()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with staged_files(tmp_path / "renamed"):
            pass
    assert any(issubclass(w.category, DisplexWarning) and ".staging.killed" in str(w.message) for w in caught)


def test_export_contact_sheet_shows_the_frames_as_the_display_does(tmp_path, small_rig, monkeypatch):
    """The sheet beside mirrored frames showed the patterns unmirrored: checked against the panel,
    every pattern looked reversed."""
    import patterns.export as export_module
    from patterns.contact_sheet import contact_sheet_figure

    seen = {}
    monkeypatch.setattr(export_module, "save_contact_sheet", lambda path, values, title, mirrored=False: seen.update(mirrored=mirrored))
    manifest = export_frames(_patterns(small_rig, 2), small_rig, tmp_path)
    assert seen["mirrored"] is manifest["columns_mirrored"] is True
    values = np.zeros((1, 9, 16, 3), np.float32)
    for mirrored, extent in ((True, (15.5, -0.5)), (False, (-0.5, 15.5))):
        fig = contact_sheet_figure(values, "sheet", mirrored=mirrored)
        assert tuple(fig.axes[0].get_images()[0].get_extent()[:2]) == extent
        assert ("pattern column 0 at the right" in fig._supxlabel.get_text().replace("\n", " ")) == mirrored
