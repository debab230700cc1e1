"""Tests for mpib_validate.runtime.io.exr: real OpenEXR files in tmp_path, no mocks."""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import OpenEXR
import pytest

from mpib_validate.runtime.io.exr import (
    ExrError,
    ExrImage,
    channels_from_rgba,
    find_pass,
    image_size,
    read_exr,
    rgba_from,
    write_exr,
)

H, W = 7, 5


def _rand(seed: int, dtype=np.float32, shape=(H, W)) -> np.ndarray:
    return (np.random.default_rng(seed).standard_normal(shape) * 10).astype(dtype)


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _leftovers(directory) -> list[str]:
    return sorted(n for n in os.listdir(directory) if ".tmp-" in n)


def _header(**extra):
    return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **extra}


# --------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------


def test_round_trip_float32_and_float16_bitwise(tmp_path):
    special = _rand(0)
    special[0, 0] = np.nan
    special[0, 1] = np.inf
    special[0, 2] = -np.inf
    special[0, 3] = -0.0
    special[0, 4] = np.float32(1e-40)  # denormal
    data = {
        "R": special,
        "G": _rand(1),
        "B": _rand(2, np.float16),
        "Depth.Z": _rand(3),
        "AllInFocus.R": _rand(4),
        "Index": np.arange(H * W, dtype=np.uint32).reshape(H, W),
    }
    path = tmp_path / "rt.exr"
    write_exr(path, data)
    img = read_exr(path)
    assert isinstance(img, ExrImage)
    assert img.path == str(path)
    assert set(img.channels) == set(data)
    for name, arr in data.items():
        assert _bits_equal(img.channels[name], arr), name
    assert img.shape == (H, W)
    assert img.header["compression"] == "ZIP_COMPRESSION"
    assert img.header["type"] == "scanlineimage"
    assert img.header["dataWindow"] == ((0, 0), (W - 1, H - 1))
    assert sorted(img.header["channels"]) == sorted(data)


def test_half_true_and_half_set(tmp_path):
    a, b = _rand(5), _rand(6)
    write_exr(tmp_path / "all.exr", {"R": a, "G": b}, half=True)
    img = read_exr(tmp_path / "all.exr")
    assert _bits_equal(img.channels["R"], a.astype(np.float16))
    assert _bits_equal(img.channels["G"], b.astype(np.float16))

    write_exr(tmp_path / "some.exr", {"R": a, "G": b}, half={"G"})
    img = read_exr(tmp_path / "some.exr")
    assert _bits_equal(img.channels["R"], a)
    assert _bits_equal(img.channels["G"], b.astype(np.float16))

    with pytest.raises(ExrError, match="Gx"):
        write_exr(tmp_path / "bad.exr", {"R": a}, half={"Gx"})


def test_float64_stored_as_float32(tmp_path):
    a = np.random.default_rng(7).random((H, W))  # float64
    write_exr(tmp_path / "f64.exr", {"Y": a})
    got = read_exr(tmp_path / "f64.exr").channels["Y"]
    assert _bits_equal(got, a.astype(np.float32))


def test_non_contiguous_input_written_correctly(tmp_path):
    # The OpenEXR binding writes strided arrays wrongly; write_exr must not.
    rgba = np.random.default_rng(8).random((H, W, 4)).astype(np.float32)
    write_exr(tmp_path / "nc.exr", {"R": rgba[..., 0], "G": rgba[..., 1], "T": rgba[..., 2].T.T})
    img = read_exr(tmp_path / "nc.exr")
    assert _bits_equal(img.channels["R"], rgba[..., 0].copy())
    assert _bits_equal(img.channels["G"], rgba[..., 1].copy())


def test_attributes_round_trip(tmp_path):
    meta = json.dumps({"scene": "plane", "f_mm": 50.0, "note": "ünïcode €"})
    write_exr(tmp_path / "a.exr", {"R": _rand(9)}, attributes={"mpib": meta, "comments": "hi"})
    img = read_exr(tmp_path / "a.exr")
    assert img.header["mpib"] == meta
    assert json.loads(img.header["mpib"])["f_mm"] == 50.0
    assert img.header["comments"] == "hi"


@pytest.mark.parametrize(
    "attributes, fragment",
    [
        ({"channels": "x"}, "reserved"),
        ({"meta": 3}, "must be a str"),
        ({"": "x"}, "non-empty"),
        ({"m" * 256: "x"}, "255"),
    ],
)
def test_bad_attributes(tmp_path, attributes, fragment):
    with pytest.raises(ExrError, match=fragment):
        write_exr(tmp_path / "a.exr", {"R": _rand(9)}, attributes=attributes)
    assert os.listdir(tmp_path) == []


def test_compression_options(tmp_path):
    a = _rand(10)
    for comp in ("none", "zips", "piz", OpenEXR.RLE_COMPRESSION):
        write_exr(tmp_path / "c.exr", {"R": a}, compression=comp)
        assert _bits_equal(read_exr(tmp_path / "c.exr").channels["R"], a)
    with pytest.raises(ExrError, match="unknown compression"):
        write_exr(tmp_path / "c.exr", {"R": a}, compression="gzip9")


def test_write_is_deterministic(tmp_path):
    data = {"R": _rand(11), "G": _rand(12, np.float16), "Depth.Z": _rand(13)}
    attrs = {"meta": json.dumps({"k": 1})}
    write_exr(tmp_path / "one.exr", data, attributes=attrs)
    write_exr(tmp_path / "sub" / "two.exr", data, attributes=attrs)
    first = (tmp_path / "one.exr").read_bytes()
    assert first == (tmp_path / "sub" / "two.exr").read_bytes()
    write_exr(tmp_path / "one.exr", data, attributes=attrs)  # overwrite
    assert (tmp_path / "one.exr").read_bytes() == first


def test_creates_parent_directories(tmp_path):
    target = tmp_path / "a" / "b" / "c.exr"
    write_exr(str(target), {"R": _rand(14)})
    assert target.is_file()
    assert _leftovers(target.parent) == []


# --------------------------------------------------------------------------
# write validation and atomicity
# --------------------------------------------------------------------------


def test_failed_write_leaves_target_untouched(tmp_path):
    target = tmp_path / "t.exr"
    write_exr(target, {"R": _rand(15)})
    before = target.read_bytes()
    with pytest.raises(ExrError) as info:
        write_exr(target, {"R": _rand(16), "Depth.Z": np.zeros((H + 1, W), np.float32)})
    msg = str(info.value)
    assert "Depth.Z" in msg and str((H + 1, W)) in msg and str((H, W)) in msg
    assert target.read_bytes() == before
    assert _leftovers(tmp_path) == []


def test_unwritable_location_raises_exr_error(tmp_path):
    target = tmp_path / "t.exr"
    write_exr(target, {"R": _rand(17)})
    before = target.read_bytes()
    # Parent "directory" is a regular file -> nothing can be created there.
    blocker = tmp_path / "blocker"
    blocker.write_bytes(b"x")
    with pytest.raises(ExrError, match="blocker"):
        write_exr(blocker / "x.exr", {"R": _rand(18)})
    assert target.read_bytes() == before
    assert _leftovers(tmp_path) == []


def test_write_target_is_directory(tmp_path):
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(ExrError, match="directory"):
        write_exr(tmp_path / "d.exr", {"R": _rand(19)})
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "channels, fragment",
    [
        ({}, "no channels"),
        ({"R": np.zeros((H, W, 3), np.float32)}, "2-D"),
        ({"R": np.zeros((0, W), np.float32)}, "empty"),
        ({"R": np.zeros((H, W), np.int64)}, "int64"),
        ({"": np.zeros((H, W), np.float32)}, "non-empty"),
        ({"X" * 256: np.zeros((H, W), np.float32)}, "255"),
        ({"\u00fc" * 128: np.zeros((H, W), np.float32)}, "255"),  # 256 UTF-8 bytes
        ({"R\x00x": np.zeros((H, W), np.float32)}, "NUL"),
    ],
)
def test_write_rejects_bad_channels(tmp_path, channels, fragment):
    with pytest.raises(ExrError, match=fragment):
        write_exr(tmp_path / "bad.exr", channels)
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------
# multi-part files (Blender 5.0 multilayer layout)
# --------------------------------------------------------------------------


def _write_multipart(path, parts):
    OpenEXR.File([OpenEXR.Part(_header(), chans, name) for name, chans in parts]).write(str(path))


def test_multipart_channel_names_fully_qualified(tmp_path):
    r, g, b, a, z = (_rand(20 + i) for i in range(5))
    path = tmp_path / "multi.exr"
    _write_multipart(
        path,
        [
            # mixed: some names already carry the part prefix, some do not
            ("ViewLayer.Combined", {"ViewLayer.Combined.R": r, "ViewLayer.Combined.G": g, "B": b, "A": a}),
            ("ViewLayer.Depth", {"Z": z}),
        ],
    )
    img = read_exr(path)
    assert sorted(img.channels) == [
        "ViewLayer.Combined.A",
        "ViewLayer.Combined.B",
        "ViewLayer.Combined.G",
        "ViewLayer.Combined.R",
        "ViewLayer.Depth.Z",
    ]
    assert _bits_equal(img.channels["ViewLayer.Combined.R"], r)
    assert _bits_equal(img.channels["ViewLayer.Combined.B"], b)
    assert _bits_equal(img.channels["ViewLayer.Depth.Z"], z)
    assert img.header["name"] == "ViewLayer.Combined"

    rgba = rgba_from(img, "ViewLayer.Combined.")
    assert rgba.shape == (H, W, 4) and rgba.dtype == np.float32
    assert _bits_equal(rgba[..., 3].copy(), a)
    assert find_pass(img, "Depth") == "ViewLayer.Depth.Z"


def test_multipart_blender_style_prefixed_names(tmp_path):
    z = _rand(30)
    path = tmp_path / "blender.exr"
    _write_multipart(
        path,
        [
            ("ViewLayer.Combined", {f"ViewLayer.Combined.{c}": _rand(31 + i) for i, c in enumerate("RGBA")}),
            ("ViewLayer.Depth", {"ViewLayer.Depth.Z": z}),
        ],
    )
    img = read_exr(path)
    assert "ViewLayer.Depth.Z" in img.channels
    assert "ViewLayer.Depth.ViewLayer.Depth.Z" not in img.channels
    assert _bits_equal(img.channels[find_pass(img, "Depth")], z)


def test_multipart_duplicate_full_name(tmp_path):
    # Part "A" channel "B.Z" -> "A.B.Z"; part "A.B" channel "Z" -> "A.B.Z".
    path = tmp_path / "clash.exr"
    _write_multipart(path, [("A", {"B.Z": _rand(52)}), ("A.B", {"Z": _rand(53)})])
    with pytest.raises(ExrError, match=r"'A\.B\.Z' occurs twice") as info:
        read_exr(path)
    assert str(path) in str(info.value)

    # Same stored channel name in differently named parts is no clash.
    path = tmp_path / "ok.exr"
    _write_multipart(path, [("A", {"Z": _rand(54)}), ("B", {"Z": _rand(55)}), ("C", {"C.Z": _rand(56)})])
    assert sorted(read_exr(path).channels) == ["A.Z", "B.Z", "C.Z"]


def test_unnamed_parts_get_default_names(tmp_path):
    # Fact about the binding: unnamed parts of a multi-part file are named
    # Part0, Part1, ... on write, so they read back qualified.
    path = tmp_path / "unnamed.exr"
    OpenEXR.File([OpenEXR.Part({}, {"Z": _rand(54)}), OpenEXR.Part({}, {"Z": _rand(55)})]).write(str(path))
    assert sorted(read_exr(path).channels) == ["Part0.Z", "Part1.Z"]


# --------------------------------------------------------------------------
# unreadable files
# --------------------------------------------------------------------------


def _good_file(tmp_path) -> bytes:
    src = tmp_path / "good.exr"
    # Enough rows for several ZIP chunks (16 scanlines each).
    write_exr(src, {"R": _rand(60, shape=(64, 32)), "G": _rand(61, shape=(64, 32))})
    return src.read_bytes()


def _corrupt_first_chunk_leader(data: bytes, n_chunks: int = 4) -> bytes:
    """Overwrite the scanline number in the first chunk's leader.

    (Flipping bytes inside ZIP-compressed data is NOT reliably detected by
    OpenEXR -- it can decode to garbage silently -- and a damaged offset
    table is silently rebuilt, so corrupt the chunk leader, which is checked.)
    """
    # The offset table (n_chunks uint64) follows the header; its first entry
    # points just past the table.
    table = next(
        p for p in range(len(data) - 8) if struct.unpack("<Q", data[p : p + 8])[0] == p + 8 * n_chunks
    )
    first_chunk = table + 8 * n_chunks
    bad = bytearray(data)
    bad[first_chunk : first_chunk + 4] = struct.pack("<i", 12345)
    return bytes(bad)


@pytest.mark.parametrize(
    "kind, fragment",
    [
        ("missing", "does not exist"),
        ("empty", "empty"),
        ("garbage", "not an OpenEXR file"),
        ("directory", "directory"),
        ("truncated_header", "header"),
        ("truncated_pixels", "truncated"),
        ("truncated_tail", "truncated"),
        ("corrupt_pixels", "corrupt"),
        ("truncated_multipart", "truncated"),
    ],
)
def test_unreadable_files_raise_exr_error(tmp_path, kind, fragment):
    path = tmp_path / f"{kind}.exr"
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "garbage":
        path.write_bytes(b"this is not an EXR file\n" * 20)
    elif kind == "directory":
        path.mkdir()
    elif kind == "truncated_header":
        path.write_bytes(_good_file(tmp_path)[:60])
    elif kind == "truncated_pixels":
        good = _good_file(tmp_path)
        path.write_bytes(good[: len(good) // 2])
    elif kind == "truncated_tail":
        path.write_bytes(_good_file(tmp_path)[:-10])
    elif kind == "corrupt_pixels":
        path.write_bytes(_corrupt_first_chunk_leader(_good_file(tmp_path)))
    elif kind == "truncated_multipart":
        src = tmp_path / "mp.exr"
        _write_multipart(src, [("a", {"R": _rand(62, shape=(64, 32))}), ("b", {"Z": _rand(63, shape=(64, 32))})])
        path.write_bytes(src.read_bytes()[:-100])
    with pytest.raises(ExrError) as info:
        read_exr(path)
    msg = str(info.value)
    assert str(path) in msg
    assert fragment in msg
    assert isinstance(info.value, ValueError)


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def test_rgba_helpers_round_trip(tmp_path):
    rgba = np.random.default_rng(70).random((H, W, 4)).astype(np.float32)
    chans = channels_from_rgba(rgba, "AllInFocus.")
    assert sorted(chans) == ["AllInFocus.A", "AllInFocus.B", "AllInFocus.G", "AllInFocus.R"]
    write_exr(tmp_path / "x.exr", {**chans, **channels_from_rgba(rgba[..., :3])})
    img = read_exr(tmp_path / "x.exr")
    assert _bits_equal(rgba_from(img, "AllInFocus."), rgba)
    plain = rgba_from(img)  # no "A" -> ones
    assert _bits_equal(plain[..., :3].copy(), rgba[..., :3].copy())
    assert np.all(plain[..., 3] == 1.0)

    with pytest.raises(ExrError):
        channels_from_rgba(np.zeros((H, W, 2)))


def test_rgba_from_half_promotes_to_float32(tmp_path):
    rgb = np.random.default_rng(71).random((H, W, 3)).astype(np.float16)
    write_exr(tmp_path / "h.exr", channels_from_rgba(rgb))
    out = rgba_from(read_exr(tmp_path / "h.exr"))
    assert out.dtype == np.float32
    assert np.array_equal(out[..., :3], rgb.astype(np.float32))


def test_rgba_from_missing_channel(tmp_path):
    path = tmp_path / "rg.exr"
    write_exr(path, {"R": _rand(72), "G": _rand(73)})
    with pytest.raises(ExrError) as info:
        rgba_from(read_exr(path))
    msg = str(info.value)
    assert str(path) in msg and "'B'" in msg
    with pytest.raises(ExrError, match=r"'ViewLayer\.Combined\.R'"):
        rgba_from(read_exr(path), "ViewLayer.Combined.")


@pytest.mark.parametrize(
    "names, expected",
    [
        (["R", "G", "B", "Z"], "Z"),
        (["R", "G", "B", "Depth.Z"], "Depth.Z"),
        (["ViewLayer.Combined.R", "ViewLayer.Depth.Z"], "ViewLayer.Depth.Z"),
    ],
)
def test_find_pass_depth(names, expected):
    img = ExrImage({n: np.zeros((1, 1), np.float32) for n in names}, {}, "mem.exr")
    assert find_pass(img, "Depth") == expected


def test_find_pass_other_pass_and_errors():
    names = ["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Mist.Z", "Z", "ViewLayer.Depth.Z"]
    img = ExrImage({n: np.zeros((1, 1), np.float32) for n in names}, {}, "file.exr")
    assert find_pass(img, "Mist") == "ViewLayer.Mist.Z"
    assert find_pass(img, "ViewLayer.Mist") == "ViewLayer.Mist.Z"

    with pytest.raises(ExrError) as info:
        find_pass(img, "Normal")
    msg = str(info.value)
    assert msg.startswith("no Normal pass in 'file.exr'; channels: ")
    assert "ViewLayer.Mist.Z" in msg

    with pytest.raises(ExrError, match="ambiguous Depth pass") as info:
        find_pass(img, "Depth")  # "Z" and "ViewLayer.Depth.Z"
    assert "'file.exr'" in str(info.value)

    with pytest.raises(ExrError, match="ambiguous Combined"):
        find_pass(img, "Combined")


def test_single_part_with_name_attribute_is_qualified(tmp_path):
    # The prefix rule applies to every named part, also in a one-part file.
    path = tmp_path / "named.exr"
    _write_multipart(path, [("ViewLayer.Combined", {"R": _rand(80), "ViewLayer.Combined.G": _rand(81)})])
    assert sorted(read_exr(path).channels) == ["ViewLayer.Combined.G", "ViewLayer.Combined.R"]


def test_half_overflow_becomes_inf(tmp_path):
    a = np.array([[1e5, -1e5, 1.0]], np.float32)
    write_exr(tmp_path / "o.exr", {"Y": a}, half=True)
    got = read_exr(tmp_path / "o.exr").channels["Y"]
    assert got.dtype == np.float16
    assert np.isposinf(got[0, 0]) and np.isneginf(got[0, 1]) and got[0, 2] == 1.0


def test_image_size_reads_the_header_only(tmp_path):
    path = tmp_path / "size.exr"
    write_exr(path, {"R": np.zeros((3, 5), np.float32)})
    assert image_size(path) == (5, 3)
    with pytest.raises(ExrError, match="does not exist"):
        image_size(tmp_path / "missing.exr")
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(ExrError, match="bad.exr"):
        image_size(bad)
