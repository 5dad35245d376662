"""Tiled reblur equals whole-image reblur and the explicit per-pose blur."""

import numpy as np
import pytest
import zarr

from reblur import PoseGrid, reblur
from reblur.simulate import blur_weights, grid_path
from reblur.tiled import iter_tiles


def test_tiles_cover_image_once():
    cover = np.zeros((70, 95), int)
    for t in iter_tiles((70, 95), 32):
        cover[t.slices] += 1
    assert (cover == 1).all()


def test_tiled_equals_whole_and_explicit(levir_rgb):
    img = levir_rgb[:700, :900].astype(np.float32)
    grid = PoseGrid((700, 900), tx=np.arange(-6, 7), ty=np.arange(-6, 7),
                    rz=[-2.0, -1.0, 0.0, 1.0, 2.5])
    w = grid_path(grid, rng=1, n_poses=25)
    whole, vwhole = reblur(img, w, grid, tile_size=4096)
    tiled, vtiled = reblur(img, w, grid, tile_size=128, workers=2)
    np.testing.assert_array_equal(vwhole, vtiled)
    assert np.max(np.abs(whole - tiled)) < 1e-4
    # explicit: one full warp per pose (simulate.blur_weights), independent code path
    explicit, vexp = blur_weights(img, grid, w, dtype=np.float32)
    np.testing.assert_array_equal(vexp, vwhole)
    m = vwhole
    # OpenCV's warps compute coordinates in single precision (and bilinear weights on a
    # 1/32-px table), so a whole-image warp and a tile-local one differ by ~1e-4 at most
    d = np.abs(explicit - whole)[m]
    assert d.max() < 2e-3 and d.mean() < 1e-4
    # far corners rotate by radius x angle: the halo must follow; unknown only near borders
    assert m[200:500, 200:700].all()
    assert not m[0, 0]


def test_tiled_reads_from_zarr_and_writes_to_zarr(levir_gray, tmp_path):
    img = levir_gray[:512, :600].astype(np.float32)
    src = zarr.open_array(tmp_path / "ref.zarr", mode="w", shape=img.shape, chunks=(128, 128),
                          dtype="f4")
    src[:] = img
    grid = PoseGrid((512, 600), tx=np.arange(-3, 4), ty=np.arange(-3, 4), rz=[-1.0, 0.0, 1.0])
    w = grid_path(grid, rng=2, n_poses=12)
    out = zarr.open_array(tmp_path / "out.zarr", mode="w", shape=img.shape, chunks=(100, 100),
                          dtype="f4")
    valid = np.zeros(img.shape, bool)
    reblur(src, w, grid, tile_size=100, out=out, valid_out=valid)
    ref, vref = reblur(img, w, grid, tile_size=1000)
    np.testing.assert_array_equal(valid, vref)
    assert np.max(np.abs(out[:] - ref)) < 1e-4  # float32 warp coordinates, see above


def test_source_box_refuses_a_window_beyond_the_horizon():
    """A homography whose horizon line crosses the window has no bounded source region:
    a clear error, not a box made of NaN casts.  A plain shift gives the shifted box."""
    import pytest

    from reblur.warp import Box, source_box

    dst = Box(0, 0, 100, 100)
    b = source_box(np.array([[1.0, 0, 7], [0, 1, -3], [0, 0, 1]]), dst, pad=0)
    assert (b.y0, b.x0, b.h, b.w) == (3, -7, 100, 100)
    # the inverse maps w = 1 - x / 50: the line x = 50 crosses the window
    Hi = np.array([[1.0, 0, 0], [0, 1, 0], [-1 / 50, 0, 1]])
    with pytest.raises(ValueError, match="horizon"):
        source_box(np.linalg.inv(Hi), dst)
    # the same matrix, negated, is the same homography: still refused, and a negated
    # plain shift is still accepted
    with pytest.raises(ValueError, match="horizon"):
        source_box(-np.linalg.inv(Hi), dst)
    b2 = source_box(-np.array([[1.0, 0, 7], [0, 1, -3], [0, 0, 1]]), dst, pad=0)
    assert (b2.y0, b2.x0) == (3, -7)


def _reblur_tile_numpy(poses, reference, box):
    """The shifted-copy sums in numpy, over the whole tile (an earlier reblur_tile)."""
    from reblur.grid import translation
    from reblur.tiled import _shared_source
    from reblur.warp import as_box, source_box, warp_window

    box = as_box(box)
    C = reference.shape[2] if reference.ndim == 3 else 1
    out = np.zeros((box.h, box.w, C), np.float32)
    valid = np.ones((box.h, box.w), bool)
    warps = []
    for b, tw in poses.groups.items():
        if not poses.integer:
            warps += [(translation(tx, ty) @ poses.base_h[b], box, v) for tx, ty, v in tw]
            continue
        tx, ty = tw[:, 0].astype(int), tw[:, 1].astype(int)
        ext = box.grow(int(ty.max()), int(-ty.min()), int(tx.max()), int(-tx.min()))
        warps.append((poses.base_h[b], ext, (tx, ty, tw[:, 2])))
    source = _shared_source(reference, [source_box(H, dst) for H, dst, _ in warps], np.float32)
    tmp = np.empty_like(out)
    for H, dst, what in warps:
        img, ok = warp_window(reference, H, dst, dtype=np.float32, source=source)
        if not poses.integer:
            out += np.asarray(what, np.float32) * img
            valid &= ok
            continue
        tx, ty, wv = what
        for sx, sy, v in zip(tx, ty, wv, strict=True):
            oy, ox = ty.max() - sy, tx.max() - sx
            np.multiply(img[oy : oy + box.h, ox : ox + box.w], np.float32(v), out=tmp)
            out += tmp
            valid &= ok[oy : oy + box.h, ox : ox + box.w]
    return out, valid


def test_reblur_tile_equals_numpy_shifted_sums(levir_rgb):
    """OpenCV's in-place scaled sums (one pass per pose) give numpy's whole-tile products
    and sums up to float32 rounding (OpenCV may fuse the multiply-add), and the same
    validity, on interior, border and odd-sized boxes, one band and three."""
    import reblur.tiled as tiled

    img = levir_rgb[:300, :400].astype(np.float32)
    grid = PoseGrid((300, 400), tx=np.arange(-5, 6), ty=np.arange(-5, 6), rz=[-1.0, 0.0, 1.5])
    w = grid_path(grid, rng=3, n_poses=20)
    poses = tiled.SparsePoses(w, grid)
    assert poses.integer and poses.n_poses > len(poses.groups)
    boxes = [(0, 0, 300, 400), (0, 0, 97, 130), (120, 150, 101, 77), (250, 330, 50, 70)]
    for box in boxes:
        for ref in (img, img[:, :, 1]):
            out, valid = tiled.reblur_tile(poses, ref, box)
            eout, evalid = _reblur_tile_numpy(poses, ref, box)
            assert out.shape == eout.shape and out.dtype == np.float32
            np.testing.assert_allclose(out, eout, rtol=1e-6, atol=1e-6 * float(img.max()))
            np.testing.assert_array_equal(valid, evalid)
            if box[0] == 0:
                assert not valid.all()  # the border: the partial-validity path


def test_8bit_reference_is_warped_in_fixed_point_within_its_rounding(levir_rgb):
    """An 8-bit reference is warped as 16-bit values (times 256): each warp rounds to a
    256th of a level, so the tile is the float32 shifted sums (on the same values as
    floats) within half of that, summed over the weights; the validity is the same."""
    import reblur.tiled as tiled

    img = np.round(levir_rgb[:300, :400] * 255).astype(np.uint8)  # the PNG's values
    grid = PoseGrid((300, 400), tx=np.arange(-5, 6), ty=np.arange(-5, 6), rz=[-1.0, 0.0, 1.5])
    w = grid_path(grid, rng=4, n_poses=20)
    poses = tiled.SparsePoses(w, grid)
    bound = 0.5 / 256 * float(w.sum()) + 1e-4  # + float32 sums of values up to 255
    for box in [(0, 0, 300, 400), (120, 150, 101, 77)]:
        for ref in (img, img[:, :, 1]):
            assert tiled._fixed_point(ref, np.float32)
            out, valid = tiled.reblur_tile(poses, ref, box)
            eout, evalid = _reblur_tile_numpy(poses, ref.astype(np.float32), box)
            assert out.dtype == np.float32
            np.testing.assert_array_equal(valid, evalid)
            d = np.abs(out - eout)[valid]
            assert d.max() <= bound, d.max()
            assert d.mean() < 0.25 * bound  # rounding errors, not a bias
            # and the 16-bit path was taken: the float32 one stays within 5e-5 here
            assert d.max() > 2e-4, d.max()


def test_grow_tile_equals_loading_the_larger_window(levir_gray):
    """A re-run with a larger halo reuses the smaller window and loads only the ring: the
    same observation and unknown mask as loading the larger window directly, and the
    reblurred reference within OpenCV's window-dependent rounding."""
    from reblur.tiled import SparsePoses
    from reblur.tilejob import grow_tile, load_tile

    ref = levir_gray[:600, :640]
    rng = np.random.default_rng(3)
    obs = (ref.astype(np.float32) + rng.normal(0, 2, ref.shape)).clip(0, 255).astype(np.uint8)
    grid = PoseGrid((600, 640), tx=np.arange(-4, 5), ty=np.arange(-4, 5),
                    rz=[-1.5, 0.0, 1.0])
    poses = SparsePoses(grid_path(grid, rng=4, n_poses=10), grid, np.eye(3))
    kw = dict(s_ref=255.0, s_obs=255.0, gain=np.array([0.9], np.float32),
              offset=np.array([0.02], np.float32))
    small, large = (200, 220, 150, 170), (130, 0, 330, 400)  # the ring touches a border
    grown = grow_tile(poses, ref, obs, small, load_tile(poses, ref, obs, small, **kw), large,
                      **kw)
    direct = load_tile(poses, ref, obs, large, **kw)
    np.testing.assert_array_equal(grown[0], direct[0])
    np.testing.assert_array_equal(grown[2], direct[2])
    assert grown[2].any() and not grown[2].all()
    assert np.max(np.abs(grown[1] - direct[1])) < 1e-5
    with pytest.raises(ValueError, match="contain"):
        grow_tile(poses, ref, obs, large, direct, small, **kw)


def test_reblur_windows_equal_each_window_reblurred_alone(levir_gray):
    """Windows reblurred together on their span (a row of tie points, overlapping ones, a
    window on the border, one of another size) are each the window reblurred alone, with
    and without a displacement field: the same validity, and values within OpenCV's
    window-dependent rounding of its warp coordinates (the reference's range is 1)."""
    from reblur.align.field import DisplacementField
    from reblur.tiled import SparsePoses, reblur_tile, reblur_windows
    from reblur.warp import Box

    ref = levir_gray[:600, :640]
    grid = PoseGrid((600, 640), tx=np.arange(-4, 5), ty=np.arange(-4, 5),
                    rz=[-1.5, 0.0, 1.0])
    w = grid_path(grid, rng=5, n_poses=12)
    yy, xx = np.mgrid[0:11, 0:11].astype(np.float64)
    d = np.stack([1.2 * np.sin(xx / 3.0), -0.8 * np.cos(yy / 4.0)], axis=2)  # smooth, +-1 px
    fld = DisplacementField(0.0, 0.0, 64.0, d)
    boxes = [Box(0, 0, 64, 64), Box(0, 100, 64, 64), Box(0, 140, 64, 64),  # overlapping
             Box(0, 576, 64, 64), Box(300, 200, 90, 130)]
    for poses in (SparsePoses(w, grid), SparsePoses(w, grid, field=fld)):
        together = reblur_windows(poses, ref, boxes)
        assert len(together) == len(boxes)
        for b, (img, ok) in zip(boxes, together, strict=True):
            alone, ok_alone = reblur_tile(poses, ref, b)
            assert img.shape == alone.shape and img.dtype == alone.dtype
            np.testing.assert_array_equal(ok, ok_alone)
            assert np.max(np.abs(img - alone)) < 1e-5
        assert not together[0][1].all()  # the border window: the partial-validity path
    # the field moved the samples: the windows differ from the plain ones
    plain = reblur_windows(SparsePoses(w, grid), ref, boxes)
    moved = reblur_windows(SparsePoses(w, grid, field=fld), ref, boxes)
    assert np.max(np.abs(plain[4][0] - moved[4][0])) > 0.05


def test_windows_cut_from_the_whole_reblur_equal_their_own(levir_gray):
    """:func:`reblur.tiled.reblur_whole` (strips on two threads, a margin around the image)
    serves :func:`reblur.tiled.reblur_windows` the windows of its poses, with and without
    a displacement field, as each window reblurred alone: the same validity (a window on
    the border reads outside the reference), values within OpenCV's window-dependent
    rounding, read only.  Other poses, or a window beyond the margin, are reblurred on
    their own."""
    import copy

    import reblur.tiled as tiled
    from reblur.align.field import DisplacementField
    from reblur.tiled import SparsePoses, reblur_tile, reblur_whole, reblur_windows
    from reblur.warp import Box

    ref = levir_gray[:600, :640]
    grid = PoseGrid((600, 640), tx=np.arange(-4, 5), ty=np.arange(-4, 5),
                    rz=[-1.5, 0.0, 1.0])
    w = grid_path(grid, rng=5, n_poses=12)
    poses = SparsePoses(w, grid)
    whole = reblur_whole(poses, ref, (600, 640), margin=8, workers=2)
    assert whole.image.shape[:2] == whole.valid.shape == (616, 656)
    assert not whole.image.flags.writeable
    yy, xx = np.mgrid[0:11, 0:11].astype(np.float64)
    d = np.stack([1.2 * np.sin(xx / 3.0), -0.8 * np.cos(yy / 4.0)], axis=2)
    moved = copy.copy(poses)  # the field's check: the same poses, with a field
    moved.field = DisplacementField(0.0, 0.0, 64.0, d)
    boxes = [Box(0, 0, 64, 64), Box(0, 100, 64, 64), Box(0, 576, 64, 64),
             Box(300, 200, 90, 130)]
    calls = []
    real = tiled._reblur_poses

    def counted(p, reference, box, dtype):
        calls.append(box)
        return real(p, reference, box, dtype)

    for p in (poses, moved):
        want = [reblur_tile(p, ref, b) for b in boxes]
        tiled._reblur_poses = counted
        try:
            got = reblur_windows(p, ref, boxes, whole=whole)
        finally:
            tiled._reblur_poses = real
        assert calls == []  # every window from the whole reblur
        for (img, ok), (alone, ok_alone) in zip(got, want, strict=True):
            np.testing.assert_array_equal(ok, ok_alone)
            assert np.max(np.abs(img - alone)) < 1e-5
        assert not got[0][1].all()
    other = SparsePoses(w, grid)  # equal weights, another object: not served
    far = [Box(0, 0, 64, 64), Box(0, 630, 64, 20)]  # the span ends 10 px beyond the image
    for p, bs in ((other, boxes), (poses, far)):
        tiled._reblur_poses = counted
        try:
            reblur_windows(p, ref, bs, whole=whole)
        finally:
            tiled._reblur_poses = real
        assert len(calls) == 1
        calls.clear()
