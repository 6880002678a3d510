"""``octolgp info MAP``: what a map file holds, read without changing it."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path

import pytest

from octolgp import OnlineMap
from octolgp.cli.main import main
from octolgp.cli.maps import map_info

INTEL20 = Path(__file__).resolve().parent / "data" / "intel_first20.log"


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("info") / "m.octolgp"
    argv = ["run", str(INTEL20), "--out", str(out), "--learn-scans", "5", "--quiet"]
    assert main([*argv, "--free-range", "12"]) == 0
    return out


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_info_tells_what_the_file_holds_and_changes_nothing(
    mapped: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = _digest(mapped)
    assert main(["info", str(mapped), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert _digest(mapped) == before
    with OnlineMap.open(mapped, read_only=True) as m:
        assert info["dim"] == 2
        assert info["resolution"] == m.config.resolution
        assert info["scans"] == m.n_scans == 20
        assert info["leaves"] == len(m.store)
        assert info["journal"] == [1, 20]
        assert info["free_range"] == 12.0
        assert info["hyperparameters"]["length_scale"] == m.hyperparameters.length_scale
        centres, _ = m.voxels()
    (xlo, xhi), (ylo, yhi) = info["extent"]
    assert xlo <= centres[:, 0].min()
    assert centres[:, 0].max() <= xhi
    assert ylo <= centres[:, 1].min()
    assert centres[:, 1].max() <= yhi
    assert info["file_bytes"] >= mapped.stat().st_size
    assert map_info(mapped) == info
    assert main(["info", str(mapped)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "dim: 2"
    assert any(line.startswith("hyperparameters: length_scale=") for line in lines)


@pytest.mark.parametrize("name", ["missing.octolgp", "not_a_map.txt"])
def test_info_on_a_bad_file_exits_2(
    name: str, tmp_path: Path, cli_exit_2: Callable[..., str]
) -> None:
    path = tmp_path / name
    if name.endswith(".txt"):
        path.write_text("hello\n")
    cli_exit_2(["info", str(path)], tmp_path, str(path))
