"""`omnigen stats`: the numbers match an independent count of the records, health catches what was
planted, the page shows only numbers from stats.json, and a browser renders it."""

from __future__ import annotations

import html.parser
import json
import math
import os
import re
import shutil
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from omnigen.cli import main
from omnigen.conventions import FINE_CLASSES
from omnigen.dataset import Dataset
from omnigen.fakes import random_frame, write_fake_dataset
from omnigen.camera import intrinsics_from_fov
from omnigen.geometry import Box3D, plane_from_height_pitch, rot_x, rot_z
from omnigen.priors import FAR_SIGMA, PRIORS, far_outside_prior
from omnigen.record import ObjectRecord
from omnigen.stats.compute import compute_stats, derive, ground_coordinates
from omnigen.stats.report import render_page, write_report
from omnigen.writer import DatasetWriter

W, H = 160, 96
KINDS = [("synthetic", "ego"), ("synthetic", "infrastructure"), ("synthetic", "aerial"),
         ("kitti", "ego"), ("dair-v2x-i", "infrastructure")]
EMPTY_FRAME = "kitti-000900"
UNREADABLE = "synthetic-000002"
WRONG_SIZE = "kitti-000003"


def _edge_on_bus(frame_id: str) -> "object":
    """An ego frame whose only object, a bus 3 m ahead seen side-on, has every corner outside the image."""
    K = intrinsics_from_fov(math.radians(60), W, H)
    box = Box3D([0.0, 0.3, 3.0], [11.0, 2.6, 3.2], np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) @ rot_z(0.0))
    rec = random_frame(5, 901, "kitti", "ego", n_objects=0, width=W, height=H)
    rec.frame_id, rec.image = frame_id, f"images/{frame_id}.png"
    rec.K = K
    rec.objects = [ObjectRecord.from_box("bus", 1, box, K, W, H, occlusion_level=0)]
    assert not rec.objects[0].in_image.any()
    return rec


def build_dataset(root: Path, frames: int = 25) -> Path:
    """Five kinds of camera, with planted problems: an empty frame, an all-outside object, a sliver
    of a 2D box, a car labelled traffic cone, an image that is not an image, one of the wrong size."""
    writer = DatasetWriter(root, durable=False)
    (root / "images").mkdir(parents=True)
    records = []
    for k in range(frames):
        source, view = KINDS[k % len(KINDS)]
        records.append(random_frame(3, k, source, view, n_objects=1 + k % 5, width=W, height=H))
    records.append(random_frame(3, 900, "kitti", "ego", n_objects=0, width=W, height=H))
    records.append(_edge_on_bus("kitti-000901"))
    sliver = records[6].objects[0]
    sliver.bbox = np.array([sliver.bbox[0], sliver.bbox[1], sliver.bbox[0] + 0.4, sliver.bbox[3]])
    relabel = next(o for r in records[7:] for o in r.objects if o.category in ("car", "van", "truck", "bus", "tram"))
    relabel.category = "traffic_cone"
    for rec in records:
        size = (W + 10, H) if rec.frame_id == WRONG_SIZE else (W, H)
        if rec.frame_id == UNREADABLE:
            (root / rec.image).write_bytes(b"this is not a PNG")
        else:
            Image.new("RGB", size, (40, 60, 80)).save(root / rec.image)
        if rec.synthetic is not None:
            for rel in (rec.synthetic.depth, rec.synthetic.instance):
                (root / rel).parent.mkdir(exist_ok=True)
                (root / rel).write_bytes(b"placeholder")
        writer.write(rec)
    writer.finalize({"name": "stats-test"}, show_progress=False)
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return build_dataset(tmp_path_factory.mktemp("stats") / "ds")


@pytest.fixture(scope="module")
def raw(dataset) -> list[dict]:
    """The records as JSON, read without omnigen: the independent side of every comparison."""
    return [json.loads(p.read_text()) for p in sorted((dataset / "records").glob("*.json"))]


@pytest.fixture(scope="module")
def report(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "report"
    r = write_report(Dataset.open(dataset, show_progress=False), out, gallery=3, jobs=1, show_progress=False)
    return r


# ---------------------------------------------------------------------------------------------
# The numbers
# ---------------------------------------------------------------------------------------------


def _objects(raw, pred=lambda f: True):
    return [o for f in raw if pred(f) for o in f["objects"]]


def test_counts_match_the_records(report, raw):
    s = report.stats
    assert s["overall"]["frames"] == len(raw)
    assert s["overall"]["objects"] == sum(len(f["objects"]) for f in raw)
    by_class = Counter(o["category"] for o in _objects(raw))
    assert s["overall"]["classes"] == {c: by_class.get(c, 0) for c in FINE_CLASSES}
    holding = Counter(c for f in raw for c in {o["category"] for o in f["objects"]})
    assert s["overall"]["class_frames"] == {c: holding.get(c, 0) for c in FINE_CLASSES}
    for key, part in (("source", "by_source"), ("view", "by_view")):
        groups = Counter(f[key] for f in raw)
        assert {g: sec["frames"] for g, sec in s[part].items()} == dict(groups)
        for g, sec in s[part].items():
            objs = _objects(raw, lambda f: f[key] == g)
            assert sec["objects"] == len(objs)
            assert sec["classes"] == {c: Counter(o["category"] for o in objs).get(c, 0) for c in FINE_CLASSES}
    per_frame = Counter(len(f["objects"]) for f in raw)
    assert s["overall"]["objects_per_frame"]["counts"] == [per_frame.get(n, 0) for n in range(max(per_frame) + 1)]
    assert s["overall"]["ignore_regions"] == sum(len(f["ignore_regions"]) for f in raw)


def test_corners_occlusion_and_truncation_match(report, raw):
    sec = report.stats["by_source"]["kitti"]
    objs = _objects(raw, lambda f: f["source"] == "kitti")
    in_image = np.array([o["in_image"] for o in objs])
    occluded = np.array([o["occluded"] for o in objs])
    behind = np.array([o["behind_camera"] for o in objs])
    assert sec["corners"]["counts"]["in_image"] == in_image.sum(0).tolist()
    assert sec["corners"]["counts"]["occluded_in_image"] == (in_image & occluded).sum(0).tolist()
    assert sec["corners"]["counts"]["behind_camera"] == behind.sum(0).tolist()
    levels = Counter(o["occlusion_level"] for o in objs)
    assert list(sec["occlusion"]["levels"].values()) == [levels.get(k, 0) for k in range(4)]
    assert sec["occlusion"]["truncation"]["truncated"] == sum(o["truncation"] > 0 for o in objs)
    assert sum(sec["occlusion"]["truncation"]["counts"]) + sec["occlusion"]["truncation"]["outside"] == len(objs)


def test_distances_sizes_and_cameras_match(report, raw):
    s = report.stats["overall"]
    for c in ("car", "pedestrian"):
        objs = [o for o in _objects(raw) if o["category"] == c]
        if not objs:
            continue
        dist = [math.dist(o["box3d"]["center"], (0, 0, 0)) for o in objs]
        assert s["distance_m"]["by_class"][c]["median"] == pytest.approx(np.median(dist), rel=1e-5)
        assert s["dims"][c]["h"]["max"] == pytest.approx(max(o["box3d"]["dims"][2] for o in objs), rel=1e-5)
        heights = [o["bbox"][3] - o["bbox"][1] for o in objs]
        assert s["pixel_height"]["by_class"][c]["median"] == pytest.approx(np.median(heights), rel=1e-5)
    ego = [f for f in raw if f["view"] == "ego"]
    cam = report.stats["by_view"]["ego"]["camera"]
    assert cam["height_m"]["summary"]["median"] == pytest.approx(np.median([f["camera_height"] for f in ego]), rel=1e-5)
    hfov = [math.degrees(2 * math.atan(f["width"] / (2 * f["K"][0][0]))) for f in ego]
    assert cam["hfov_deg"]["summary"]["min"] == pytest.approx(min(hfov), rel=1e-5)
    assert cam["focal_px"]["summary"]["max"] == pytest.approx(max(f["K"][0][0] for f in ego), rel=1e-5)


def test_weather_and_lighting_mix_of_rendered_frames(report, raw):
    cond = report.stats["overall"]["conditions"]
    rendered = [f for f in raw if f["synthetic"]]
    assert cond["frames"] == len(rendered)
    fog = cond["weather"]["fog"]
    assert fog["kind"] == "numeric" and fog["summary"]["n"] == len(rendered)
    assert report.stats["by_source"]["kitti"]["conditions"]["frames"] == 0


def test_image_heatmap_counts_projected_centres(report, raw):
    """Each object's projected cuboid centre lands in the cell the heatmap counts it in."""
    h = report.stats["overall"]["heatmaps"]["image"]
    expected = np.zeros((len(h["y_edges"]) - 1, len(h["x_edges"]) - 1), dtype=int)
    for f in raw:
        K = np.array(f["K"])
        for o in f["objects"]:
            c = np.array(o["box3d"]["center"])
            if c[2] <= 0:
                continue
            u, v, w = K @ c
            x, y = u / w / f["width"], v / w / f["height"]
            i, j = np.searchsorted(h["y_edges"], y, "right") - 1, np.searchsorted(h["x_edges"], x, "right") - 1
            if 0 <= i < expected.shape[0] and 0 <= j < expected.shape[1]:
                expected[i, j] += 1
    assert np.array_equal(np.array(h["counts"]), expected)


def test_ground_coordinates_recover_the_world_position():
    """A box placed at (right, forward) on the ground of a pitched camera is found there again."""
    height, pitch = 6.0, math.radians(25)
    plane = plane_from_height_pitch(height, pitch)
    world_to_cam = rot_x(pitch) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    truth = np.array([[3.0, 20.0], [-7.5, 41.0], [0.0, 5.0]])
    dims = np.array([[4.2, 1.8, 1.5], [0.6, 0.6, 1.8], [11, 2.6, 3.2]])
    centers = np.array([world_to_cam @ [x, y, -height + d[2] / 2] for (x, y), d in zip(truth, dims)])
    rotations = np.array([world_to_cam @ rot_z(a) for a in (0.3, -1.2, 2.0)])
    planes = np.array([[*plane.normal, plane.offset]])
    got = ground_coordinates(planes, np.zeros(3, dtype=int), centers, rotations, dims)
    np.testing.assert_allclose(got, truth, atol=1e-9)
    no_plane = ground_coordinates(np.full((1, 4), np.nan), np.zeros(3, dtype=int), centers, rotations, dims)
    assert np.isnan(no_plane).all()


# ---------------------------------------------------------------------------------------------
# Health
# ---------------------------------------------------------------------------------------------


def _check(stats, name):
    return next(c for c in stats["health"]["checks"] if c["name"] == name)


def test_health_flags_what_was_planted(report, raw):
    s = report.stats
    objs = _objects(raw)
    outside = _check(s, "corners_all_outside")
    assert outside["count"] == sum(not any(o["in_image"]) for o in objs) >= 1
    assert "kitti-000901" in {e["frame_id"] for e in outside["examples"]}

    degenerate = _check(s, "degenerate_boxes")
    expected = [o for o in objs if o["bbox"][2] - o["bbox"][0] < 1 or o["bbox"][3] - o["bbox"][1] < 1
                or min(o["box3d"]["dims"]) < 0.05]
    assert degenerate["count"] == len(expected) >= 1
    assert any("0.40 x" in e["detail"] for e in degenerate["examples"])

    far = _check(s, "dims_outside_priors")
    expected = [o for o in objs if any(abs(d - m) > FAR_SIGMA * sd for d, m, sd in
                                       zip(o["box3d"]["dims"], PRIORS[o["category"]].mean, PRIORS[o["category"]].std))]
    assert far["count"] == len(expected) >= 1
    assert far["by_class"].get("traffic_cone", 0) >= 1

    empty = _check(s, "frames_without_objects")
    assert empty["count"] == sum(not f["objects"] for f in raw)
    assert EMPTY_FRAME in {e["frame_id"] for e in empty["examples"]}

    unreadable = _check(s, "images_unreadable")
    assert unreadable["count"] == 1 and unreadable["examples"][0]["frame_id"] == UNREADABLE
    wrong = _check(s, "image_size_mismatch")
    assert wrong["count"] == 1 and wrong["examples"][0]["frame_id"] == WRONG_SIZE
    assert s["health"]["problems"] == sum(c["count"] for c in s["health"]["checks"])


def test_priors_hold_typical_sizes():
    """The fakes' typical sizes sit well inside the priors; swapped dimensions do not."""
    from omnigen.fakes import TYPICAL_DIMS

    cats = np.array([FINE_CLASSES.index(c) for c in TYPICAL_DIMS])
    dims = np.array(list(TYPICAL_DIMS.values()))
    assert not far_outside_prior(cats, dims).any()
    car = FINE_CLASSES.index("car")
    assert far_outside_prior(np.array([car]), np.array([[1.5, 1.8, 4.2]])).all()  # l and h swapped


# ---------------------------------------------------------------------------------------------
# The report folder and page
# ---------------------------------------------------------------------------------------------


class _Page(html.parser.HTMLParser):
    """Collects <img src>, <a href>, and the text of every .num / .pct span."""

    def __init__(self):
        super().__init__()
        self.images, self.links, self.numbers, self._cls = [], [], [], None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a["src"])
        if tag == "a":
            self.links.append(a.get("href", ""))
        if tag == "span" and a.get("class") in ("num", "pct"):
            self._cls = a["class"]

    def handle_data(self, data):
        if self._cls:
            self.numbers.append((self._cls, data))
            self._cls = None


class _JsonInt(int):
    """A number read from stats.json: arithmetic on it gives a plain int, so a number the page
    computes itself is told apart from one it shows."""


class _JsonFloat(float):
    pass


def _tag(obj):
    if isinstance(obj, dict):
        return {k: _tag(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_tag(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    return _JsonInt(obj) if isinstance(obj, int) else _JsonFloat(obj)


def _from_stats_json(v):
    if v is not None and not isinstance(v, (_JsonInt, _JsonFloat)):
        raise AssertionError(f"the page shows {v!r}, which is not a number of stats.json")


def test_the_page_is_a_function_of_stats_json(report):
    """index.html renders again, byte for byte, from stats.json alone, and every number it shows
    (through the num and pct filters) is a value of stats.json, not one computed by the template."""
    text = (report.out / "index.html").read_text()
    stored = json.loads((report.out / "stats.json").read_text())
    assert render_page(stored) == text
    render_page(_tag(stored), check=_from_stats_json)
    page = _Page()
    page.feed(text)
    assert len(page.numbers) > 200
    with pytest.raises(AssertionError, match="not a number of stats.json"):  # the check can fail
        _from_stats_json(stored["overall"]["objects"] / 7)


def test_report_files_are_offline_and_complete(report):
    text = (report.out / "index.html").read_text()
    assert not re.search(r"(src|href)=\"(https?:)?//", text), "the page must not fetch anything from the network"
    page = _Page()
    page.feed(text)
    assert len(page.images) == report.figures + len(report.stats["gallery"])
    for src in page.images:
        with Image.open(report.out / src) as im:
            assert im.format == "PNG" and im.width > 100
    assert report.stats["gallery"] and all((report.out / g["file"]).exists() for g in report.stats["gallery"])
    groups = {(g["source"], g["view"]) for g in report.stats["gallery"]}
    assert len(groups) == len(report.stats["gallery"]) == 3, "the gallery shows a different camera each time first"
    stored = json.loads((report.out / "stats.json").read_text())
    assert stored["overall"] == json.loads(json.dumps(report.stats["overall"]))


def test_figures_redraw_from_stats_json_alone(report, tmp_path):
    from omnigen.stats.plots import plot_heatmaps

    stored = json.loads((report.out / "stats.json").read_text())
    plot_heatmaps(stored["by_view"]["aerial"], stored, tmp_path / "h.png")
    with Image.open(tmp_path / "h.png") as im:
        assert im.width > 300


def test_stats_command(tmp_path, capsys):
    """One source seen from one view: its source and view sections point at the overall one."""
    write_fake_dataset(tmp_path / "ds", 4, objects_per_frame=3, source="kitti")
    assert main(["stats", str(tmp_path / "ds"), "--out", str(tmp_path / "r"), "--gallery", "0", "--no-check-images",
                 "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert "index.html" in out and "statistics" in out
    stats = json.loads((tmp_path / "r" / "stats.json").read_text())
    assert stats["gallery"] == [] and not stats["health"]["images_checked"]
    assert {c["name"] for c in stats["health"]["checks"]} == {
        "corners_all_outside", "degenerate_boxes", "dims_outside_priors", "frames_without_objects"}
    assert stats["by_source"]["kitti"]["objects"] == stats["overall"]["objects"] == 12
    assert sorted(p.name for p in (tmp_path / "r" / "plots").iterdir()) == ["overall"]
    page = (tmp_path / "r" / "index.html").read_text()
    assert 'id="source-kitti"' in page and 'id="view-ego"' in page and "its numbers are those of" in page


def test_stats_refuses_an_output_folder_it_did_not_make(tmp_path, capsys):
    """Issue 27: --out DIR deleted DIR/plots and DIR/gallery whatever DIR was."""
    write_fake_dataset(tmp_path / "ds", 2, objects_per_frame=1, source="kitti")
    theirs = tmp_path / "theirs"
    for sub in ("plots", "gallery"):
        (theirs / sub).mkdir(parents=True)
        (theirs / sub / "keep.png").write_bytes(b"someone else's")
    args = ["stats", str(tmp_path / "ds"), "--gallery", "0", "--no-check-images", "--jobs", "1"]
    assert main([*args, "--out", str(theirs)]) == 1
    assert "did not make" in capsys.readouterr().err
    assert sorted(p.relative_to(theirs).as_posix() for p in theirs.rglob("*")) == [
        "gallery", "gallery/keep.png", "plots", "plots/keep.png"]
    # its own folder, and a report from before the marker, are rewritten
    mine = tmp_path / "mine"
    assert main([*args, "--out", str(mine)]) == 0
    assert main([*args, "--out", str(mine)]) == 0
    (mine / ".omnigen-job").unlink()
    assert main([*args, "--out", str(mine)]) == 0
    assert (mine / ".omnigen-job").read_text() == "stats\n"


def test_compute_is_vectorised_over_sections(dataset):
    """Sections partition the objects: per-source object counts add up to the total."""
    ds = Dataset.open(dataset, show_progress=False)
    s = compute_stats(ds, derive(ds))
    assert sum(sec["objects"] for sec in s["by_source"].values()) == s["overall"]["objects"] == len(ds.objects)
    assert sum(sec["frames"] for sec in s["by_view"].values()) == len(ds)


# ---------------------------------------------------------------------------------------------
# In a browser
# ---------------------------------------------------------------------------------------------

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--enable-logging=stderr", "--v=0", "--virtual-time-budget=10000"]


def _chromium() -> str | None:
    for name in (os.environ.get("OMNIGEN_CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _run_chromium(browser: str, profile: Path, *args: str) -> subprocess.CompletedProcess:
    profile.mkdir(parents=True, exist_ok=True)
    return subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args],
                          capture_output=True, text=True, timeout=120)


def _render_check(dom: str) -> dict[str, str]:
    m = re.search(r'<span id="render-check"([^>]*)>', dom)
    assert m, "the page's image check did not run"
    return dict(re.findall(r'(data-[a-z]+)="([^"]*)"', m.group(1)))


def test_report_renders_in_chromium(report, tmp_path):
    browser = _chromium()
    if browser is None:
        pytest.skip("chromium not installed (Debian: apt-get install -y chromium; `make test` does it when it can)")
    url = (report.out / "index.html").resolve().as_uri()
    run = _run_chromium(browser, tmp_path / "profile1", "--dump-dom", url)
    assert run.returncode == 0, run.stderr[-2000:]
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line]
    assert not console, f"console messages: {console}"
    check = _render_check(run.stdout)
    assert check["data-state"] == "ok", check
    assert int(check["data-total"]) == report.figures + len(report.stats["gallery"])

    shot = tmp_path / "report.png"
    run = _run_chromium(browser, tmp_path / "profile2", f"--screenshot={shot}", "--window-size=1280,2000",
                        "--hide-scrollbars", url)
    assert run.returncode == 0 and shot.exists(), run.stderr[-2000:]
    with Image.open(shot) as im:
        assert im.size == (1280, 2000)
        assert np.asarray(im.convert("L")).std() > 10, "the screenshot is blank"
    print(f"screenshot: {shot}")

    # The check can fail: a report with a figure removed is caught and the file named.
    broken = tmp_path / "broken"
    shutil.copytree(report.out, broken)
    victim = next((broken / "plots" / "overall").glob("*.png"))
    victim.unlink()
    run = _run_chromium(browser, tmp_path / "profile3", "--dump-dom", (broken / "index.html").resolve().as_uri())
    check = _render_check(run.stdout)
    assert check["data-state"] == "broken" and f"plots/overall/{victim.name}" in check["data-broken"]


def test_report_without_objects_or_ground_planes(tmp_path):
    """Frames with nothing in them and no ground plane still give a whole report, and say so."""
    root = tmp_path / "ds"
    (root / "images").mkdir(parents=True)
    writer = DatasetWriter(root, durable=False)
    for i in range(3):
        rec = random_frame(0, i, "kitti", "ego", n_objects=0 if i < 2 else 2, width=W, height=H)
        rec.ground_plane, rec.camera_height, rec.camera_pitch = None, None, None
        Image.new("RGB", (W, H)).save(root / rec.image)
        writer.write(rec)
    writer.finalize(show_progress=False)
    r = write_report(Dataset.open(root, show_progress=False), tmp_path / "r", gallery=3, jobs=1, show_progress=False)
    sec = r.stats["overall"]
    assert sec["camera"]["without_ground_plane"] == 3 and sec["camera"]["height_m"]["summary"]["n"] == 0
    assert sec["heatmaps"]["ground"]["missing"] == sec["objects"] == 2
    assert _check(r.stats, "frames_without_objects")["count"] == 2
    assert len(r.stats["gallery"]) == 3 and r.stats["gallery"][0]["objects"] == 2  # frames with objects first
    assert (tmp_path / "r" / "index.html").exists()


def test_image_check_reports_a_fifo_instead_of_waiting_on_it(tmp_path):
    """An image path that is a FIFO (or a device) is a reported problem: opening it for its header
    would block the report for ever (issue 27)."""
    import os
    import threading

    from omnigen.fakes import write_fake_dataset
    from omnigen.stats.health import image_checks

    ds = write_fake_dataset(tmp_path / "ds", 3, objects_per_frame=2, seed=1)
    victim = ds.path(ds.table.image[1])
    victim.unlink()
    os.mkfifo(victim)
    result: list = []
    worker = threading.Thread(target=lambda: result.append(image_checks(ds, show_progress=False)), daemon=True)
    worker.start()
    worker.join(20)
    assert result, "the image check waited on a FIFO"
    unreadable = next(c for c in result[0] if c["name"] == "images_unreadable")
    assert unreadable["count"] == 1 and unreadable["examples"][0]["frame_id"] == ds.table.frame_id[1]


def test_a_single_valued_field_is_written_out_not_drawn_as_an_empty_axis():
    """Fog off in every frame drew one thin bar on a unit-wide axis, read as an empty plot."""
    from matplotlib.figure import Figure

    from omnigen.stats.compute import histogram, linear_edges, summary
    from omnigen.stats.plots import _hist_or_value

    constant, spread = np.zeros(5), np.array([0.0, 0.1, 0.2, 0.3, 0.4])
    for values, drawn in ((constant, False), (spread, True)):
        ax = Figure().subplots()
        _hist_or_value(ax, {**histogram(values, linear_edges(values, bins=12)), "summary": summary(values)}, "fog")
        texts = [t.get_text() for t in ax.texts]
        assert bool(ax.patches) == drawn
        assert (texts == ["fog:\nall 5 values 0"]) != drawn


def test_the_gallery_leaves_out_stand_ins_too_small_to_look_at_and_says_so(tmp_path):
    """The demo's report showed the 96x54 generated DAIR-V2X-C stand-in beside camera frames as if
    it were data: images under GALLERY_MIN_SIDE on a side are not drawn, and the page counts them."""
    from omnigen.converters.dair_fixture import write_dair_tree
    from omnigen.fakes import write_fake_dataset
    from omnigen.stats.gallery import GALLERY_MIN_SIDE

    write_fake_dataset(tmp_path / "syn", 4)
    write_dair_tree(tmp_path / "dair-src", 4, seed=0, variant="c")
    assert main(["convert", "dair", str(tmp_path / "dair-src"), "--out", str(tmp_path / "dair")]) == 0
    assert main(["merge", str(tmp_path / "syn"), str(tmp_path / "dair"), "--out", str(tmp_path / "uov")]) == 0
    ds = Dataset.open(tmp_path / "uov", show_progress=False)
    small = sum(min(ds[i].width, ds[i].height) < GALLERY_MIN_SIDE for i in range(len(ds)))
    assert small == 4
    report = write_report(ds, tmp_path / "report", gallery=8, jobs=1, show_progress=False)
    assert report.stats["gallery"] and all(g["source"] == "synthetic" for g in report.stats["gallery"])
    assert report.stats["gallery_too_small"] == {"frames": 4, "min_side": GALLERY_MIN_SIDE}
    assert '<span class="num">4</span> frames whose images are under 64 px' in (tmp_path / "report" / "index.html").read_text()
