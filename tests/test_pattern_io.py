import json
import io
import struct
import zlib
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.png import decode_png, encode_png, read_png, write_png
from patterns.families import make_patterns
from patterns.io import check_patterns_match_rig, load_patterns, save_patterns


def _patterns(num_patterns=3, rows=9, cols=16, seed=0):
    return np.random.default_rng(seed).uniform(0, 1, (num_patterns, rows, cols, 3)).astype(np.float32)


# --- pattern files -----------------------------------------------------------------------------

def test_npz_round_trip_keeps_values_and_meta(tmp_path):
    patterns = _patterns()
    meta = {"family": "tri_random", "parameters": {"seed": 3}, "rig": "dir-odyssey-ark", "made_by": "test"}
    path = tmp_path / "set.npz"
    save_patterns(path, patterns, meta)
    loaded, loaded_meta = load_patterns(path)
    assert loaded.dtype == np.float32 and loaded.shape == patterns.shape
    np.testing.assert_array_equal(loaded, patterns)
    assert loaded_meta == meta
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_tensor_and_float64_inputs_are_stored_as_float32(tmp_path):
    patterns = torch.rand(2, 4, 8, 3, dtype=torch.float64)
    save_patterns(tmp_path / "set.npz", patterns)
    loaded, meta = load_patterns(tmp_path / "set.npz")
    assert loaded.dtype == np.float32 and meta == {}
    np.testing.assert_allclose(loaded, patterns.numpy(), atol=1e-7)


def test_plain_npy_is_accepted(tmp_path):
    patterns = _patterns(2)
    np.save(tmp_path / "plain.npy", patterns.astype(np.float64))
    loaded, meta = load_patterns(tmp_path / "plain.npy")
    np.testing.assert_array_equal(loaded, patterns)
    assert meta == {}


@pytest.mark.parametrize(
    "array, message",
    [
        (np.zeros((9, 16, 3), np.float32), "shape"),
        (np.zeros((2, 9, 16, 4), np.float32), "shape"),
        (np.zeros((0, 9, 16, 3), np.float32), "at least one"),
        (np.full((1, 9, 16, 3), np.nan, np.float32), "NaN"),
        (np.full((1, 9, 16, 3), 1.5, np.float32), r"\[0, 1\]"),
        (np.full((1, 9, 16, 3), -0.01, np.float32), r"\[0, 1\]"),
        (np.array([["a"]]), "real numbers"),
    ],
)
def test_bad_arrays_raise_one_clear_error(tmp_path, array, message):
    np.save(tmp_path / "bad.npy", array)
    with pytest.raises(InputError, match=message):
        load_patterns(tmp_path / "bad.npy")
    if array.dtype.kind == "f":
        with pytest.raises(InputError, match=message):
            save_patterns(tmp_path / "bad.npz", array)


def test_bad_files_raise(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_patterns(tmp_path / "missing.npz")
    (tmp_path / "garbage.npz").write_bytes(b"this is not an array file")
    with pytest.raises(InputError, match="not a pattern file"):
        load_patterns(tmp_path / "garbage.npz")
    np.savez(tmp_path / "other.npz", olat=np.zeros(3))
    with pytest.raises(InputError, match="no 'patterns'"):
        load_patterns(tmp_path / "other.npz")
    save_patterns(tmp_path / "good.npz", _patterns(1))
    truncated = (tmp_path / "good.npz").read_bytes()[:200]
    (tmp_path / "truncated.npz").write_bytes(truncated)
    with pytest.raises(InputError, match="not a readable"):
        load_patterns(tmp_path / "truncated.npz")
    np.savez(tmp_path / "badmeta.npz", patterns=_patterns(1), meta=np.array("[1, 2]"))
    with pytest.raises(InputError, match="JSON object"):
        load_patterns(tmp_path / "badmeta.npz")
    np.savez_compressed(tmp_path / "big.npz", patterns=np.random.default_rng(0).random((8, 9, 16, 3), dtype=np.float32))
    damaged = bytearray((tmp_path / "big.npz").read_bytes())
    damaged[200:232] = bytes(32)  # inside the compressed array
    (tmp_path / "damaged.npz").write_bytes(bytes(damaged))
    with pytest.raises(InputError, match="not a readable"):
        load_patterns(tmp_path / "damaged.npz")
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(InputError, match="not a pattern file"):
        load_patterns(tmp_path / "empty.npz")
    np.savez(tmp_path / "notjson.npz", patterns=_patterns(1), meta=np.array("{oops"))
    with pytest.raises(InputError, match="not JSON"):
        load_patterns(tmp_path / "notjson.npz")


def test_absurdly_nested_meta_is_one_clear_error(tmp_path):
    nested = '{"a":' + "[" * 100000 + "]" * 100000 + "}"
    np.savez(tmp_path / "deep.npz", patterns=_patterns(1), meta=np.array(nested.encode("ascii")))
    with pytest.raises(InputError, match="nested too deeply"):
        load_patterns(tmp_path / "deep.npz")


def test_meta_must_be_json(tmp_path):
    with pytest.raises(InputError, match="JSON"):
        save_patterns(tmp_path / "set.npz", _patterns(1), {"rig": object()})
    assert not (tmp_path / "set.npz").exists()
    for meta in ("made by hand", [1, 2], 42):  # JSON, but not a dict: load_patterns would refuse the file
        with pytest.raises(InputError, match="must be a dict"):
            save_patterns(tmp_path / "set.npz", _patterns(1), meta)
        assert not (tmp_path / "set.npz").exists()


def test_non_finite_meta_and_json_outputs_are_strict_json(tmp_path):
    # NaN and infinities have no JSON token: they are written as null, which every parser reads.
    from capture_sim.atomic import write_json

    meta = {"val_mae_history": [[50, float("nan")], (100, 9.5)], "loss": float("inf"), "nested": {"x": -float("inf")}}
    save_patterns(tmp_path / "set.npz", _patterns(1), meta)
    expected = {"val_mae_history": [[50, None], [100, 9.5]], "loss": None, "nested": {"x": None}}
    stored = np.load(tmp_path / "set.npz")["meta"].item().decode("ascii")
    assert "NaN" not in stored and "Infinity" not in stored
    assert load_patterns(tmp_path / "set.npz")[1] == expected
    write_json(tmp_path / "r.json", meta)
    text = (tmp_path / "r.json").read_text()
    assert json.loads(text, parse_constant=lambda token: pytest.fail(f"non-standard token {token}")) == expected


def test_check_patterns_match_rig(reference_rig):
    check_patterns_match_rig(_patterns(2), reference_rig.rows, reference_rig.cols)
    with pytest.raises(InputError, match="9 x 16"):
        check_patterns_match_rig(_patterns(2, 4, 8), reference_rig.rows, reference_rig.cols)
    with pytest.raises(InputError, match="grid"):
        check_patterns_match_rig(torch.zeros(9, 16, 3), 9, 16)


# --- PNG ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(5, 7, 3), (4, 6), (1, 1, 3)])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_round_trip(tmp_path, shape, dtype):
    image = np.random.default_rng(0).integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    write_png(tmp_path / "image.png", image)
    loaded = read_png(tmp_path / "image.png")
    assert loaded.dtype == dtype and loaded.shape == shape
    np.testing.assert_array_equal(loaded, image)


def test_png_8bit_matches_an_independent_decoder():
    image = np.random.default_rng(1).integers(0, 256, (6, 9, 3)).astype(np.uint8)
    decoded = mpimg.imread(io.BytesIO(encode_png(image)), format="png")
    np.testing.assert_array_equal(np.round(decoded * 255).astype(np.uint8), image)


def test_png_16bit_is_big_endian_in_the_stream():
    image = np.array([[[0x0102, 0x0304, 0x0506]]], dtype=np.uint16)
    data = encode_png(image, level=0)
    idat_start = data.index(b"IDAT") + 4
    length = struct.unpack(">I", data[idat_start - 8 : idat_start - 4])[0]
    raw = zlib.decompress(data[idat_start : idat_start + length])
    assert raw == bytes([0, 1, 2, 3, 4, 5, 6])


def _with_filter(data: bytes, filter_type: int) -> bytes:
    """Rebuild a displex PNG with every row tagged with another filter type."""
    start = data.index(b"IDAT")
    length = struct.unpack(">I", data[start - 4 : start])[0]
    raw = bytearray(zlib.decompress(data[start + 4 : start + 4 + length]))
    raw[0] = filter_type
    body = zlib.compress(bytes(raw))
    chunk = struct.pack(">I", len(body)) + b"IDAT" + body + struct.pack(">I", zlib.crc32(b"IDAT" + body))
    return data[: start - 4] + chunk + data[start + 8 + length :]


def test_png_bad_inputs_raise(tmp_path):
    with pytest.raises(InputError, match="uint8 or uint16"):
        encode_png(np.zeros((2, 2, 3), np.float32))
    with pytest.raises(InputError, match="shape"):
        encode_png(np.zeros((2, 2, 4), np.uint8))
    with pytest.raises(InputError, match="not found"):
        read_png(tmp_path / "missing.png")
    with pytest.raises(InputError, match="not a PNG"):
        decode_png(b"GIF89a")
    good = encode_png(np.zeros((2, 3, 3), np.uint8))
    corrupt = bytearray(good)
    corrupt[-20] ^= 0xFF
    with pytest.raises(InputError, match="corrupt"):
        decode_png(bytes(corrupt))
    with pytest.raises(InputError, match="filter"):
        decode_png(_with_filter(good, 1))
    rgba = io.BytesIO()
    mpimg.imsave(rgba, np.zeros((2, 3, 3)), format="png")
    with pytest.raises(InputError, match="grey or RGB"):
        decode_png(rgba.getvalue())


def test_bfloat16_patterns_and_list_shapes_are_read():
    import torch

    from patterns.io import check_patterns_match_rig, validate_patterns

    values = validate_patterns(torch.full((1, 2, 3, 3), 0.5, dtype=torch.bfloat16))
    assert values.dtype == np.float32 and (values == 0.5).all()
    with pytest.raises(InputError):
        check_patterns_match_rig([1, 2], 9, 16)


def test_meta_of_a_large_random_set_stays_small(tmp_path):
    """A random family's file does not repeat its values as named parameters, and keeps its meta
    as compressed ASCII (it used to be 40x the values); files of the older layout still read."""
    from train.cli import run

    assert run(["patterns", "make", "--family", "tri_random", "--M", "100", "--out", str(tmp_path / "many.npz")]) == 0
    loaded, meta = load_patterns(tmp_path / "many.npz")
    assert (tmp_path / "many.npz").stat().st_size < 1.2 * loaded.nbytes and meta["family"] == "tri_random"
    assert np.array_equal(loaded, make_patterns("tri_random", 100).numpy())
    save_patterns(tmp_path / "note.npz", loaded[:1], {"note": "réglé", "weights": [0.1] * 1000})
    assert load_patterns(tmp_path / "note.npz")[1] == {"note": "réglé", "weights": [0.1] * 1000}
    np.savez(tmp_path / "old.npz", patterns=loaded, meta=np.array(json.dumps({"family": "tri_random"})))
    assert load_patterns(tmp_path / "old.npz")[1] == {"family": "tri_random"}


def test_a_pattern_file_named_in_capitals_is_one_to_start_from():
    """check_pattern_output accepts x.NPZ, so x.NPZ must also read as a pattern file (--init)."""
    from patterns.io import names_pattern_file

    assert names_pattern_file("learned.NPZ") and names_pattern_file("p.Npy") and not names_pattern_file("tri_gradient")


def test_an_output_path_through_missing_folders_and_back_creates_none(tmp_path, monkeypatch):
    """'a/b/../../p.npz' is p.npz: the parents as written (a/, a/b/) were created and left behind.
    A symlink as the output is replaced by the file, as before; its target is left alone."""
    from capture_sim.atomic import write_json

    monkeypatch.chdir(tmp_path)
    save_patterns(Path("a/b/../../p.npz"), np.zeros((2, 9, 16, 3), dtype=np.float32))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["p.npz"]
    (tmp_path / "target.json").write_text("{}")
    (tmp_path / "link.json").symlink_to(tmp_path / "target.json")
    write_json(Path("link.json"), {"x": 1})
    assert not (tmp_path / "link.json").is_symlink() and (tmp_path / "target.json").read_text() == "{}"
