"""Map files (validation, spatial queries) and the warehouse map generator."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tagloc.cli import main
from tagloc.core.errors import InputError, MapError
from tagloc.core.stickermap import StickerMap, load_map, save_map
from tagloc.sim.mapgen import GridMapConfig, grid_map, summarise_map, write_grid_map

HEADER = "id,x_m,y_m,yaw_deg\n"
GOOD_ROW = "7,10.0,10.0,0\n"  # line 2 of every case below; the bad row is line 3


def _write(tmp_path, text: str, name: str = "m.csv"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize(
    "row, fragment",
    [
        ("1,0.0,0.0\n", "3 columns"),
        ("1,0,0,0,5\n", "5 columns"),
        ("1,abc,0,0\n", "x_m 'abc' is not a number"),
        ("1,nan,0,0\n", "finite"),
        ("1,0,inf,0\n", "finite"),
        ("1,0,0,-inf\n", "finite"),
        ("7,5,5,0\n", "duplicate id 7"),
        ("-1,0,0,0\n", "not an integer in 0-99999"),
        ("100000,0,0,0\n", "not an integer in 0-99999"),
        ("1.5,0,0,0\n", "not an integer in 0-99999"),
        ("x,0,0,0\n", "id 'x' is not a number"),
        ("8,10.05,10.0,0\n", "closer than 0.100 m"),
        ("8,10.0,10.099,45\n", "closer than 0.100 m"),
    ],
)
def test_bad_row_refused_naming_file_and_line(tmp_path, row, fragment):
    p = _write(tmp_path, HEADER + GOOD_ROW + row)
    with pytest.raises(MapError) as info:
        load_map(p)
    msg = str(info.value)
    assert msg.startswith(f"{p}:3:")
    assert fragment in msg
    assert "\n" not in msg


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("", "empty file"),
        ("id,x,y,yaw\n" + GOOD_ROW, ":1: header"),
        ("x_m,id,y_m,yaw_deg\n" + GOOD_ROW, ":1: header"),
        (GOOD_ROW, ":1: header"),
        (HEADER, "no stickers"),
        (HEADER + "\n\n", "no stickers"),
    ],
)
def test_bad_file_refused(tmp_path, text, fragment):
    p = _write(tmp_path, text)
    with pytest.raises(MapError) as info:
        load_map(p)
    assert str(info.value).startswith(str(p)) and fragment in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_and_binary_files_refused(tmp_path):
    with pytest.raises(MapError, match="cannot read"):
        load_map(tmp_path / "absent.csv")
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(MapError, match="UTF-8"):
        load_map(binary)


def test_good_map_loads(tmp_path):
    p = _write(tmp_path, HEADER + GOOD_ROW + " 99999 , -1.5 , 2.25 , 90 \n\n0,0,0,-45.5\n")
    m = load_map(p)
    assert list(m.ids) == [7, 99999, 0]
    assert m.xy == pytest.approx(np.array([[10, 10], [-1.5, 2.25], [0, 0]]))
    assert m.yaw == pytest.approx(np.radians([0, 90, -45.5]))
    assert 99999 in m and 8 not in m and m.row(0) == 2
    T = m.T_world_sticker(99999)
    assert T[:3, 3] == pytest.approx((-1.5, 2.25, 0)) and T[:2, 0] == pytest.approx((0, 1), abs=1e-12)
    save_map(m, tmp_path / "again.csv")
    m2 = load_map(tmp_path / "again.csv")
    assert np.array_equal(m2.ids, m.ids) and m2.xy == pytest.approx(m.xy) and m2.yaw == pytest.approx(m.yaw)


def _random_map(rng, n=3000, size=60.0) -> StickerMap:
    return StickerMap(rng.choice(100000, n, replace=False), rng.uniform(0, size, (n, 2)), rng.uniform(0, 6.28, n))


def test_within_matches_brute_force(rng):
    m = _random_map(rng)
    for _ in range(50):
        x, y = rng.uniform(-5, 65, 2)
        r = rng.uniform(0.1, 6.0)
        got = m.within(x, y, r)
        d = np.hypot(m.xy[:, 0] - x, m.xy[:, 1] - y)
        assert set(got.tolist()) == set(np.flatnonzero(d <= r).tolist())
        assert np.all(np.diff(d[got]) >= 0)  # nearest first
    assert len(m.within(-100, -100, 1.0)) == 0


def test_in_polygon_matches_brute_force(rng):
    m = _random_map(rng)
    star = [
        (
            30 + (20 if k % 2 == 0 else 7) * math.cos(k * math.pi / 5),
            30 + (20 if k % 2 == 0 else 7) * math.sin(k * math.pi / 5),
        )
        for k in range(10)
    ]
    sliver = [(1, 1), (59, 3), (2, 4)]  # long, thin: vertex mean far from the tip
    for _ in range(20):
        box = rng.uniform(0, 60, (2, 2))
        (x0, x1), (y0, y1) = np.sort(box[:, 0]), np.sort(box[:, 1])
        rect = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        for poly in (rect, star, sliver):
            contour = np.asarray(poly, np.float32).reshape(-1, 1, 2)
            truth = [
                k for k, (x, y) in enumerate(m.xy) if cv2.pointPolygonTest(contour, (float(x), float(y)), False) > 0
            ]
            assert m.in_polygon(np.asarray(poly)).tolist() == truth
    assert len(m.in_polygon(np.array([(100, 100), (101, 100), (101, 101)]))) == 0


# --- generator -------------------------------------------------------------------------------------


def test_grid_map_is_warehouse_like():
    c = GridMapConfig()
    m = grid_map(c)
    assert 150 < len(m) < 400
    assert len(set(m.ids.tolist())) == len(m) and m.ids.min() >= 0 and m.ids.max() <= 99999
    assert m.ids.max() - m.ids.min() > 10 * len(m)  # random IDs, not a run
    x0, y0, x1, y1 = m.bounds
    assert x0 >= c.margin_m - c.jitter_m and x1 <= c.width_m - c.margin_m + c.jitter_m
    assert y0 >= c.margin_m - c.jitter_m and y1 <= c.depth_m - c.margin_m + c.jitter_m
    aisle_x = np.arange(2.0, 38.01, 3.0)  # 13 aisles centred in 40 m
    on_aisle = np.abs(m.xy[:, 0, None] - aisle_x[None]).min(axis=1) <= c.jitter_m + 1e-9
    for ax in aisle_x:
        ys = np.sort(m.xy[np.abs(m.xy[:, 0] - ax) <= c.jitter_m + 1e-9, 1])
        assert len(ys) >= 10
        gaps = np.diff(ys)
        assert gaps.min() >= c.spacing_min_m - 1e-9 and gaps.max() <= c.spacing_max_m + 1e-9
    assert (~on_aisle).sum() >= 20  # cross-aisle stickers exist
    info = summarise_map(m)
    assert info.nn_min >= c.spacing_min_m - 1e-9
    assert info.nn_max <= c.spacing_max_m + 2 * c.jitter_m
    # Yaws cover the circle evenly.
    counts = np.histogram(m.yaw, bins=4, range=(0, 2 * np.pi))[0]
    assert m.yaw.min() >= 0 and m.yaw.max() < 2 * np.pi and counts.min() > 0.15 * len(m)


def test_grid_map_deterministic_and_seeded():
    a, b = grid_map(GridMapConfig(seed=3)), grid_map(GridMapConfig(seed=3))
    assert np.array_equal(a.ids, b.ids) and np.array_equal(a.xy, b.xy) and np.array_equal(a.yaw, b.yaw)
    c = grid_map(GridMapConfig(seed=4))
    assert not (len(a) == len(c) and np.allclose(a.xy, c.xy))


def test_grid_map_sequential_ids_and_small_floor(tmp_path):
    c = GridMapConfig(width_m=8, depth_m=6, cross_aisles=1, ids="sequential", first_id=500, seed=1)
    info = write_grid_map(c, tmp_path / "small.csv")  # reloaded through full validation
    m = load_map(tmp_path / "small.csv")
    assert info.count == len(m) > 5
    assert m.ids.tolist() == list(range(500, 500 + len(m)))


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"spacing_min_m": 2.5}, "spacing-min"),
        ({"spacing_min_m": 0.05, "spacing_max_m": 0.5}, "spacing-min"),
        ({"jitter_m": -0.1}, "jitter"),
        ({"width_m": 1.5}, "margin"),
        ({"aisle_spacing_m": 0.5}, "aisle spacing"),
        ({"cross_aisles": 40}, "cross aisles"),
        ({"ids": "sequential", "first_id": 99990}, "beyond"),
        ({"ids": "shuffled"}, "ids"),
    ],
)
def test_grid_map_refuses_bad_config(kwargs, fragment):
    with pytest.raises(InputError, match=fragment):
        grid_map(GridMapConfig(**kwargs))


def test_demo_map_is_the_documented_grid(demo_map_path):
    demo = load_map(demo_map_path)
    ref = grid_map(
        GridMapConfig(
            width_m=40, depth_m=25, aisle_spacing_m=3.0, spacing_min_m=1.2, spacing_max_m=2.0, jitter_m=0.05, seed=7
        )
    )
    assert np.array_equal(demo.ids, ref.ids)
    assert demo.xy == pytest.approx(ref.xy, abs=1e-4)
    assert demo.yaw == pytest.approx(ref.yaw, abs=1e-4)
    info = summarise_map(demo)
    assert info.nn_max < 2.0 and info.bounds[2] - info.bounds[0] > 35 and info.bounds[3] - info.bounds[1] > 20


def test_summarise_map_numbers():
    info = summarise_map(StickerMap([1, 2, 3], [[0, 0], [1, 0], [3, 0]], [0, 0, 0]))
    assert (info.count, info.id_min, info.id_max) == (3, 1, 3)
    assert info.bounds == (0, 0, 3, 0)
    assert (info.nn_min, info.nn_median, info.nn_mean, info.nn_max) == pytest.approx((1, 1, 4 / 3, 2))


def test_cli_map_grid_and_info(tmp_path, capsys):
    out = tmp_path / "g.csv"
    assert main(["map", "grid", "-o", str(out), "--width", "12", "--depth", "9", "--seed", "3"]) == 0
    n = len(load_map(out))
    assert main(["map", "info", str(out)]) == 0
    assert f"{n} stickers" in capsys.readouterr().out
    assert main(["map", "grid", "-o", str(out), "--spacing-min", "3", "--spacing-max", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "spacing-min" in err and len(err.splitlines()) == 1
    bad = _write(tmp_path, HEADER + "1,0,0\n", "bad.csv")
    assert main(["map", "info", str(bad)]) == 2
    assert f"{bad}:2:" in capsys.readouterr().err


def test_survey_sigma_columns_round_trip(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("id,x_m,y_m,yaw_deg,sigma_m,sigma_deg\n1,0,0,0,0.02,1.5\n2,1,0,90,,\n")
    smap = load_map(path)
    assert smap.sigma_xy[0] == pytest.approx(0.02) and smap.sigma_yaw[0] == pytest.approx(math.radians(1.5))
    assert np.isnan(smap.sigma_xy[1]) and np.isnan(smap.sigma_yaw[1])  # empty cells: not stated
    save_map(smap, tmp_path / "again.csv")
    again = load_map(tmp_path / "again.csv")
    np.testing.assert_allclose(again.sigma_xy, smap.sigma_xy)
    np.testing.assert_allclose(again.sigma_yaw, smap.sigma_yaw)
    # One column alone, the other left to the default.
    (tmp_path / "deg.csv").write_text("id,x_m,y_m,yaw_deg,sigma_deg\n1,0,0,0,2\n")
    one = load_map(tmp_path / "deg.csv")
    assert np.isnan(one.sigma_xy[0]) and one.sigma_yaw[0] == pytest.approx(math.radians(2))
    # A map without them writes the plain four-column header.
    save_map(load_map(tmp_path / "deg.csv"), tmp_path / "deg2.csv")
    assert (tmp_path / "deg2.csv").read_text().startswith("id,x_m,y_m,yaw_deg,sigma_m,sigma_deg\n")
    plain = StickerMap([1], [[0.0, 0.0]], [0.0])
    save_map(plain, tmp_path / "plain.csv")
    assert (tmp_path / "plain.csv").read_text().splitlines()[0] == "id,x_m,y_m,yaw_deg"


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("id,x_m,y_m,yaw_deg,sigma_m\n1,0,0,0,-0.01\n", "m.csv:2: sigma_m '-0.01' is negative"),
        ("id,x_m,y_m,yaw_deg,sigma_m\n1,0,0,0,abc\n", "m.csv:2: sigma_m 'abc' is not a number"),
        ("id,x_m,y_m,yaw_deg,sigma_m\n1,0,0,0,1e300\n", "m.csv:2: sigma_m '1e300' is more than 10"),
        ("id,x_m,y_m,yaw_deg,sigma_deg\n1,0,0,0,200\n", "m.csv:2: sigma_deg '200' is more than 180"),
        ("id,x_m,y_m,yaw_deg,colour\n1,0,0,0,red\n", "m.csv:1: header"),
        ("id,x_m,y_m,yaw_deg,sigma_m,sigma_m\n1,0,0,0,1,1\n", "m.csv:1: header"),
    ],
)
def test_bad_sigma_columns_refused(tmp_path, text, fragment):
    (tmp_path / "m.csv").write_text(text)
    with pytest.raises(MapError, match=fragment.replace("(", r"\(").replace(")", r"\)")):
        load_map(tmp_path / "m.csv")


def test_map_with_byte_order_mark_loads(tmp_path):
    (tmp_path / "bom.csv").write_bytes("\ufeffid,x_m,y_m,yaw_deg\n5,1.0,2.0,30\n".encode())
    smap = load_map(tmp_path / "bom.csv")
    assert smap.ids.tolist() == [5] and smap.yaw[0] == pytest.approx(math.radians(30))


def test_saved_sigmas_are_never_sharper_than_stated(tmp_path):
    """A sigma is written rounded up to the map's steps: rounded to nearest, one under 0.05 mm came
    back as 0 (an exact map), a yaw sigma under 0.0005 deg too."""
    sig_m = np.array([0.00003, 0.015, 0.01234567, 0.0])
    sig_deg = np.array([0.0004, 1.5, 0.2601, 0.0])
    smap = StickerMap(
        np.array([1, 2, 3, 4]),
        np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]),
        np.zeros(4),
        sigma_xy=sig_m,
        sigma_yaw=np.radians(sig_deg),
    )
    save_map(smap, tmp_path / "m.csv")
    back = load_map(tmp_path / "m.csv")
    assert np.all(back.sigma_xy >= sig_m) and np.all(np.degrees(back.sigma_yaw) >= sig_deg - 1e-12)
    np.testing.assert_allclose(back.sigma_xy, [0.0001, 0.015, 0.0124, 0.0])
    np.testing.assert_allclose(np.degrees(back.sigma_yaw), [0.001, 1.5, 0.261, 0.0], atol=1e-12)
    assert not math.isnan(back.sigma_xy[3])
