"""Exports in bounded chunks: the streamed files equal the ones written from whole arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
from octolgp.cli.main import main
from octolgp.export.pcd import write_pcd, write_pcd_chunks
from octolgp.export.ply import write_ply, write_ply_chunks

INTEL20 = Path(__file__).resolve().parent / "data" / "intel_first20.log"
HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.04, alpha=5.0)


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("chunks") / "m.octolgp"
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP), path=path) as m:
        m.insert_scans(list(load_scans(INTEL20)))
    return path


def test_voxel_chunks_are_the_voxels_in_pieces(mapped: Path) -> None:
    with OnlineMap.open(mapped, read_only=True) as m:
        centres, prob = m.voxels()
        chunks = list(m.voxel_chunks(size=1000))
    assert len(chunks) > 3
    assert all(c.shape[0] < 1000 + m.grid.voxels_per_leaf for c, _ in chunks)
    np.testing.assert_array_equal(np.concatenate([c for c, _ in chunks]), centres)
    np.testing.assert_array_equal(np.concatenate([p for _, p in chunks]), prob)


@pytest.mark.parametrize("binary", [True, False])
def test_streamed_point_clouds_equal_the_whole_ones(
    mapped: Path, tmp_path: Path, binary: bool
) -> None:
    with OnlineMap.open(mapped, read_only=True) as m:
        centres, prob = m.voxels()
        chunks = list(m.voxel_chunks(size=700))
    for whole, streamed, ext in (
        (write_ply, write_ply_chunks, "ply"),
        (write_pcd, write_pcd_chunks, "pcd"),
    ):
        a, b = tmp_path / f"a.{ext}", tmp_path / f"b.{ext}"
        whole(a, centres, prob, binary=binary)
        assert streamed(b, iter(chunks), binary=binary) == centres.shape[0]
        assert a.read_bytes() == b.read_bytes()


def test_cli_export_streams_the_occupied_voxels(mapped: Path, tmp_path: Path) -> None:
    with OnlineMap.open(mapped, read_only=True) as m:
        centres, prob = m.voxels()
    keep = prob > 0.5
    for ext, whole in (("ply", write_ply), ("pcd", write_pcd)):
        out, want = tmp_path / f"m.{ext}", tmp_path / f"want.{ext}"
        assert main(["export", str(mapped), "--out", str(out)]) == 0
        whole(want, centres[keep], prob[keep])
        assert out.read_bytes() == want.read_bytes()
    leftovers = [
        p for p in tmp_path.iterdir() if p.name not in {"m.ply", "m.pcd", "want.ply", "want.pcd"}
    ]
    assert not leftovers  # the records' temporary file is gone
