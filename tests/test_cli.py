"""End to end: the CLI and the paper benchmark on small inputs."""

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from octolgp.bench.fig2 import run_fig2
from octolgp.cli import main
from octolgp.io import load_scans, read_truth


def test_simulate_writes_scan_log_with_truth(tmp_path: Path) -> None:
    out = tmp_path / "p.npz"
    assert main(["simulate", "paper2d", "--out", str(out), "--seed", "3"]) == 0
    scans = list(load_scans(out))
    assert len(scans) == 28
    assert 1200 <= sum(len(s) for s in scans) <= 1400
    points, labels = read_truth(out)
    assert points.shape == (9900, 2)
    assert set(np.unique(labels)) == {0, 1}


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "paper2d", "--out", "x.txt"],
        ["simulate", "paper2d", "--out", "/proc/forbidden/x.npz"],
    ],
)
def test_bad_input_exits_2_with_one_line(
    argv: list[str], tmp_path: Path, cli_exit_2: Callable[..., str]
) -> None:
    cli_exit_2(argv, tmp_path)


def test_version_is_eager(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert "octolgp" in capsys.readouterr().out


def test_fig2_overlap_halves_the_border_jump(tmp_path: Path) -> None:
    r = run_fig2(tmp_path / "fig2.png")
    assert r.jump_overlap <= 0.5 * r.jump_disjoint
    assert r.jump_disjoint > 0.01  # disjoint local GPs really do jump
    assert r.rmse_overlap <= r.rmse_disjoint
    assert (tmp_path / "fig2.png").stat().st_size > 0


def test_bench_paper2d_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench"
    assert main(["bench", "paper2d", "--out", str(out), "--repeats", "1", "--seeds", "1"]) == 0
    text = capsys.readouterr().out
    for name in ("OM_LGP", "OM_GP", "OM_MGP", "OGM", "sigma_f", "border jump"):
        assert name in text
    for png in ("fig3_maps.png", "fig4_roc.png", "fig2_1d.png"):
        assert (out / png).stat().st_size > 1000
    table = (out / "table2.txt").read_text()
    auc_lgp = float(
        next(line for line in table.splitlines() if line.startswith("OM_LGP")).split()[-1]
    )
    assert auc_lgp > 0.97


INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"


def test_run_then_query_reads_the_map(tmp_path: Path) -> None:
    from octolgp import OnlineMap

    out = tmp_path / "m.octolgp"
    argv = ["run", str(INTEL20), "--out", str(out), "--learn-scans", "5", "--quiet"]
    assert main([*argv, "--limit", "12"]) == 0
    with OnlineMap.open(out) as m:
        assert m.n_scans == 12
        centres, prob = m.occupied_voxels(0.5)
        assert centres.shape[0] > 50
    pts = tmp_path / "q.npy"
    np.save(pts, np.vstack([centres[:10], [[500.0, 500.0]]]))
    probs = tmp_path / "p.npy"
    assert main(["query", str(out), "--points", str(pts), "--out", str(probs)]) == 0
    got = np.load(probs)
    # default: the continuous (interpolated) map, equal to the voxel value at its centre
    np.testing.assert_allclose(got[:10], prob[:10], rtol=0, atol=1e-5)
    assert got[10] == 0.5
    argv_q = [
        "query",
        str(out),
        "--points",
        str(pts),
        "--out",
        str(probs),
        "--nearest",
        "--overwrite",
    ]
    assert main(argv_q) == 0
    got = np.load(probs)
    assert np.array_equal(got[:10], prob[:10])
    assert got[10] == 0.5
    # an existing map is never overwritten silently
    assert main(argv) == 2
    assert main([*argv, "--overwrite"]) == 0
    with OnlineMap.open(out) as m:
        assert m.n_scans == 20


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "missing.log", "--out", "m.octolgp"],
        ["run", "bad.log", "--out", "m.octolgp"],
        ["run", "bad.log", "--out", "m.octolgp", "--resolution", "-1"],
        ["query", "missing.octolgp", "--points", "q.npy", "--out", "p.npy"],
        ["query", "bad.log", "--points", "bad.log", "--out", "p.npy"],
    ],
)
def test_run_and_query_bad_input_exit_2(
    argv: list[str], tmp_path: Path, cli_exit_2: Callable[..., str]
) -> None:
    (tmp_path / "bad.log").write_text("FLASER 3 1.0 1.0\n")
    cli_exit_2(argv, tmp_path, prefix="octolgp")  # argparse's: "octolgp run: error: ..."


def test_run_skip_bad_skips_and_counts_malformed_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = INTEL20.read_text().splitlines(keepends=True)
    laser = [i for i, line in enumerate(lines) if line.startswith("FLASER")]
    lines[laser[3]] = "FLASER 180 1.0 2.0 oops\n"
    bad = tmp_path / "bad.log"
    bad.write_text("".join(lines))
    out = tmp_path / "m.octolgp"
    argv = ["run", str(bad), "--out", str(out), "--learn-scans", "3", "--quiet", "--limit", "8"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert f"bad.log:{laser[3] + 1}" in err[0]
    assert main([*argv, "--overwrite", "--skip-bad", "--limit", "30"]) == 0
    err = capsys.readouterr().err
    assert "skipped 1 malformed" in err
    from octolgp import OnlineMap

    with OnlineMap.open(out) as m:
        assert m.n_scans == len(laser) - 1


@pytest.mark.parametrize(
    "fixture", ["rosbag/intel.bag", "pointcloud/scan_nodes.dat", "pointcloud/cloud_binary.pcd"]
)
def test_run_maps_every_loader_format(tmp_path: Path, fixture: str) -> None:
    from octolgp import OnlineMap, load_scans

    src = INTEL20.parent / fixture
    out = tmp_path / "m.octolgp"
    argv = ["run", str(src), "--out", str(out), "--resolution", "0.2", "--quiet"]
    assert main([*argv, "--learn-scans", "2"]) == 0
    with OnlineMap.open(out) as m:
        assert m.n_scans == len(list(load_scans(src)))
        assert m.occupied_voxels(0.5)[0].shape[0] > 0
