"""nav2 maps (PGM + YAML) and PCD voxel clouds: round trips against the map, malformed input."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
from octolgp.cli import main
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.export.nav2 import (
    FREE,
    LOAD_FREE_THRESH,
    OCCUPIED,
    UNKNOWN,
    cell_states,
    project_cells,
    trinary_grid,
    write_nav2_map,
)
from octolgp.export.nav2_read import read_nav2_map
from octolgp.export.pcd import write_pcd
from octolgp.io import read_kitti, read_pcd
from octolgp.io.pcd import read_pcd_header

DATA = Path(__file__).parent / "data"
INTEL20 = DATA / "intel_first20.log"
HP2 = Hyperparameters(
    length_scale=1.2, signal_variance=3.8, noise_variance=0.006, alpha=4.5, beta=1.0
)
RES = 0.1


@pytest.fixture(scope="module")
def map2d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2D map file of the first 3 Intel scans at 0.1 m."""
    path = tmp_path_factory.mktemp("nav2") / "intel.octolgp"
    with OnlineMap(MapConfig(dim=2, resolution=RES, hyperparameters=HP2), path=path) as m:
        m.insert_scans(list(load_scans(INTEL20))[:3])
    return path


@pytest.fixture(scope="module")
def map3d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3D map file of the KITTI fixture's five scans at 0.5 m (z up), the default config
    (hyperparameters learnt, α, β calibrated on the map's own free weights)."""
    path = tmp_path_factory.mktemp("nav2") / "street.octolgp"
    scans = list(read_kitti(DATA / "kitti" / "sequences" / "00", world="velodyne"))
    with OnlineMap(MapConfig(dim=3, resolution=0.5), path=path) as m:
        m.insert_scans(scans)
    return path


def _pgm(path: Path) -> np.ndarray:
    """The image as a standard tool reads it (Pillow), row 0 on top."""
    with Image.open(path) as im:
        assert im.format == "PPM"
        assert im.mode == "L"
        return np.asarray(im)


# ---------------------------------------------------------------- nav2: round trips


def test_2d_map_round_trip(map2d: Path, tmp_path: Path) -> None:
    with OnlineMap.open(map2d) as m:
        centres, prob = m.voxels()
    yaml = write_nav2_map(tmp_path / "intel.pgm", centres, prob, RES)
    assert yaml == tmp_path / "intel.yaml"
    back = read_nav2_map(yaml)
    expected = cell_states(prob)
    np.testing.assert_array_equal(back.states_at(centres), expected)
    # every cell without a voxel is unknown: the known cells are exactly the known voxels
    for state in (OCCUPIED, FREE):
        assert int((back.cells == state).sum()) == int((expected == state).sum()) > 0
    # origin = the lower-left corner of the lower-left cell; image row 0 = the largest y
    np.testing.assert_allclose(back.origin[:2], centres.min(axis=0) - RES / 2, atol=1e-9)
    assert back.origin[2] == 0.0
    image = _pgm(tmp_path / "intel.pgm")
    assert image.shape == back.cells.shape
    assert set(np.unique(image).tolist()) <= {0, 205, 254}
    top = np.argmax(centres[:, 1])
    col = round((centres[top, 0] - back.origin[0]) / RES - 0.5)
    pixel = {OCCUPIED: 0, FREE: 254, UNKNOWN: 205}[int(expected[top])]
    assert image[0, col] == pixel
    np.testing.assert_allclose(back.cell_centres().min(axis=0), centres.min(axis=0), atol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_occupancy_grid_is_the_pgm_as_map_server_loads_it(
    map2d: Path, map3d: Path, tmp_path: Path, dim: int
) -> None:
    """Every cell the PGM makes occupied is 100 (lethal) in the grid a ROS node publishes;
    free 0, unknown -1: cell for cell, with the same origin and size."""
    with OnlineMap.open(map2d if dim == 2 else map3d) as m:
        centres, prob = m.voxels()
        res = m.config.resolution
    option: dict[str, Any] = {} if dim == 2 else {"z_range": (0.1, 2.0)}
    grid = trinary_grid(centres, prob, res, **option)
    back = read_nav2_map(write_nav2_map(tmp_path / "m.pgm", centres, prob, res, **option))
    assert grid.data.dtype == np.int8
    np.testing.assert_array_equal(grid.data, back.cells)
    assert grid.origin == pytest.approx(back.origin[:2])
    assert grid.resolution == back.resolution
    occupied = back.cells == OCCUPIED
    assert occupied.sum() > 10
    assert np.all(grid.data[occupied] == 100)  # nav2's static layer: lethal at 100
    assert set(np.unique(grid.data).tolist()) <= {-1, 0, 100}


def test_yaml_is_what_map_server_reads(tmp_path: Path) -> None:
    yaml_lib = pytest.importorskip("yaml")
    centres = np.array([[0.05, 0.05], [0.15, 0.05], [0.05, 0.25]])
    yaml = write_nav2_map(tmp_path / "m.pgm", centres, [0.9, 0.1, 0.5], RES)
    doc = yaml_lib.safe_load(yaml.read_text())
    assert doc == {
        "image": "m.pgm",
        "mode": "trinary",
        "resolution": RES,
        "origin": [0.0, 0.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": LOAD_FREE_THRESH,
    }
    # 3 rows (y 0..0.3), 2 columns; top row y in [0.2, 0.3): only (0.05, 0.25), unknown
    np.testing.assert_array_equal(_pgm(tmp_path / "m.pgm"), [[205, 205], [205, 205], [0, 254]])
    # The loader's free_thresh must sit between the unknown (occ 0.196) and free pixels:
    # with nav2's old 0.25 the unknown cells would load as free.
    assert 1 - 254 / 255 < LOAD_FREE_THRESH < 1 - 205 / 255
    text = yaml.read_text().replace(f"free_thresh: {LOAD_FREE_THRESH}", "free_thresh: 0.25")
    yaml.write_text(text)
    assert (read_nav2_map(yaml).cells == UNKNOWN).sum() == 0


def test_cell_states_thresholds() -> None:
    prob = np.array([0.0, 0.2, 0.25, 0.3, 0.5, 0.6, 0.65, 0.7, 1.0])
    expected = [FREE, FREE, UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED, OCCUPIED]
    np.testing.assert_array_equal(cell_states(prob), expected)
    # P exactly 0.5 is no information, whatever the thresholds
    states = cell_states([0.5, 0.45], occupied_thresh=0.4, free_thresh=0.2)
    np.testing.assert_array_equal(states, [UNKNOWN, OCCUPIED])


@given(st.lists(st.sampled_from([0.0, 0.1, 0.4, 0.5, 0.55, 0.9, 1.0]), min_size=1, max_size=60))
def test_random_grids_round_trip(values: list[float]) -> None:
    import tempfile

    n = len(values)
    rng = np.random.default_rng(n)
    cells = rng.choice(100, size=n, replace=False)
    centres = (np.column_stack([cells % 10, cells // 10]) - 4.5) * 0.25 + 0.125
    with tempfile.TemporaryDirectory() as tmp:
        back = read_nav2_map(write_nav2_map(Path(tmp) / "g.pgm", centres, values, 0.25))
    np.testing.assert_array_equal(back.states_at(centres), cell_states(values))
    assert int((back.cells != UNKNOWN).sum()) == int((cell_states(values) != UNKNOWN).sum())


def test_3d_slice_and_projection() -> None:
    res = 1.0
    # four columns at x = 0.5, 1.5, 2.5, 3.5; voxels at z = 0.5, 1.5, 2.5
    centres = np.array(
        [[0.5, 0.5, z] for z in (0.5, 1.5, 2.5)]  # free, occupied, free
        + [[1.5, 0.5, z] for z in (0.5, 1.5, 2.5)]  # all free
        + [[2.5, 0.5, z] for z in (0.5, 1.5)]  # exactly 0.5 (unknown), uncertain
        + [[3.5, 0.5, 0.5], [3.5, 0.5, 1.5]]  # free, uncertain
    )
    prob = np.array([0.1, 0.9, 0.1, 0.1, 0.1, 0.1, 0.5, 0.55, 0.1, 0.55])
    states = cell_states(prob)
    xy, column = project_cells(centres, states, res, z_range=(0.0, 3.0))
    np.testing.assert_allclose(xy[:, 0], [0.5, 1.5, 2.5, 3.5])
    np.testing.assert_array_equal(column, [OCCUPIED, FREE, UNKNOWN, FREE])
    xy, column = project_cells(centres, states, res, z_range=(2.0, 3.0))  # above the box
    np.testing.assert_array_equal(column, [FREE, FREE])
    xy, layer = project_cells(centres, states, res, z=1.2)
    np.testing.assert_array_equal(layer, [OCCUPIED, FREE, UNKNOWN, UNKNOWN])


@pytest.mark.parametrize("scale", [1.0, 1e15])
def test_projection_merges_columns_as_a_brute_force_merge(scale: float) -> None:
    """Columns merged by packed keys (or, at huge coordinates, row by row) as a dict does."""
    rng = np.random.default_rng(7)
    centres = np.c_[rng.integers(-6, 6, (400, 2)) * scale + 0.5, rng.uniform(0, 3, 400)]
    states = rng.choice(np.array([UNKNOWN, FREE, OCCUPIED], dtype=np.int8), 400)
    xy, column = project_cells(centres, states, 1.0, z_range=(0.0, 3.0))
    best: dict[tuple[float, float], int] = {}
    rank = {UNKNOWN: 0, FREE: 1, OCCUPIED: 2}
    for (x, y, _), state in zip(centres.tolist(), states.tolist(), strict=True):
        key = (math.floor(x) + 0.5, math.floor(y) + 0.5)
        best[key] = max(best.get(key, 0), rank[state])
    expected = sorted(best)  # x, then y: the order of the output
    np.testing.assert_array_equal(xy, expected)
    np.testing.assert_array_equal(column, [[UNKNOWN, FREE, OCCUPIED][best[k]] for k in expected])


@pytest.mark.parametrize("kind", ["z", "z_range"])
def test_3d_map_round_trip(map3d: Path, tmp_path: Path, kind: str) -> None:
    with OnlineMap.open(map3d) as m:
        centres, prob = m.voxels()
    option: dict[str, Any] = {"z": -1.6} if kind == "z" else {"z_range": (-2.0, 1.0)}
    back = read_nav2_map(write_nav2_map(tmp_path / "s.pgm", centres, prob, 0.5, **option))
    xy, expected = project_cells(centres, cell_states(prob), 0.5, **option)
    np.testing.assert_array_equal(back.states_at(xy), expected)
    assert int((back.cells == OCCUPIED).sum()) == int((expected == OCCUPIED).sum()) > 0
    assert int((back.cells == FREE).sum()) == int((expected == FREE).sum()) > 0


# ---------------------------------------------------------------- nav2: malformed input


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"path": "m.png"}, "must end in .pgm"),
        ({"free_thresh": 0.7}, "free_thresh"),
        ({"occupied_thresh": 1.0}, "occupied_thresh"),
        ({"prob": [0.5, 1.5]}, "prob must lie in"),
        ({"prob": [0.5]}, "prob must have shape"),
        ({"centres": [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]}, "exactly one of z"),
        ({"z": 1.0}, "3D maps only"),
        ({"resolution": -1.0}, "resolution"),
    ],
)
def test_write_nav2_map_rejects(tmp_path: Path, kwargs: dict[str, Any], message: str) -> None:
    args: dict[str, Any] = {
        "path": "m.pgm",
        "centres": [[0.05, 0.05], [0.15, 0.05]],
        "prob": [0.9, 0.1],
        "resolution": RES,
    }
    args |= kwargs
    args["path"] = tmp_path / args["path"]
    with pytest.raises(OctolgpError, match=message):
        write_nav2_map(**args)


def test_project_cells_rejects() -> None:
    c3 = np.array([[0.5, 0.5, 0.5]])
    with pytest.raises(OctolgpError, match="zmin <= zmax"):
        project_cells(c3, [FREE], 1.0, z_range=(2.0, 1.0))
    with pytest.raises(OctolgpError, match="no voxel centre in z_range"):
        project_cells(c3, [FREE], 1.0, z_range=(3.0, 4.0))
    with pytest.raises(OctolgpError, match="no voxel in the height slice"):
        project_cells(c3, [FREE], 1.0, z=7.0)
    with pytest.raises(OctolgpError, match="states must be integers"):
        project_cells(c3, [0.5], 1.0, z=0.5)


@pytest.fixture
def small_map(tmp_path: Path) -> Path:
    return write_nav2_map(tmp_path / "m.pgm", [[0.05, 0.05], [0.15, 0.05]], [0.9, 0.1], RES)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("resolution: 0.1", "resolution 0.1"), r"m\.yaml:5: expected 'key: value'"),
        (("resolution: 0.1", "resolution: fine"), r"m\.yaml:5: resolution must be a number"),
        (("resolution: 0.1", "resolution: -0.1"), r"m\.yaml:5: resolution must be > 0"),
        (("resolution: 0.1\n", ""), r"m\.yaml: no 'resolution'"),
        (("origin: [0.0, 0.0, 0.0]", "origin: [0.0, 0.0"), r"m\.yaml:6: origin: unclosed list"),
        (("origin: [0.0, 0.0, 0.0]", "origin: [0.0, 0.0]"), r"m\.yaml:6: origin must be"),
        (("mode: trinary", "mode: raw"), r"m\.yaml:4: mode must be one of"),
        (("free_thresh: 0.196", "free_thresh: 0.9"), r"m\.yaml: need 0 <= free_thresh"),
        (("image: m.pgm\n", ""), r"m\.yaml: no 'image'"),
    ],
)
def test_read_nav2_map_rejects_bad_yaml(
    small_map: Path, edit: tuple[str, str], message: str
) -> None:
    text = small_map.read_text()
    assert edit[0] in text
    small_map.write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(OctolgpError, match=message):
        read_nav2_map(small_map)


def test_read_nav2_map_rejects_bad_images(small_map: Path) -> None:
    pgm = small_map.with_suffix(".pgm")
    data = pgm.read_bytes()
    pgm.write_bytes(data[:-1])
    with pytest.raises(OctolgpError, match=r"m\.pgm: byte \d+: truncated: 1 of 2 pixels"):
        read_nav2_map(small_map)
    pgm.write_bytes(b"P2\n2 1\n255\n0 254\n")
    with pytest.raises(OctolgpError, match=r"m\.pgm: byte 0: not a binary PGM"):
        read_nav2_map(small_map)
    pgm.write_bytes(b"P5\n2")
    with pytest.raises(OctolgpError, match="truncated header"):
        read_nav2_map(small_map)
    pgm.unlink()
    with pytest.raises(MapFileNotFound, match=r"m\.pgm"):
        read_nav2_map(small_map)
    with pytest.raises(MapFileNotFound, match="does not exist"):
        read_nav2_map(small_map.with_name("absent.yaml"))


# ---------------------------------------------------------------- PCD of occupied voxels


@pytest.mark.parametrize("binary", [True, False])
def test_pcd_round_trip(tmp_path: Path, binary: bool) -> None:
    rng = np.random.default_rng(1)
    centres = rng.uniform(-50, 50, (300, 3))
    prob = rng.uniform(0.5, 1.0, 300)
    out = tmp_path / "occ.pcd"
    write_pcd(out, centres, prob, binary=binary)
    (scan,) = list(read_pcd(out))
    np.testing.assert_array_equal(scan.points, centres.astype(np.float32))
    np.testing.assert_array_equal(scan.origin, 0.0)
    header = read_pcd_header(out)
    assert header.fields == ("x", "y", "z", "prob")
    assert header.data == ("binary" if binary else "ascii")
    # PCL's header order: VERSION FIELDS SIZE TYPE COUNT WIDTH HEIGHT VIEWPOINT POINTS DATA
    keys = [line.split()[0] for line in out.read_bytes().split(b"DATA")[0].decode().splitlines()]
    order = ["VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT"]
    assert [k for k in keys if not k.startswith("#")] == [*order, "POINTS"]
    if binary:
        raw = np.frombuffer(out.read_bytes()[header.data_offset :], dtype=header.dtype())
        np.testing.assert_array_equal(raw["f3"], prob.astype(np.float32))
    else:
        rows = np.loadtxt(out, skiprows=header.header_lines, ndmin=2)
        np.testing.assert_array_equal(rows[:, 3].astype(np.float32), prob.astype(np.float32))


def test_pcd_2d_empty_and_rejects(tmp_path: Path) -> None:
    write_pcd(tmp_path / "flat.pcd", [[1.0, 2.0]], [0.8])
    (scan,) = list(read_pcd(tmp_path / "flat.pcd"))
    np.testing.assert_array_equal(scan.points, [[1.0, 2.0, 0.0]])
    write_pcd(tmp_path / "empty.pcd", np.zeros((0, 3)), np.zeros(0))
    assert read_pcd_header(tmp_path / "empty.pcd").points == 0
    with pytest.raises(OctolgpError, match="prob must lie in"):
        write_pcd(tmp_path / "x.pcd", [[0.0, 0.0, 0.0]], [2.0])
    with pytest.raises(OctolgpError, match="centres must be"):
        write_pcd(tmp_path / "x.pcd", [[0.0, 0.0, 0.0, 0.0]], [0.5])
    with pytest.raises(OctolgpError, match="cannot be written"):
        write_pcd(tmp_path / "absent" / "x.pcd", [[0.0, 0.0, 0.0]], [0.5])


# ---------------------------------------------------------------- CLI


def test_cli_export_nav2_and_pcd(map2d: Path, map3d: Path, tmp_path: Path) -> None:
    pgm = tmp_path / "intel.pgm"
    assert main(["export", str(map2d), "--out", str(pgm)]) == 0
    with OnlineMap.open(map2d) as m:
        centres, prob = m.voxels()
    back = read_nav2_map(pgm.with_suffix(".yaml"))
    np.testing.assert_array_equal(back.states_at(centres), cell_states(prob))
    argv = ["export", str(map2d), "--out", str(pgm), "--overwrite", "--occupied-thresh", "0.8"]
    assert main([*argv, "--free-thresh", "0.1"]) == 0
    back = read_nav2_map(pgm.with_suffix(".yaml"))
    strict = cell_states(prob, occupied_thresh=0.8, free_thresh=0.1)
    np.testing.assert_array_equal(back.states_at(centres), strict)

    street = tmp_path / "street.pgm"
    assert main(["export", str(map3d), "--out", str(street), "--z-range", "-2", "1"]) == 0
    with OnlineMap.open(map3d) as m:
        c3, p3 = m.voxels()
    xy, expected = project_cells(c3, cell_states(p3), 0.5, z_range=(-2.0, 1.0))
    np.testing.assert_array_equal(
        read_nav2_map(street.with_suffix(".yaml")).states_at(xy), expected
    )
    assert main(["export", str(map3d), "--out", str(street), "--z", "-1.6", "--overwrite"]) == 0

    pcd = tmp_path / "street.pcd"
    assert main(["export", str(map3d), "--out", str(pcd), "--threshold", "0.7"]) == 0
    (scan,) = list(read_pcd(pcd))
    np.testing.assert_array_equal(scan.points, c3[p3 > 0.7].astype(np.float32))


@pytest.mark.parametrize(
    ("which", "extra", "message"),
    [
        ("3d", [], "needs --z HEIGHT"),
        ("3d", ["--z-range", "1", "0"], "zmin <= zmax"),
        ("3d", ["--z", "1", "--z-range", "0", "1"], "not allowed with argument"),
        ("2d", ["--z", "0"], "apply to 3D maps only"),
        ("2d", ["--free-thresh", "0.7"], "--free-thresh (0.7) must be below"),
    ],
)
def test_cli_export_bad_input_exit_2(
    map2d: Path,
    map3d: Path,
    tmp_path: Path,
    which: str,
    extra: list[str],
    message: str,
    cli_exit_2: Callable[..., str],
) -> None:
    source = map3d if which == "3d" else map2d
    argv = ["export", str(source), "--out", str(tmp_path / "x.pgm"), *extra]
    if which == "3d" and not extra:  # once through a real process: one line, no traceback
        cli_exit_2(argv, tmp_path, message)
        return
    try:
        status = main(argv)
    except SystemExit as exc:  # argparse's own errors
        status = int(exc.code or 0)
    assert status == 2
    assert not (tmp_path / "x.pgm").exists()


def test_cli_export_messages(
    map2d: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(["export", str(map2d), "--out", str(tmp_path / "x.pgm"), "--z-range", "0", "1"]) == 2
    )
    assert (
        main(["export", str(map2d), "--out", str(tmp_path / "x.png"), "--z-range", "0", "1"]) == 2
    )
    err = capsys.readouterr().err.splitlines()
    assert "--z and --z-range apply to 3D maps only" in err[0]
    assert "--z-range applies to a nav2 map (--out FILE.pgm) only" in err[1]
