"""eval/detail.py: the error split by the reference's detail, its broad colour, and the best pixel shift."""

import numpy as np
import pytest

from eligsir_o3d.eval.detail import best_shift, detail_split


def _texture(h=96, w=128, seed=0):
    """A reference with flat regions and sharp texture: smooth colour ramps plus a checker patch."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([x / w, y / h, 0.5 + 0.2 * np.sin(x / 17.0)], -1) * 0.6 + 0.2
    checker = ((x // 3 + y // 3) % 2).astype(np.float32)
    patch = (slice(20, 60), slice(30, 90))
    img[patch] = (0.15 + 0.7 * checker[patch])[..., None] * np.array([0.9, 0.8, 0.7], np.float32)
    return np.clip(img + rng.normal(0, 0.002, img.shape).astype(np.float32), 0, 1)


def test_a_blurred_render_loses_on_detail_and_not_in_broad_colour():
    import cv2

    ref = _texture()
    blurred = cv2.GaussianBlur(ref, (0, 0), 2.0)
    d = detail_split(blurred, ref)
    assert d["detail_pixels"] == round(0.2 * ref.shape[0] * ref.shape[1])
    assert d["detail"] < d["flat"] - 6.0  # blur costs the edges and the checker, not the ramps
    assert d["lowpass"] > d["detail"] + 15.0  # after a common blur the two agree


def test_a_colour_offset_costs_detail_flat_and_broad_colour_alike():
    ref = _texture()
    d = detail_split(np.clip(ref + 0.05, 0, 1), ref)
    want = -10 * np.log10(0.05 ** 2)  # 26.02 dB where nothing clips
    for k in ("detail", "flat", "lowpass"):
        assert d[k] == pytest.approx(want, abs=0.6), k


def test_the_mask_chooses_the_pixels_and_an_empty_mask_gives_nan():
    ref = _texture()
    pred = ref.copy()
    pred[:, :64] = 0.0  # the left half is wrong
    right = np.zeros(ref.shape[:2], bool)
    right[:, 64:] = True
    assert detail_split(pred, ref, right)["flat"] == pytest.approx(120.0)  # capped: perfect where it counts
    empty = detail_split(pred, ref, np.zeros_like(right))
    assert np.isnan(empty["detail"]) and empty["detail_pixels"] == 0


@pytest.mark.parametrize("dx,dy", [(0, 0), (3, -5), (-7, 2), (12, 12), (-1, 11)])
def test_best_shift_finds_the_shift_of_a_moved_render(dx, dy):
    ref = _texture(seed=1)
    pred = np.roll(np.roll(ref, dy, 0), dx, 1)  # the render moved by (dx, dy): shifting it back matches
    s = best_shift(pred, ref)
    assert (s["dx"], s["dy"]) == (-dx, -dy)
    assert s["psnr"] == pytest.approx(120.0)
    assert (dx, dy) == (0, 0) or s["psnr_unshifted"] < 30.0


def test_bad_inputs_name_the_problem():
    ref = _texture()
    with pytest.raises(ValueError, match="pred"):
        detail_split(ref[..., 0], ref)
    with pytest.raises(ValueError, match="differ in shape"):
        best_shift(ref[:50], ref)
    with pytest.raises(ValueError, match="mask"):
        detail_split(ref, ref, np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="radius"):
        best_shift(ref, ref, radius=60)
    with pytest.raises(ValueError, match="detail_share"):
        detail_split(ref, ref, detail_share=1.0)


def test_holes_that_move_with_the_render_do_not_anchor_its_shift():
    """A render with holes (a TSDF's unobserved pixels, black): without ``valid`` a shift is charged for the black
    pixels it moves into the mask, which pins the render in place; with it the true shift is found."""
    ref = _texture(seed=2)
    pred = np.roll(ref, 3, 1)  # the render sits 3 px right of the reference
    holes = np.zeros(ref.shape[:2], bool)
    holes[10:90:8, 15:120] = True  # thin rows of holes, as a TSDF's cracks
    holes[:, 40:44] = True
    pred[holes] = 0.0
    s = best_shift(pred, ref, valid=~holes)
    assert (s["dx"], s["dy"]) == (-3, 0)
    assert s["psnr"] == pytest.approx(120.0)
