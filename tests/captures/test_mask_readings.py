"""Images and masks as phones and tools write them (issue 52): EXIF orientation honoured, mattes read from
an alpha channel (RGBA cut-outs, a white image with the matte in alpha), 0/1 label maps, 0/255 and grey
levels at 8 and 16 bits; each read is checked value for value against the mask that was written (a wrong
read fails), and a capture whose masks come in any of these encodings opens with the same masks."""

from __future__ import annotations

import io
import json
import shutil
import warnings

import numpy as np
import pytest
from PIL import Image

from _train_kit import make_tiny_dataset
from meshsplat.data import open_dataset
from meshsplat.errors import MeshsplatError, MeshsplatWarning
from meshsplat.io.images import image_size, read_image, read_mask

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

ENCODINGS = ("grey8", "binary255", "labels01", "grey16", "rgba_cutout", "white_alpha", "la", "rgb_grey")


def encode(mask: np.ndarray, encoding: str, rng: np.random.Generator) -> tuple[Image.Image, np.ndarray, str]:
    """``mask`` uint8 [H, W] written as ``encoding``: the PIL image, the float mask a correct read gives,
    and the reading it should report."""
    h, w = mask.shape
    exact = mask.astype(np.float32) / 255.0
    if encoding == "grey8":
        return Image.fromarray(mask, "L"), exact, "grey"
    if encoding == "binary255":
        b = np.where(mask >= 128, 255, 0).astype(np.uint8)
        return Image.fromarray(b, "L"), b / np.float32(255.0), "grey"
    if encoding == "labels01":
        lab = (mask >= 128).astype(np.uint8)
        return Image.fromarray(lab, "L"), lab.astype(np.float32), "labels"
    if encoding == "grey16":
        g = mask.astype(np.uint16) * 257
        return Image.fromarray(g), exact, "grey"
    if encoding == "rgba_cutout":  # the subject's colours where it is, anything where it is not
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        return Image.fromarray(np.dstack([rgb, mask]), "RGBA"), exact, "alpha"
    if encoding == "white_alpha":  # a white image whose alpha is the matte (read as all-white before)
        white = np.full((h, w, 3), 255, np.uint8)
        return Image.fromarray(np.dstack([white, mask]), "RGBA"), exact, "alpha"
    if encoding == "la":
        return Image.fromarray(np.dstack([np.full_like(mask, 255), mask]), "LA"), exact, "alpha"
    if encoding == "rgb_grey":  # a grey mask saved as RGB
        return Image.fromarray(np.repeat(mask[..., None], 3, -1), "RGB"), exact, "grey"
    raise AssertionError(encoding)


def _mask(draw_shape, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    h, w = draw_shape
    m = rng.integers(0, 256, (h, w), dtype=np.uint8)
    m[0, 0], m[-1, -1] = 0, 255  # both ends present: the alpha is never uniform, the labels never all 0
    return m


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    shape=st.tuples(st.integers(2, 24), st.integers(2, 24)),
    seed=st.integers(0, 2**31 - 1),
    encoding=st.sampled_from(ENCODINGS),
)
def test_every_mask_encoding_reads_back_the_values_written(tmp_path, shape, seed, encoding):
    mask = _mask(shape, seed)
    im, expected, reading = encode(mask, encoding, np.random.default_rng(seed))
    path = tmp_path / f"m_{encoding}.png"
    im.save(path)
    got, how = read_mask(path)
    assert how == reading
    assert got.dtype == np.float32 and got.shape == (*mask.shape, 1)
    np.testing.assert_allclose(got[..., 0], expected, rtol=0, atol=1e-6)


STORED = {  # EXIF orientation -> the pixels a camera stores for an upright image ``a`` [H, W, C]
    1: lambda a: a,
    2: lambda a: a[:, ::-1],  # mirrored
    3: lambda a: a[::-1, ::-1],  # upside down
    4: lambda a: a[::-1],  # flipped
    5: lambda a: np.transpose(a, (1, 0, 2)),  # transposed
    6: lambda a: np.rot90(a, 1),  # turned counter-clockwise: shown turned clockwise
    7: lambda a: np.transpose(a[::-1, ::-1], (1, 0, 2)),  # transposed across the other diagonal
    8: lambda a: np.rot90(a, -1),  # turned clockwise: shown turned counter-clockwise
}


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_turns_a_phone_photo_upright(tmp_path, orientation):
    h, w = 6, 10  # landscape upright: a portrait-stored file for orientations 5-8
    upright = np.zeros((h, w, 3), np.uint8)
    upright[0, 0] = (255, 0, 0)  # a red top-left corner
    upright[h - 1, :] = (0, 0, 255)  # a blue bottom row
    stored = np.ascontiguousarray(STORED[orientation](upright))
    exif = Image.Exif()
    exif[0x0112] = orientation
    path = tmp_path / f"o{orientation}.webp"  # lossless, with EXIF as a phone writes it
    Image.fromarray(stored).save(path, lossless=True, exif=exif.tobytes())
    assert image_size(path) == (w, h)
    got = read_image(path, 3)
    np.testing.assert_array_equal(got, upright)
    np.testing.assert_array_equal(read_image(path, 4)[..., :3], upright)


def test_a_phone_jpeg_mask_turns_with_its_image(tmp_path):
    mask = np.zeros((8, 16), np.uint8)
    mask[:, :4] = 255  # the left quarter upright
    exif = Image.Exif()
    exif[0x0112] = 6  # stored turned: the camera's usual portrait tag
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(np.rot90(mask, 1)), "L").save(buf, "JPEG", quality=100, exif=exif.tobytes())
    (tmp_path / "m.jpg").write_bytes(buf.getvalue())
    got, how = read_mask(tmp_path / "m.jpg")
    assert how == "grey" and got.shape == (8, 16, 1)
    assert got[:, :3].min() > 0.9 and got[:, 5:].max() < 0.1


@pytest.mark.parametrize("encoding", ["rgba_cutout", "white_alpha", "labels01"])
def test_a_capture_with_masks_in_any_encoding_opens_with_the_same_masks(tmp_path, encoding):
    root = make_tiny_dataset(tmp_path / "ref")
    ref = open_dataset(root)
    other = shutil.copytree(root, tmp_path / encoding)
    manifest = json.loads((other / "manifest.json").read_text())
    rng = np.random.default_rng(0)
    expected = []
    for rec in manifest["frames"]:
        mask = np.array(Image.open(other / rec["mask"]).convert("L"))
        if encoding == "labels01":
            mask = np.where(mask >= 128, 255, 0).astype(np.uint8)
        im, want, _ = encode(mask, encoding, rng)
        im.save(other / rec["mask"])
        expected.append(want)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = open_dataset(other)  # the camera check passes: these masks are right
        masks = [ds[i].mask for i in range(len(ds))]
    notes = {str(w.message) for w in caught if issubclass(w.category, MeshsplatWarning)}
    assert any("masks read from" in n for n in notes), notes
    for i, m in enumerate(masks):
        np.testing.assert_allclose(m[..., 0].numpy(), expected[i], atol=1e-6)
        if encoding != "labels01":
            np.testing.assert_allclose(m.numpy(), ref[i].mask.numpy(), atol=1e-6)


def test_inverted_masks_are_named_as_such_not_as_a_wrong_camera(tmp_path):
    root = make_tiny_dataset(tmp_path / "ref")
    inverted = shutil.copytree(root, tmp_path / "inverted")
    manifest = json.loads((inverted / "manifest.json").read_text())
    for rec in manifest["frames"]:
        m = np.array(Image.open(inverted / rec["mask"]).convert("L"))
        Image.fromarray(255 - m).save(inverted / rec["mask"])
    with pytest.raises(MeshsplatError) as info:
        open_dataset(inverted)
    text = str(info.value)
    assert "masks of camera 'cam0' look inverted on 6 of 6 frames" in text and "invert them" in text, text
    assert "does not see the subject" not in text
    open_dataset(root)  # the right masks pass


def test_one_inverted_mask_is_a_bad_frame_named_as_inverted(tmp_path):
    root = shutil.copytree(make_tiny_dataset(tmp_path / "ref"), tmp_path / "one")
    rec = json.loads((root / "manifest.json").read_text())["frames"][2]
    m = np.array(Image.open(root / rec["mask"]).convert("L"))
    Image.fromarray(255 - m).save(root / rec["mask"])
    with pytest.raises(MeshsplatError, match=r"the mask looks inverted") as info:
        open_dataset(root)
    assert rec["image"] in str(info.value) or rec["name"] in str(info.value)
