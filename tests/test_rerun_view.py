"""What the Rerun view shows beyond the map: heading, colours and legend, the provisional
map, free voxels and the default view's bounds (read back from recording files)."""

from __future__ import annotations

import collections
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from octolgp import Hyperparameters, MapConfig, OnlineConfig, OnlineMap, Scan, load_scans
from octolgp.cli import main
from octolgp.cli.main import RERUN_COLORS, make_parser
from octolgp.errors import OctolgpError
from octolgp.io.rrd_read import read_rrd
from octolgp.sinks.colours import (
    PROBABILITY_ANCHORS,
    grey_levels,
    png,
    probability_colours,
    probability_palette,
)
from octolgp.sinks.heading import BLIND_DEGREES, Heading, view_direction
from octolgp.sinks.rerun import (
    COLORS,
    FREE_BELOW,
    FREE_STRIDE,
    GREY_STEPS,
    RerunSink,
    default_blueprint,
    legend_colours,
)

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"
HP = Hyperparameters(length_scale=0.8, signal_variance=1.0, noise_variance=0.05, alpha=5.0)


# ---------------------------------------------------------------- reading recordings
def _rows(path: Path, prefix: str, column: str) -> list[tuple[str, int | None, Any]]:
    """``(entity, scan or None when static, value)`` of every row of entities under a prefix."""
    out: list[tuple[str, int | None, Any]] = []
    for chunk in RrdReader(path).stream():
        entity = str(chunk.entity_path)
        batch = chunk.to_record_batch()
        if not entity.startswith(prefix) or column not in batch.schema.names:
            continue
        values = batch.column(column)
        scans = batch.column("scan").to_pylist() if "scan" in batch.schema.names else None
        for i in range(batch.num_rows):  # one iteration per row
            if values[i].is_valid:
                out.append((entity, None if scans is None else scans[i], values[i]))
    return out


def _latest(rows: list[tuple[str, int | None, Any]], at: int | None = None) -> dict[str, Any]:
    """Each entity's value at its last scan up to ``at`` (static rows count as earliest)."""
    best: dict[str, tuple[int, Any]] = {}
    for entity, scan, value in rows:  # one iteration per row
        when = -1 if scan is None else scan
        if at is not None and when > at:
            continue
        if entity not in best or when >= best[entity][0]:
            best[entity] = (when, value)
    return {e: v for e, (_, v) in best.items()}


def _image(value: Any) -> np.ndarray:
    """The pixels of one ``EncodedImage:blob`` cell, RGB when the PNG has colours."""
    from PIL import Image

    blob = bytes(value.values[0].values.to_numpy(zero_copy_only=False))
    image = Image.open(io.BytesIO(blob))
    return np.asarray(image.convert("RGB") if image.mode in ("P", "RGB") else image)


def _record(path: Path, scans: list[Scan], config: MapConfig, **options: Any) -> OnlineMap:
    """Map ``scans`` with a Rerun sink writing to ``path``; the open map."""
    rec = rr.RecordingStream("octolgp-test")
    rec.save(path)
    m = OnlineMap(config, sink=RerunSink(rec, **options))
    m.insert_scans(scans)
    rec.flush()
    rec.disconnect()
    return m


def _sphere_scans(dim: int, n: int, step: np.ndarray) -> list[Scan]:
    """All-round scans (beams in every direction) from origins ``step`` apart."""
    rng = np.random.default_rng(dim)
    out = []
    for k in range(n):
        origin = k * step
        d = rng.normal(size=(300, dim))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out.append(Scan(origin=origin, points=origin + 3.0 * d))
    return out


# ---------------------------------------------------------------- heading
def _exact(dim: int) -> MapConfig:
    """A map that keeps scans unrounded (rounding to 1 cm moves an arrow by < 0.2 degrees)."""
    online = OnlineConfig(scan_precision=None)
    return MapConfig(dim=dim, resolution=0.2, hyperparameters=HP, online=online)


@pytest.mark.parametrize("fov_degrees", [180.0, 240.0, 270.0])
def test_view_direction_is_the_yaw_of_a_forward_facing_sensor(fov_degrees: float) -> None:
    half = np.radians(fov_degrees) / 2
    for yaw in np.linspace(-np.pi, np.pi, 13):  # includes the ±π seam
        scan = Scan.from_ranges([1.0, -2.0, yaw], np.full(181, 4.0), np.linspace(-half, half, 181))
        v = view_direction(scan)
        assert v is not None
        assert np.isclose(np.arctan2(v[1], v[0]), np.angle(np.exp(1j * yaw)), atol=1e-9) or (
            np.isclose(abs(yaw), np.pi) and np.isclose(abs(np.arctan2(v[1], v[0])), np.pi)
        )
    all_round = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    assert view_direction(Scan.from_ranges([0, 0, 0.3], np.full(360, 4.0), all_round)) is None
    narrow = 360.0 - BLIND_DEGREES + 10.0  # a gap narrower than BLIND_DEGREES: all round
    angles = np.radians(np.linspace(-narrow / 2, narrow / 2, 361))
    assert view_direction(Scan.from_ranges([0, 0, 0.3], np.full(361, 4.0), angles)) is None


def test_heading_of_an_all_round_sensor_is_its_travel() -> None:
    heading = Heading()
    step = np.array([0.3, -0.4, 0.1])
    scans = _sphere_scans(3, 3, step)
    assert heading.update(scans[0]) is None  # not moved yet
    for scan in scans[1:]:
        np.testing.assert_allclose(heading.update(scan), step / np.linalg.norm(step))
    still = Scan(origin=scans[-1].origin + 0.01, points=scans[-1].points)
    np.testing.assert_allclose(heading.update(still), step / np.linalg.norm(step))  # kept


def test_2d_heading_arrow_is_the_pose_yaw(tmp_path: Path) -> None:
    """A 180-degree laser turning as it drives: each scan's arrow points along its yaw,
    from the robot's position, in the view's flipped y."""
    rrd = tmp_path / "m.rrd"
    poses = [(0.1 * k, 0.05 * k, -2.8 + 0.9 * k) for k in range(7)]
    angles = np.linspace(-np.pi / 2, np.pi / 2, 91)
    scans = [Scan.from_ranges(p, np.full(91, 3.0), angles) for p in poses]
    with _record(rrd, scans, _exact(2)):
        pass
    vectors = _rows(rrd, "/map/heading", "Arrows2D:vectors")
    origins = _rows(rrd, "/map/heading", "Arrows2D:origins")
    assert [s for _, s, _ in vectors] == list(range(1, 8))
    for (_, scan, v), (_, _, o), (x, y, yaw) in zip(vectors, origins, poses, strict=True):
        vx, vy = v.as_py()[0]
        assert np.isclose(np.arctan2(-vy, vx), np.angle(np.exp(1j * yaw)), atol=1e-5), scan
        np.testing.assert_allclose(o.as_py()[0], [x, -y], atol=1e-5)


def test_3d_heading_arrow_is_the_pose_rotation(tmp_path: Path) -> None:
    """A forward-facing 3D sensor turned by a yaw about z: the arrow is the rotation's x
    axis. Then an all-round one driving: the arrow is its direction of travel."""
    rrd = tmp_path / "m.rrd"
    rng = np.random.default_rng(3)
    local = rng.normal(size=(400, 3))
    local[:, 0] = np.abs(local[:, 0])  # the front half-space: a 180-degree field of view
    local /= np.linalg.norm(local, axis=1, keepdims=True)
    local = np.concatenate([local, local * [1.0, -1.0, 1.0]])  # symmetric about the x axis
    yaws = [0.4, 1.9, -2.2]
    scans = []
    for k, yaw in enumerate(yaws):
        c, s = np.cos(yaw), np.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([0.2 * k, 0.0, 0.0])
        scans.append(Scan(origin=origin, points=origin + 3.0 * local @ rotation.T))
    step = np.array([0.3, 0.2, 0.05])
    scans += [Scan(origin=s.origin + 1.0, points=s.points + 1.0) for s in _sphere_scans(3, 3, step)]
    with _record(rrd, scans, _exact(3)) as m:
        assert m.n_scans == 6
    got = {
        s: np.asarray(v.as_py()[0])
        for _, s, v in _rows(rrd, "/world/sensor/heading", "Arrows3D:vectors")
    }
    for k, yaw in enumerate(yaws, start=1):
        np.testing.assert_allclose(
            got[k] / np.linalg.norm(got[k]), [np.cos(yaw), np.sin(yaw), 0], atol=1e-5
        )
    # scan 4 jumps from scan 3 (a step, no front): travel; scans 5 and 6 drive by step
    for k in (5, 6):
        np.testing.assert_allclose(
            got[k] / np.linalg.norm(got[k]), step / np.linalg.norm(step), atol=1e-5
        )


# ---------------------------------------------------------------- colours and legend
def test_probability_colours_follow_the_documented_map() -> None:
    for p, r, g, b in PROBABILITY_ANCHORS:
        assert probability_colours(np.array([p])).tolist() == [[r, g, b]]
    mid = probability_colours(np.array([0.125]))[0]
    np.testing.assert_allclose(
        mid, 0.5 * (PROBABILITY_ANCHORS[0, 1:] + PROBABILITY_ANCHORS[1, 1:]), atol=0.5
    )
    assert (
        probability_colours(np.array([-1.0, 2.0])).tolist()
        == probability_colours(np.array([0.0, 1.0])).tolist()
    )
    index, palette = probability_palette(GREY_STEPS)
    p = np.linspace(0, 1, 101)
    steps = np.rint((1.0 - p) * GREY_STEPS)  # the grey images' step of each P
    np.testing.assert_array_equal(index[grey_levels(p, GREY_STEPS)], steps)
    want = probability_colours(1.0 - steps / GREY_STEPS)  # P rounded to the steps
    np.testing.assert_array_equal(palette[index[grey_levels(p, GREY_STEPS)]], want)
    np.testing.assert_array_equal(palette[index[128]], probability_colours(np.array([0.5]))[0])
    assert COLORS == RERUN_COLORS


def test_png_round_trips_grey_palette_and_rgb() -> None:
    from PIL import Image

    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (5, 7), dtype=np.uint8)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    indices = rng.integers(0, 4, (5, 7), dtype=np.uint8)
    palette = rng.integers(0, 256, (4, 3), dtype=np.uint8)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png(grey)))), grey)
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(png(rgb)))), rgb)
    indexed = Image.open(io.BytesIO(png(indices, palette)))
    assert indexed.mode == "P"
    assert np.array_equal(np.asarray(indexed.convert("RGB")), palette[indices])


def test_2d_probability_tiles_and_legend(tmp_path: Path) -> None:
    """Each cell's colour is the colour of its P rounded to the images' steps; the legend
    is a colour bar of that map with its ends labelled."""
    rrd, tile, res = tmp_path / "m.rrd", 32, 0.2
    scans = _sphere_scans(2, 4, np.array([0.3, 0.0]))
    config = MapConfig(dim=2, resolution=res, hyperparameters=HP)
    with _record(rrd, scans, config, tile=tile, colors="probability") as m:
        centres, prob = m.voxels()
    images = {
        e: _image(v) for e, v in _latest(_rows(rrd, "/map/tiles/", "EncodedImage:blob")).items()
    }
    assert images
    cells = np.floor(centres / res).astype(np.int64)
    unknown = probability_colours(np.array([0.5]))[0]
    for entity, image in images.items():  # one iteration per tile
        tx, ty = (int(v) for v in entity.rsplit("/", 1)[1].split("_"))
        want = np.broadcast_to(unknown, (tile, tile, 3)).copy()
        mine = (cells[:, 0] // tile == tx) & (cells[:, 1] // tile == ty)
        k = np.rint((1.0 - prob[mine]) * GREY_STEPS)
        rows = tile - 1 - (cells[mine, 1] - ty * tile)
        want[rows, cells[mine, 0] - tx * tile] = probability_colours(1.0 - k / GREY_STEPS)
        assert np.array_equal(image, want), entity
    bar = _image(_latest(_rows(rrd, "/legend/bar", "EncodedImage:blob"))["/legend/bar"])
    assert np.array_equal(bar[0], legend_colours("probability", 2))
    assert np.array_equal(bar[0], probability_colours(np.linspace(0, 1, bar.shape[1])))
    labels = _latest(_rows(rrd, "/legend/labels", "Points2D:labels"))["/legend/labels"].as_py()
    assert labels == ["P(occupied)", "0 free", "0.5 unknown", "1 occupied"]


def test_grey_and_height_legends(tmp_path: Path) -> None:
    rrd = tmp_path / "m.rrd"
    scans = _sphere_scans(3, 2, np.array([0.3, 0.0, 0.0]))
    with _record(rrd, scans, MapConfig(dim=3, resolution=0.2, hyperparameters=HP)):
        pass
    labels = _latest(_rows(rrd, "/legend/labels", "Points2D:labels"))["/legend/labels"].as_py()
    assert labels[0] == "height of occupied voxels"
    assert all(text.endswith(" m") for text in labels[1:])
    bar = np.asarray(legend_colours("auto", 2))
    assert np.all(bar[:, 0] == bar[:, 1])
    assert bar[0, 0] == 255
    assert bar[-1, 0] == 0


def test_3d_probability_voxels(tmp_path: Path) -> None:
    rrd, res = tmp_path / "m.rrd", 0.2
    scans = _sphere_scans(3, 3, np.array([0.3, 0.0, 0.0]))
    config = MapConfig(dim=3, resolution=res, hyperparameters=HP)
    with _record(rrd, scans, config, colors="probability") as m:
        centres, prob = m.voxels()
    by_key = {
        tuple(k): p for k, p in zip(np.floor(centres / res).astype(np.int64), prob, strict=True)
    }
    boxes = _latest(_rows(rrd, "/world/map/voxels/", "Boxes3D:centers"))
    colours = _latest(_rows(rrd, "/world/map/voxels/", "Boxes3D:colors"))
    halves = _latest(_rows(rrd, "/world/map/voxels/", "Boxes3D:half_sizes"))
    n = 0
    for entity, value in boxes.items():  # one iteration per region
        c = np.asarray(value.as_py())
        packed = np.asarray(colours[entity].as_py(), dtype=np.uint32)
        rgb = np.stack([(packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255], axis=1)
        if np.allclose(halves[entity].as_py(), 0.5 * res):
            for centre, colour in zip(c, rgb, strict=True):  # one iteration per voxel box
                p = by_key[tuple(np.floor(centre / res + 1e-6).astype(np.int64))]
                assert p > 0.5
                level = np.rint(p * GREY_STEPS) / GREY_STEPS
                assert colour.tolist() == probability_colours(np.array([level]))[0].tolist()
                n += 1
    assert n > 0


def test_bad_colors_raise_naming_the_field() -> None:
    with pytest.raises(OctolgpError, match="colors"):
        RerunSink(rr.RecordingStream("octolgp-test"), colors="viridis")


# ---------------------------------------------------------------- provisional map
def test_the_provisional_map_is_drawn_while_learning_then_cleared(tmp_path: Path) -> None:
    """Learning on 6 scans: the provisional fit after buffered scans 1 and 4, each the
    map reads then gave, labelled; cleared at scan 6, where the learnt map's tiles begin."""
    rrd, tile, res = tmp_path / "m.rrd", 32, 0.1
    scans = list(load_scans(INTEL20))[:8]
    rec = rr.RecordingStream("octolgp-test")
    rec.save(rrd)
    config = MapConfig(dim=2, resolution=res, online=OnlineConfig(learn_scans=6, n_jobs=1))
    provisional = {}
    with OnlineMap(config, sink=RerunSink(rec, tile=tile)) as m:
        for k, scan in enumerate(scans, start=1):  # one iteration per scan
            m.insert_scan(scan)
            if k == 4:
                assert m.provisional
                provisional[k] = m.voxels()  # the provisional fit, the one the sink drew
    rec.flush()
    rec.disconnect()
    drawn = _rows(rrd, "/map/provisional/tiles/", "EncodedImage:blob")
    assert {s for _, s, _ in drawn} == {1, 4}
    labels = _rows(rrd, "/map/provisional/label", "Boxes2D:labels")
    assert [s for _, s, _ in labels] == [1, 4]
    assert all("provisional" in v.as_py()[0] for _, _, v in labels)
    clears = _rows(rrd, "/map/provisional", "Clear:is_recursive")
    assert [(e, s, v.as_py()) for e, s, v in clears] == [("/map/provisional", 6, [True])]
    learnt = _rows(rrd, "/map/tiles/", "EncodedImage:blob")
    assert min(s for _, s, _ in learnt) == 6
    # the tiles drawn at scan 4 are the provisional map the reads answered from
    centres, prob = provisional[4]
    cells = np.floor(centres / res).astype(np.int64)
    images = _latest(drawn, at=4)
    for entity, value in images.items():  # one iteration per tile
        tx, ty = (int(v) for v in entity.rsplit("/", 1)[1].split("_"))
        mine = (cells[:, 0] // tile == tx) & (cells[:, 1] // tile == ty)
        got = _image(value)[tile - 1 - (cells[mine, 1] - ty * tile), cells[mine, 0] - tx * tile]
        assert np.array_equal(got, grey_levels(prob[mine], GREY_STEPS))
    assert images
    # the metrics are plotted while learning too, and the recording still replays
    assert len(_rows(rrd, "/metrics/insert_seconds", "Scalars:scalars")) == 8
    assert len(list(read_rrd(rrd))) == 8


def test_3d_provisional_voxels_while_learning(tmp_path: Path) -> None:
    rrd = tmp_path / "m.rrd"
    scans = _sphere_scans(3, 4, np.array([0.3, 0.0, 0.0]))
    config = MapConfig(dim=3, resolution=0.2, online=OnlineConfig(learn_scans=3, n_jobs=1))
    with _record(rrd, scans, config):
        pass
    drawn = _rows(rrd, "/world/provisional/voxels/", "Boxes3D:centers")
    assert drawn
    assert {s for _, s, _ in drawn} == {1}
    labels = _rows(rrd, "/world/provisional/label", "Boxes3D:labels")
    assert labels
    assert all("provisional" in v.as_py()[0] for _, _, v in labels)
    clears = _rows(rrd, "/world/provisional", "Clear:is_recursive")
    assert [(e, s) for e, s, _ in clears if e == "/world/provisional"] == [
        ("/world/provisional", 3)
    ]
    assert min(s for _, s, _ in _rows(rrd, "/world/map/voxels/", "Boxes3D:centers")) == 3


def test_no_provisional_map_when_turned_off(tmp_path: Path) -> None:
    rrd = tmp_path / "m.rrd"
    config = MapConfig(dim=2, resolution=0.2, online=OnlineConfig(learn_scans=3, n_jobs=1))
    with _record(rrd, list(load_scans(INTEL20))[:2], config, provisional=False):
        pass
    assert not _rows(rrd, "/map/provisional", "EncodedImage:blob")


# ---------------------------------------------------------------- free voxels and bounds
def test_free_voxels_only_when_asked_and_within_the_bound(tmp_path: Path) -> None:
    res, region = 0.2, 16
    scans = _sphere_scans(3, 3, np.array([0.3, 0.0, 0.0]))
    config = MapConfig(dim=3, resolution=res, hyperparameters=HP)
    off, on = tmp_path / "off.rrd", tmp_path / "on.rrd"
    with _record(off, scans, config, region=region):
        pass
    assert not _rows(off, "/world/map/free/", "Points3D:positions")
    with _record(on, scans, config, region=region, free_voxels=True) as m:
        centres, prob = m.voxels()
    by_key = {
        tuple(k): p for k, p in zip(np.floor(centres / res).astype(np.int64), prob, strict=True)
    }
    drawn = _latest(_rows(on, "/world/map/free/", "Points3D:positions"))
    assert drawn
    keys = set()
    for value in drawn.values():  # one iteration per region
        points = np.asarray(value.as_py())
        assert len(points) <= (region // FREE_STRIDE) ** 3
        k = np.floor(points / res + 1e-6).astype(np.int64)
        assert np.all(k % FREE_STRIDE == 0)
        keys.update(tuple(x) for x in k)
    assert all(by_key[k] < FREE_BELOW for k in keys)
    want = {k for k, p in by_key.items() if p < FREE_BELOW and all(x % FREE_STRIDE == 0 for x in k)}
    assert keys == want


def test_the_3d_view_opens_on_the_voxels_drawn(tmp_path: Path) -> None:
    rrd, res = tmp_path / "m.rrd", 0.2
    scans = _sphere_scans(3, 3, np.array([0.3, 0.0, 0.0]))
    rec = rr.RecordingStream("octolgp-test")
    rec.save(rrd)
    sink = RerunSink(rec)
    with OnlineMap(MapConfig(dim=3, resolution=res, hyperparameters=HP), sink=sink) as m:
        m.insert_scans(scans)
        centres, prob = m.voxels()
    rec.disconnect()
    assert sink.shown is not None
    assert len(sink.shown) == 3
    occupied = centres[prob > 0.5]
    for axis, (lo, hi) in enumerate(sink.shown):
        assert lo < occupied[:, axis].min()
        assert occupied[:, axis].max() < hi
        assert hi - lo < 1.3 * np.ptp(occupied[:, axis]) + res + 2.1
    assert len(RrdReader(rrd).blueprints()) >= 2  # the first, then one with the camera
    assert default_blueprint(3, bounds=sink.shown) is not None


# ---------------------------------------------------------------- the CLI
def test_cli_flags_parse_and_reach_the_recording(tmp_path: Path) -> None:
    args = make_parser().parse_args(["run", "x.log", "--out", "m.octolgp"])
    assert (args.rerun_colors, args.rerun_free_voxels) == ("auto", False)
    out, rrd = tmp_path / "m.octolgp", tmp_path / "m.rrd"
    argv = ["run", str(INTEL20), "--out", str(out), "--rerun-save", str(rrd), "--quiet"]
    flags = ["--rerun-colors", "probability", "--rerun-free-voxels", "--limit", "3"]
    assert main([*argv, "--resolution", "0.2", "--learn-scans", "2", *flags]) == 0
    bar = _image(_latest(_rows(rrd, "/legend/bar", "EncodedImage:blob"))["/legend/bar"])
    assert np.array_equal(bar[0], legend_colours("probability", 2))
    tiles = _latest(_rows(rrd, "/map/tiles/", "EncodedImage:blob"))
    assert tiles
    assert all(_image(v).ndim == 3 for v in tiles.values())
    assert _rows(rrd, "/map/heading", "Arrows2D:vectors")


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--rerun-colors", "viridis"), ("--rerun-colors", ""), ("--rerun-free-voxels", "3")],
)
def test_bad_rerun_flags_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flag: str, value: str
) -> None:
    argv = ["run", str(INTEL20), "--out", str(tmp_path / "m.octolgp"), flag, value]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert flag in err or value in err


def test_counts_of_a_default_run(tmp_path: Path) -> None:
    """The extra entities cost a few rows: one heading per scan, the legend once."""
    rrd = tmp_path / "m.rrd"
    scans = _sphere_scans(2, 3, np.array([0.3, 0.0]))
    with _record(rrd, scans, MapConfig(dim=2, resolution=0.2, hyperparameters=HP)):
        pass
    rows: collections.Counter[str] = collections.Counter()
    for chunk in RrdReader(rrd).stream():
        rows[str(chunk.entity_path)] += int(chunk.num_rows)
    assert rows["/map/heading"] == 1 + 2  # the style (static), then scans 2 and 3
    assert rows["/legend/bar"] == 1
    assert rows["/legend/labels"] == 1


def test_heading_of_a_scan_with_its_rotation_is_its_forward_axis() -> None:
    """An all-round scan carrying its orientation: the arrow is the rotation's x axis,
    not the travel, from the first scan on."""
    heading = Heading()
    step = np.array([0.3, -0.4, 0.1])
    for k, scan in enumerate(_sphere_scans(3, 3, step)):
        yaw = 0.5 + k
        c, s = np.cos(yaw), np.sin(yaw)
        rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        posed = Scan(origin=scan.origin, points=scan.points, rotation=rotation)
        np.testing.assert_allclose(heading.update(posed), [c, s, 0.0], atol=1e-12)
