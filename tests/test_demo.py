"""The demo (``make demo``: examples/intel_lab.py) on the first scans of the Intel log."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from PIL import Image

from octolgp.errors import OctolgpError
from octolgp.export.image import UNKNOWN_GREY, floor_plan, write_floor_plan
from octolgp.export.nav2 import cell_states
from octolgp.export.nav2_read import read_nav2_map
from octolgp.export.octomap_read import decode_bt, read_bt_header
from octolgp.io.rrd_read import read_rrd
from octolgp.mapping.online import OnlineMap

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "intel_lab.py"
SCANS = 10  # the first scans of the log: about 15 s on one core


def _example() -> ModuleType:
    spec = importlib.util.spec_from_file_location("intel_lab_example", EXAMPLE)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_demo_writes_every_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    example = _example()
    assert example.main(["--out", str(tmp_path), "--limit", str(SCANS)]) == 0
    assert f"mapped {SCANS} scans" in capsys.readouterr().out
    names = {p.name for p in tmp_path.iterdir()}
    stem = "intel_lab"
    expected = {f"{stem}.{ext}" for ext in ("octolgp", "rrd", "png", "bt", "pgm", "yaml")}
    assert expected | {f"{stem}.octolgp.toml"} <= names

    with OnlineMap.open(tmp_path / f"{stem}.octolgp") as m:
        assert m.n_scans == SCANS
        res = m.config.resolution
        assert (m.config.dim, res) == (2, 0.1)
        low, high = example.hits_box(m)
        # The floor plan: one pixel per cell of the box, north up, exactly the map's P.
        with Image.open(tmp_path / f"{stem}.png") as png:
            assert png.mode == "L"
            image = np.asarray(png)
        nx, ny = (np.rint((high - low) / res).astype(int) + 1).tolist()
        assert image.shape == (ny, nx)
        rows, cols = np.array([0, ny // 3, ny - 1]), np.array([nx - 1, nx // 2, 0])
        centres = np.column_stack([low[0] + cols * res, low[1] + (ny - 1 - rows) * res])
        p = m.occupancy(centres)
        want = np.where(p == 0.5, UNKNOWN_GREY, np.rint(255 * (1 - p)))
        np.testing.assert_array_equal(image[rows, cols], want)
        assert image.min() < 40
        assert image.max() > 215
        assert (image == UNKNOWN_GREY).any()

        voxels, prob = m.voxels()
        # OctoMap: the header and every node decode with octolgp's reference reader.
        header = read_bt_header(tmp_path / f"{stem}.bt")
        assert (header["kind"], header["res"]) == ("bt", res)
        _, occupied, _ = decode_bt(tmp_path / f"{stem}.bt")
        assert occupied.any()
        assert not occupied.all()
        # nav2: both files read back as map_server does, cell states as the map's.
        nav = read_nav2_map(tmp_path / f"{stem}.yaml")
        assert nav.resolution == res
        assert nav.mode == "trinary"
        pick = np.linspace(0, len(prob) - 1, 500).astype(int)
        np.testing.assert_array_equal(nav.states_at(voxels[pick]), cell_states(prob[pick]))

    # The Rerun recording replays into the scans that were mapped.
    assert len(list(read_rrd(tmp_path / f"{stem}.rrd"))) == SCANS


def test_floor_plan_is_north_up_with_grey_unknown(tmp_path: Path) -> None:
    def occupancy(points: np.ndarray) -> np.ndarray:
        # Occupied north of y = 1, free south of it, unknown west of x = 0.
        p = np.where(points[:, 1] > 1.0, 0.9, 0.1)
        return np.where(points[:, 0] < 0.0, 0.5, p)

    calls: list[int] = []

    def counted(points: np.ndarray) -> np.ndarray:
        calls.append(len(points))
        return occupancy(points)

    image = floor_plan(counted, [-0.95, 0.05], [0.95, 1.95], 0.1, chunk=40)
    assert image.shape == (20, 20)
    assert image.dtype == np.uint8
    assert max(calls) <= 40
    assert sum(calls) == 400
    assert (image[:, :10] == UNKNOWN_GREY).all()
    assert (image[:10, 10:] == np.rint(255 * (1 - 0.9))).all()  # north (top rows): dark
    assert (image[10:, 10:] == np.rint(255 * (1 - 0.1))).all()  # south: free, light
    write_floor_plan(tmp_path / "plan.png", image)
    with Image.open(tmp_path / "plan.png") as png:
        np.testing.assert_array_equal(np.asarray(png), image)
    with pytest.raises(OctolgpError, match="below low"):
        floor_plan(occupancy, [1.0, 1.0], [0.0, 0.0], 0.1)
    with pytest.raises(OctolgpError, match="uint8"):
        write_floor_plan(tmp_path / "x.png", image.astype(float))
