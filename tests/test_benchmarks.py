"""The cost curve's arithmetic (``benchmarks/scale.py``): the affine split of the time and
the size-independent time a log-log slope allows, against closed forms."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import REPO

if str(REPO) not in sys.path:  # the benchmarks live beside src/, not in the package
    sys.path.insert(0, str(REPO))
from benchmarks.scale import _affine, _fixed_budget, _fixed_costs, _slope  # noqa: E402

SIZES = np.array([25.0, 100.0, 400.0, 1000.0])


def test_affine_fit_recovers_fixed_time_and_rate():
    F, b = _affine(SIZES, 3.7 + 0.081 * SIZES)
    assert F == pytest.approx(3.7, rel=1e-9)
    assert b == pytest.approx(0.081, rel=1e-9)


@pytest.mark.parametrize("slope", [0.7, 0.9, 0.95])
def test_fixed_budget_two_sizes_matches_the_closed_form(slope):
    # two sizes N1 < N2, r = N2 / N1: log((F + b N2) / (F + b N1)) / log(r) = s  gives
    # F = b (N2 - N1 r^s) / (r^s - 1)
    n1, n2, b = 25.0, 1000.0, 0.074
    rs = (n2 / n1) ** slope
    expected = b * (n2 - n1 * rs) / (rs - 1.0)
    assert _fixed_budget([n1, n2], b, slope) == pytest.approx(expected, rel=1e-9)


def test_fixed_budget_gives_the_slope_over_four_sizes():
    b = 0.074
    F = _fixed_budget(SIZES, b, 0.9)
    # an independent log-log fit of the affine times at that budget
    s = np.polyfit(np.log(SIZES), np.log(F + b * SIZES), 1)[0]
    assert s == pytest.approx(0.9, abs=1e-9)
    # more fixed time, a smaller slope; none, exactly linear
    assert _slope(SIZES, 2 * F + b * SIZES) < 0.9
    assert _slope(SIZES, b * SIZES) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError):
        _fixed_budget(SIZES, b, 1.0)
    with pytest.raises(ValueError):
        _fixed_budget(SIZES, 0.0, 0.9)


def test_fixed_costs_lines_report_the_split():
    b, F = 0.07, 4.0
    local = {}
    for mp in SIZES:
        tiles = b * mp
        local[int(mp)] = dict(
            mp=mp, time_s=F + tiles,
            timings=dict(align=1.5, photometry=0.1, estimate=1.6, refine=0.3),
            seconds=dict(fit=0.5, tiles=tiles))
    text = " ".join(_fixed_costs(local))
    assert "T = 4.0 s + 70 ms per MP, within 0 % of every row" in text
    # the slope of F + b N depends on F / b alone: the budget is b / (the rate for F = 1)
    assert f"leaves at most {b / _rate_for_slope(1.0, SIZES, 0.9):.1f} s" in text
    assert "tile pass alone (`seconds.tiles`) has slope 1.00" in text
    assert "would be 1.00" in text  # the rest is the tile pass alone: linear


def _rate_for_slope(F, sizes, slope):
    """The per-pixel rate b at which F + b N has log-log slope ``slope``: a bisection on
    b (the slope rises with b), independent of ``_fixed_budget``'s bisection on F."""
    lo, hi = 1e-9, 1e3
    for _ in range(200):
        mid = np.sqrt(lo * hi)
        s = np.polyfit(np.log(sizes), np.log(F + mid * sizes), 1)[0]
        lo, hi = (lo, mid) if s > slope else (mid, hi)
    return np.sqrt(lo * hi)


def test_fixed_costs_lines_state_what_both_targets_need():
    F, b = 4.4, 0.081
    local = {int(mp): dict(mp=mp, time_s=F + b * mp, timings={}, seconds={})
             for mp in SIZES}
    text = " ".join(_fixed_costs(local))
    need = _rate_for_slope(F, SIZES, 0.9)
    assert f"needs at least {1000 * need:.0f} ms per MP, {F + 1000 * need:.0f} s at 1 Gpx" in text
    # the largest fixed time for which the rate giving slope 0.9 keeps 1 Gpx within 240 s
    lo, hi = 0.0, 240.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mid + 1000 * _rate_for_slope(mid, SIZES, 0.9) < 240 else (lo, mid)
    assert f"allow at most {lo:.1f} s of it" in text
    # no gigapixel row, no statement about the 4-minute target
    small = {k: v for k, v in local.items() if k < 1000}
    assert "240 s" not in " ".join(_fixed_costs(small))


def test_fixed_costs_without_a_fixed_cost_only_state_the_fit():
    # time growing faster than the pixels: a negative intercept, no budget to speak of
    local = {int(mp): dict(mp=mp, time_s=-2.0 + 0.1 * mp, timings={}, seconds={})
             for mp in SIZES}
    text = " ".join(_fixed_costs(local))
    assert "T = -2.0 s + 100 ms per MP" in text
    assert "leaves at most" not in text


def test_cost_lattice_covers_the_asked_share_and_blocks_read_the_other_scene():
    from benchmarks.cost import _Blocks, _lattice

    shape = (1000, 1200)
    for frac, k in ((0.05, 4), (0.45, 1)):
        boxes = _lattice(shape, frac, k)
        area = sum((y1 - y0) * (x1 - x0) for y0, y1, x0, x1 in boxes)
        assert len(boxes) == k * k
        assert area / (shape[0] * shape[1]) == pytest.approx(frac, rel=0.02)
    base, other = np.zeros(shape), np.ones(shape)
    mixed = _Blocks(base, other, _lattice(shape, 0.45, 1))
    # read in two overlapping windows, the share of the other scene is the asked one
    top, bottom = mixed[0:500, 0:1200], mixed[500:1000, 0:1200]
    assert (top.sum() + bottom.sum()) / (1000 * 1200) == pytest.approx(0.45, rel=0.02)
    assert mixed[0:10, 0:10].sum() == 0 and mixed[495:505, 595:605].sum() == 100


def test_cost_targets_give_the_slope_against_the_decided_pixels():
    """Tile-pass seconds proportional to the pixels decided -- one tile without halo at
    1 MP, 1.3x the image with halos above: the slope against those pixels is 1, the one
    against MP holds the halos' step (computed here from the rows' own numbers)."""
    from benchmarks.cost import targets

    rows, mps, secs = [], [1, 25, 100], []
    for mp, factor, halo in ((1, 1, 1.0), (25, 5, 1.3), (100, 10, 1.3)):
        px = int((1024 * factor) ** 2 * halo)
        t = px * 4e-8
        secs.append(t)
        rows.append(dict(mp=mp, content="unchanged", seconds=3.0 + t,
                         stages={"report": 0.5, "reblur_decide": t + 0.1},
                         decide_seconds={"tiles": t}, tile_work={"pixels": px}))
    text = targets(rows)
    assert "slope 1.00; decided / image pixels 1.00 / 1.30 / 1.30" in text
    want = np.polyfit(np.log(mps), np.log(secs), 1)[0]
    assert f"log-log slope 0.9-1.1: {want:.2f} over 1, 25, 100 MP" in text
    assert 1.05 < want < 1.1


def test_cost_slope_counts_the_tiles_a_small_image_loads_ahead():
    """A small image's padded tiles are read and reblurred in the decision's fit
    (``seconds.preload``): the per-pixel stage is that plus the tile pass, so a 1 MP row
    whose tile pass read nothing does not bend the slope (computed here from the rows'
    own numbers)."""
    from benchmarks.cost import targets

    rows, mps, secs = [], [1, 25, 100], []
    for mp in mps:
        t = 0.12 * mp
        secs.append(t)
        dec = {"tiles": 0.1 * t, "preload": 0.9 * t} if mp == 1 else {"tiles": t, "preload": 0.0}
        rows.append(dict(mp=mp, content="unchanged", seconds=3.0 + t,
                         stages={"report": 0.5, "reblur_decide": t + 0.1},
                         decide_seconds=dec, tile_work={"pixels": mp * 2**20}))
    text = targets(rows)
    want = np.polyfit(np.log(mps), np.log(secs), 1)[0]
    assert f"log-log slope 0.9-1.1: {want:.2f} over 1, 25, 100 MP: met" in text


def test_cost_table_shows_the_time_outside_the_stages_and_targets_by_kind():
    """The seconds a run spends outside its stages (start-up, imports, exit) are its
    process time less the pipeline's total, the opening and the writing (by hand here);
    the 1 MP target lists each kind of pair apart."""
    from benchmarks.cost import table, targets

    def row(content, seconds):
        return dict(mp=1, content=content, seconds=seconds,
                    stages={"open": 0.1, "align": 0.5, "total": 2.0, "report": 0.3})

    rows = [row("unchanged", 3.0), row("real: GoPro GOPR0374", 6.0),
            row("shake: 20 px", 8.5), row("defocus", 9.0)]
    assert "| 1 MP | unchanged | 3.0 | 0.10 | 0.50 | - | - | - | - | - | 0.30 | 0.60 |" \
        in table(rows)
    text = targets(rows)
    assert "worst 9.0 s (defocus): NOT met" in text
    assert "real camera shake (GoPro, colour): 1 pairs, 6.0-6.0 s" in text
    assert "the issue's contents (one 6 px shake; aerial pairs years apart): 1 pairs, " \
        "3.0-3.0 s" in text
    assert "larger blurs (shakes of 6-35 px, a 1.5 degree tilt, defocus): 2 pairs, " \
        "8.5-9.0 s (worst: defocus)" in text


def test_window_side_boxes_are_the_windows_central_parts():
    """``benchmarks.window_side``: the ``--box`` of each window's central part, by hand;
    a window smaller than the side is left out (its part would not be smaller)."""
    from benchmarks.window_side import _centred

    wins = [[100, 700, 500, 500], [100, 200, 500, 500], [0, 0, 300, 300]]
    assert _centred(wins, 400) == ["150,750,400,400", "150,250,400,400"]
    assert _centred(wins, 256) == ["222,822,256,256", "222,322,256,256", "22,22,256,256"]
    # the part lies inside its window, centred to within a pixel
    for (y, x, h, w), b in zip(wins, _centred(wins, 255), strict=True):
        by, bx, bh, bw = map(int, b.split(","))
        assert y <= by and by + bh <= y + h and x <= bx and bx + bw <= x + w
        assert abs((by - y) - (y + h - by - bh)) <= 1


def test_gram_work_counts_a_warm_start_as_its_full_product(levir_gray):
    """A warm start on every pose of a small grid grows the Gram once, by all of them:
    one SYRK (numpy's ``X @ X.T`` of no old columns), P (P + 1) / 2 products over every
    pixel of the window (the dense path), over every other row with ``row_step=2``;
    stopped before any pose is added (``time_limit=0``).  The adjoint products are counted
    too."""
    import reblur.solve as S
    from benchmarks.gram_work import counted_blocks
    from reblur import PoseGrid
    from reblur.operator import BlurOperator
    from reblur.solve import active_set

    grid = PoseGrid(levir_gray.shape, tx=[-1, 0, 1], ty=[-1, 0, 1], rz=[0.0])
    box = (200, 300, 96, 80)
    op = BlurOperator(levir_gray, grid, box)
    g = op.matvec(np.full(grid.shape, 1.0 / grid.size)).reshape(op.dimsd)
    with counted_blocks() as counts:
        active_set([op], [g], w0=np.full(grid.shape, 1.0 / grid.size), time_limit=0.0)
    P = grid.size
    assert counts["macs"] == P * (P + 1) // 2 * 96 * 80 * op.dimsd[2]
    assert counts["copied"] == P * 96 * 80 * op.dimsd[2]
    assert counts["blocks"] >= 1
    # the adjoints: the KKT test's scale at w = 0, then the first outer iteration's
    # gradient (the time limit stops it there)
    assert counts["adjoints"] == 2 and counts["adjoint_cpu_s"] > 0
    # on every other row (row_step=2) the products are over the 48 rows fitted
    with counted_blocks() as half:
        active_set([op], [g], w0=np.full(grid.shape, 1.0 / grid.size), time_limit=0.0,
                   row_step=2)
    assert half["macs"] == P * (P + 1) // 2 * 48 * 80 * op.dimsd[2]
    assert S._Window._block.__name__ == "_block"  # restored
    assert BlurOperator.rmatvec.__name__ == "rmatvec"


def test_ab_scores_both_runs_on_the_pixels_both_left_known_and_unflagged():
    """``benchmarks.ab.score``: each run's PSNR over the pixels no run flagged or left
    unknown (one pixel value per run differs there: 10 log10(1 / (d^2 / n))), recall and
    false alarms against a truth."""
    from benchmarks.ab import score

    obs = np.full((4, 5, 1), 0.5)
    truth = np.zeros((4, 5), bool)
    truth[0, :2] = True
    runs = []
    for d, flag in ((0.1, (0, 0)), (0.2, (3, 4))):
        reb = obs.copy()
        reb[1, 1, 0] += d  # the only kept pixel that differs
        reb[0, 0, 0] += 0.9  # flagged by the first run: out of both scores
        changes = np.zeros((4, 5), bool)
        changes[flag] = True
        unknown = np.zeros((4, 5), bool)
        unknown[2, 2] = True
        runs.append({"seconds": 1.0, "changes": changes, "unknown": unknown,
                     "reblurred": reb})
    rows = score(runs, obs, truth)
    n = 20 - 3  # (0, 0), (3, 4) flagged, (2, 2) unknown
    for row, d in zip(rows, (0.1, 0.2), strict=True):
        assert row["psnr_db"] == pytest.approx(10 * np.log10(n / d**2))
        assert row["scored"] == pytest.approx(n / 20)
        assert "reblurred" not in row and row["seconds"] == 1.0
    assert rows[0]["recall"] == 0.5 and rows[0]["false_alarms"] == 0.0
    assert rows[1]["recall"] == 0.0 and rows[1]["false_alarms"] == pytest.approx(1 / 18)


def test_cores_section_keeps_this_run_and_the_saved_befores():
    """``benchmarks.cores``: the section shows this checkout's run, then every saved
    "before" run under its label; shares in percent, bytes as same / differ."""
    from benchmarks.cores import section

    row = {"pair": "p", "flagged_one": 0.01245, "flagged_all": 0.0125, "masks_same": False,
           "reblurred_same": True, "differing": 7}
    runs = {"now": {"label": "abc1234", "cpus": [0, 1, 2], "rows": [row]},
            "before": [{"label": "old", "cpus": [0, 1], "rows": [dict(row, masks_same=True)]}]}
    lines = section(runs).splitlines()
    assert lines[0] == "## One core against 3 (`python -m benchmarks.cores`, abc1234)"
    assert lines[4] == "| p | 1.245 % | 1.250 % | differ | same | 7 |"
    assert lines[6] == "Before (`python -m benchmarks.cores --src` a checkout of old):"
    assert lines[10] == "| p | 1.245 % | 1.250 % | same | same | 7 |"
