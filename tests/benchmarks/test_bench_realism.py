"""benchmarks/bench_realism.py: the statistics on arrays whose answer is known (luminance std, edge
density, histogram distances), the object readers on the real sample labels, the class figure's
targets, and the tables and --figures end to end at a tiny size (skipped without EGL)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench_realism as br

REALDATA = Path(__file__).resolve().parents[3] / "shared" / "realdata"


def grey(values: np.ndarray) -> np.ndarray:
    """An RGB image whose three channels hold `values` (so its luminance is `values`)."""
    return np.repeat(np.asarray(values, dtype=np.uint8)[..., None], 3, axis=2)


def test_luminance_uses_the_issue_weights():
    assert br.luminance(np.array([[[255, 0, 0]]], np.uint8))[0, 0] == pytest.approx(0.299 * 255)
    assert br.luminance(np.array([[[0, 255, 0]]], np.uint8))[0, 0] == pytest.approx(0.587 * 255)
    assert br.luminance(grey(np.full((2, 2), 100)))[0, 0] == pytest.approx(100.0)


def test_luminance_std_of_a_half_black_half_grey_frame_is_known():
    im = np.zeros((10, 20), np.uint8)
    im[:, 10:] = 200  # values 0 and 200 in equal parts: std exactly 100
    assert br.frame_stats(grey(im)).lum_std == pytest.approx(100.0)
    s = br.set_stats("x", [grey(im), grey(np.full((10, 20), 50))])
    assert s.lum_std == pytest.approx(50.0)  # the median of 100 and 0
    assert s.lum_std_per_frame == [100.0, 0.0]


def test_edge_density_counts_the_two_columns_beside_each_step():
    w = 64
    stripes = grey(np.tile(np.repeat(np.array([0, 255] * 4), 8), (32, 1)))  # 8 stripes of 8 px: 7 steps
    assert stripes.shape == (32, w, 3)
    assert br.edge_density(stripes) == pytest.approx(14 / w)
    assert br.edge_density(grey(np.full((32, w), 128))) == 0.0
    ramp = grey(np.tile(np.arange(w) * 3, (32, 1)))  # 3 grey levels a pixel: shading, not an edge
    assert br.edge_density(ramp) == 0.0
    # A step of s grey levels gives s/2 a pixel on both sides of it: the threshold (32) lies between 62 and 66.
    step = np.zeros((8, 16), np.uint8)
    step[:, 8:] = 66
    assert br.edge_density(grey(step)) == pytest.approx(2 / 16)
    step[:, 8:] = 62
    assert br.edge_density(grey(step)) == 0.0


def test_sobel_magnitude_of_a_horizontal_step():
    im = np.zeros((16, 8))
    im[8:] = 100.0
    m = br.sobel_magnitude(im)
    assert m[7] == pytest.approx(np.full(8, 50.0)) and m[8] == pytest.approx(np.full(8, 50.0))
    assert m[:7].max() == 0.0 and m[9:].max() == 0.0


def test_histogram_distances():
    black, white = grey(np.zeros((4, 4))), grey(np.full((4, 4), 255))
    a, b = br.frame_stats(black), br.frame_stats(white)
    assert a.hist_lum.sum() == pytest.approx(1.0)
    assert br.intersection(a.hist_lum, a.hist_lum) == pytest.approx(1.0)
    assert br.intersection(a.hist_lum, b.hist_lum) == 0.0
    assert br.emd(a.hist_lum, a.hist_lum) == 0.0
    assert br.emd(a.hist_lum, b.hist_lum) == pytest.approx((br.BINS - 1) * 256 / br.BINS)  # first bin to last
    d = br.compare(br.set_stats("a", [black]), br.set_stats("b", [white]))
    assert d["r_emd"] == d["lum_emd"] and d["rgb_intersection"] == 0.0


def test_bin_centres_lie_in_their_own_bins():
    c = br.bin_centres()
    assert len(c) == br.BINS and c[0] == pytest.approx(4.0) and c[-1] == pytest.approx(252.0)
    assert [int(np.argmax(br.histogram(v))) for v in c] == list(range(br.BINS))


def test_the_figure_shows_the_frame_nearest_the_median_std_and_the_json_rounds_it():
    half = np.zeros((10, 20), np.uint8)
    half[:, 10:] = 200  # std 100
    third = np.zeros((9, 20), np.uint8)
    third[:3] = 100  # std 100 * sqrt(2) / 3, not a round number
    s = br.set_stats("x", [grey(np.full((10, 20), 50)), grey(half), grey(third)])
    assert br.representative(s) == 2 and s.lum_std == s.lum_std_per_frame[2]
    assert s.to_dict()["lum_std_per_frame"] == [0.0, 100.0, round(100 * 2 ** 0.5 / 3, 3)]


def test_colourfulness_is_zero_for_grey_and_grows_with_colour():
    assert br.colourfulness(grey(np.random.default_rng(0).integers(0, 255, (8, 8)))) == pytest.approx(0.0)
    im = np.zeros((8, 8, 3), np.uint8)
    im[:4, :, 0] = 255  # half red, half blue
    im[4:, :, 2] = 255
    assert br.colourfulness(im) > 100


def _mix(cars, peds, extra=()):
    """One frame's class mix: cars of the given lengths, pedestrians of the given heights, and one
    object of each extra class."""
    from omnigen.rigs.class_mix import ClassMix

    mix = ClassMix()
    mix.add_frame(["car"] * len(cars) + ["pedestrian"] * len(peds) + list(extra),
                  [(l, 1.8, 1.5) for l in cars] + [(0.6, 0.6, h) for h in peds] + [(1.0, 1.0, 1.0)] * len(extra))
    return mix


def test_class_summary_meets_the_targets_only_when_all_hold():
    extra = ("van", "truck", "bus", "traffic_cone")
    ok = br.class_summary(_mix([4.0, 4.2, 4.6], [1.6, 1.9], extra), ["downtown"])
    assert ok["n_classes"] == 6 and ok["traffic_cone"] and ok["car_length_median"] == pytest.approx(4.2)
    assert ok["pedestrian_height_range"] == (1.6, 1.9) and ok["meets_targets"]
    assert not br.class_summary(_mix([4.0], [1.47, 1.9], extra), [])["meets_targets"]  # a short pedestrian
    assert not br.class_summary(_mix([5.0], [1.7], extra), [])["meets_targets"]  # long cars
    no_cones = br.class_summary(_mix([4.0], [1.7], ("van", "truck", "bus", "cyclist")), [])
    assert no_cones["n_classes"] == 6 and not no_cones["traffic_cone"] and not no_cones["meets_targets"]
    assert "traffic cones no" in br.class_line(no_cones)


@pytest.mark.skipif(not (REALDATA / "kitti").is_dir(), reason="no ../shared/realdata/kitti (real sample absent)")
def test_kitti_and_dair_labels_are_read_with_their_sizes_and_distances():
    k = br.kitti_objects(REALDATA / "kitti" / "training")
    assert sorted(k.values("car length").round(2)) == [3.69, 4.36]
    assert k.values("ped. height").tolist() == [1.89]
    # The pedestrian of 000000: bottom centre (1.84, 1.47, 8.41), h 1.89: centre 0.945 m higher.
    assert k.distance[0] == pytest.approx(np.linalg.norm([1.84, 1.47 - 0.945, 8.41]))
    d = br.dair_objects(br.dair_labels(REALDATA / "dair-v2x-c" / "infrastructure-side"))
    assert d.category.count("car") == 4 and d.category.count("motorcyclist") == 3
    assert d.category.count("traffic_cone") == 1  # 'Trafficcone', mixed case
    assert br.summary(d.values("ped. height"))["n"] == 0


def _egl_or_skip():
    pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")
    from omnigen.scenes import raster_backend
    from omnigen.scenes.generate import SceneGenerator

    try:
        raster_backend.RasterScene(SceneGenerator("tiny", 0).frame(0, 0))
    except Exception as exc:  # no headless GL here: say so rather than fail obscurely
        pytest.skip(f"headless EGL rendering unavailable: {exc}")


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_tables_and_figures_end_to_end_at_tiny_size(tmp_path, capsys):
    _egl_or_skip()
    work, out = tmp_path / "work", tmp_path / "realism.json"
    args = ["--frames", "2", "--size", "96", "--work", str(work), "--no-classes", "--scene", "tiny", "--cycles-frames", "0"]
    assert br.main(args + ["--realdata", str(tmp_path / "none"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "KITTI comparison skipped" in text and "DAIR-V2X comparison skipped" in text
    last = text.strip().splitlines()[-1]
    assert last.startswith("realism: ego lum std ") and "(>= 55)" in last and "drone lum std" in last
    res = json.loads(out.read_text())
    assert set(res["images"]) == {"ego", "pole", "drone"} and res["images"]["ego"]["frames"] == 2
    assert res["lum_std"]["ego"] > 0 and res["histogram_distances_to_kitti"] == {}
    assert f"{res['lum_std']['pole']:.1f}" in last
    image = next((work / "ego-2-96-s0-tiny" / "images").glob("*.png"))
    before = image.stat().st_mtime_ns

    if (REALDATA / "kitti").is_dir():  # the same renders again (reused), now against the real sample
        assert br.main(args + ["--realdata", str(REALDATA), "--out", str(out)]) == 0
        res = json.loads(out.read_text())
        assert image.stat().st_mtime_ns == before  # reused, not rendered again
        assert res["images"]["kitti"]["frames"] == 3
        assert 0 < res["histogram_distances_to_kitti"]["ego"]["lum_intersection"] <= 1
        assert res["objects"]["dair-v2x"]["car length"]["n"] == 4

    figs = tmp_path / "figs"
    assert br.main(["--frames", "2", "--size", "96", "--work", str(work), "--figures", str(figs),
                    "--realdata", str(REALDATA), "--scene", "tiny"]) == 0
    for name in ("realism-ego.png", "realism-pole.png"):
        assert 0 < (figs / name).stat().st_size < 400 * 1024
    assert image.stat().st_mtime_ns == before


def test_road_mask_keeps_background_pixels_on_the_ground_plane():
    """A level camera 1.5 m up over flat ground (plane n = (0, -1, 0), offset 1.5 in its frame):
    pixels below the horizon whose depth meets the ground are road; a kerb-high (0.15 m) point, an
    agent's pixel and the sky are not."""
    K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
    v = np.mgrid[0:48, 0:64][0].astype(np.float64)
    down = (v - 23.5) / 50.0
    depth = np.where(down > 0, 1.5 / np.where(down > 0, down, 1.0), np.inf)  # the ground's camera z
    instance = np.zeros((48, 64), np.uint16)
    instance[40:, :8] = 3
    depth[30, 10] = (1.5 - 0.15) / down[30, 10]  # a sidewalk's top
    mask = br.road_mask(depth, instance, K, (0.0, -1.0, 0.0), 1.5)
    assert mask[24:].sum() == 24 * 64 - 8 * 8 - 1 and not mask[:24].any()
    assert not mask[30, 10] and not mask[45, 3]


def test_ground_strip_is_the_lane_ahead():
    """KITTI's stand-in road: pixels whose ray meets the ground 5-20 m ahead, within 2 m of the axis."""
    K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 10.0], [0.0, 0.0, 1.0]])
    m = br.ground_strip(K, 101, 60, camera_height=1.65, ahead=(5.1, 20.0), half_width=2.0)
    # on the axis (column 50): rows 10 + 100 * 1.65 / d for d in [5.1, 20]: 18.25 .. 42.35
    assert np.nonzero(m[:, 50])[0].tolist() == list(range(19, 43))
    # row 26 meets the ground 1.65 / 0.16 = 10.3 m ahead, where +-2 m is +-19.4 px
    assert np.nonzero(m[26])[0].tolist() == list(range(31, 70))


def test_road_summary_counts_frames_in_kittis_range():
    r = br.road_summary([60.0, 90.0, 240.0], (78.6, 231.6))
    assert r["median"] == 90.0 and r["in_range"] == 1 and r["in_span"] and r["per_frame"] == [60.0, 90.0, 240.0]
    assert not br.road_summary([60.0, 70.0], (78.6, 231.6))["in_span"]
    assert br.road_summary([], None) == {"frames": 0, "per_frame": [], "median": None, "in_range": None, "in_span": None}
    line = br.road_line({"ego (cycles)": br.road_summary([250.0], (78.6, 231.6))}, (78.6, 231.6), ["ego (cycles)"])
    assert line == "realism: ego (cycles) road median 250.0 OUT of range (KITTI's road p10-p90 78.6-231.6)"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_cycles_rows_end_to_end_at_tiny_size(tmp_path, capsys):
    """The Cycles rows: one ego frame through `omnigen render --backend cycles`, its road median
    and seconds per frame printed, in the JSON, and the render reused on a second run."""
    pytest.importorskip("bpy", reason="bpy not installed")
    _egl_or_skip()
    work, out = tmp_path / "work", tmp_path / "realism.json"
    args = ["--frames", "1", "--size", "48", "--work", str(work), "--no-classes", "--scene", "tiny",
            "--cycles-frames", "1", "--cycles-size", "64", "--cycles-rigs", "ego", "--realdata", str(REALDATA), "--out", str(out)]
    assert br.main(args) == 0
    text = capsys.readouterr().out
    assert "cycles rows: 1 frames a rig at 64x64" in text and "ego (cycles)" in text
    res = json.loads(out.read_text())
    road = res["road_luminance"]
    assert road["sets"]["ego (cycles)"]["frames"] == 1 and road["cycles_seconds_per_frame"]["ego (cycles)"] > 0
    assert set(res["images"]) >= {"ego", "pole", "drone", "ego (cycles)"}
    if road["kitti_p10_p90"] is not None:
        lo, hi = road["kitti_p10_p90"]
        assert 0 < lo < hi <= 255 and "road median" in text.strip().splitlines()[-2]
    image = next((work / "cycles-ego-1-64-s0-tiny" / "images").glob("*.png"))
    before = image.stat().st_mtime_ns
    assert br.main(args) == 0
    assert image.stat().st_mtime_ns == before  # reused
