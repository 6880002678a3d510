"""Config files: MapConfig <-> TOML, ``--config`` on run/replay/build/eval, ``dump-config``."""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from pathlib import Path

import pytest

from octolgp.cli import main
from octolgp.config import Hyperparameters, MapConfig, OgmConfig, OnlineConfig, TrainingConfig
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.mapping.online import OnlineMap

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"

NON_DEFAULT = MapConfig(
    dim=2,
    resolution=0.05,
    hyperparameters=Hyperparameters(length_scale=0.4, noise_variance=0.05, beta=-0.25),
    memory_budget_mb=128.5,
    tree_depth=15,
    training=TrainingConfig(free_margin=0.02, dedup=False, max_quadrature_nodes=17),
    ogm=OgmConfig(prob_hit=0.8),
    online=OnlineConfig(engine="exact", clear_scans=0, halo=0.3, learn_scans=7, n_jobs=2),
)

FILE = """\
resolution = 0.2

[online]
halo = 0.25
learn_scans = 3

[hyperparameters]  # given: the CLI tests learn nothing
length_scale = 1.0
signal_variance = 5.0
alpha = 5.0
beta = 1.5
"""


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --- MapConfig <-> TOML -------------------------------------------------------------------------


@pytest.mark.parametrize("config", [MapConfig(), NON_DEFAULT], ids=["defaults", "non-default"])
def test_config_toml_config_round_trip(config: MapConfig, tmp_path: Path) -> None:
    text = config.to_toml()
    back = MapConfig.from_toml(_write(tmp_path / "c.toml", text))
    assert back == config
    assert back.to_toml() == text  # TOML -> config -> TOML


def test_partial_file_keeps_its_values_and_fills_defaults(tmp_path: Path) -> None:
    config = MapConfig.from_toml(_write(tmp_path / "c.toml", FILE))
    assert config.resolution == 0.2
    assert config.online.halo == 0.25
    assert config.online.learn_scans == 3
    assert config.online.engine == OnlineConfig().engine
    dumped = tomllib.loads(config.to_toml())
    assert dumped["resolution"] == 0.2
    assert dumped["online"]["halo"] == 0.25
    assert dumped["online"]["learn_scans"] == 3
    assert set(dumped) >= {"dim", "training", "partition", "learning", "ogm", "online"}
    assert MapConfig.from_toml(_write(tmp_path / "d.toml", config.to_toml())) == config


BAD_FILES = [
    ("[online]\nclear_scan = 3\n", r"online\.clear_scan: unknown key \(keys: engine, leaf_depth, "),
    ("resolutoin = 0.1\n", r"resolutoin: unknown key"),
    ("[hyperparameters]\nsigma = 1.0\n", r"hyperparameters\.sigma: unknown key"),
    ("[nav]\nx = 1\n", r"nav: unknown key"),
    ("[online]\nhalo = -1.0\n", r"online\.halo must be"),
    ("[ogm]\nprob_hit = 'high'\n", r"ogm\.prob_hit must be"),
    ("resolution = -0.1\n", r"c\.toml': resolution must be a finite number > 0"),
    ("online = 3\n", r"online: must be a table of OnlineConfig fields"),
    ("[online]\nengine = 'fast'\n", r"online\.engine"),
    ("resolution = \n", r"is not valid TOML"),
]


@pytest.mark.parametrize(("text", "why"), BAD_FILES)
def test_bad_file_names_the_file_and_the_key(text: str, why: str, tmp_path: Path) -> None:
    path = _write(tmp_path / "c.toml", text)
    with pytest.raises(OctolgpError, match=why) as exc:
        MapConfig.from_toml(path)
    assert str(path) in str(exc.value)


def test_missing_file_and_from_dict_names() -> None:
    with pytest.raises(MapFileNotFound, match="does not exist"):
        MapConfig.from_toml("/nonexistent/c.toml")
    with pytest.raises(OctolgpError, match=r"MapConfig\.online\.clear_scan: unknown key"):
        MapConfig.from_dict({"online": {"clear_scan": 1}})


# --- the command line ---------------------------------------------------------------------------


def test_dump_config_defaults_file_and_flags(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dump-config"]) == 0
    dumped = tomllib.loads(capsys.readouterr().out)
    assert MapConfig.from_dict(dumped) == MapConfig().resolve()
    assert dumped["online"]["leaf_depth"] == 12  # every derived default, filled in
    assert dumped["lattice"]["tile_voxels"] == 4
    assert dumped["lattice"]["clear_margin"] == pytest.approx(0.5)
    path = _write(tmp_path / "c.toml", FILE)
    argv = [
        "dump-config",
        "--config",
        str(path),
        "--resolution",
        "0.3",
        "--dim",
        "2",
        "--jobs",
        "3",
    ]
    assert main(argv) == 0
    got = MapConfig.from_dict(tomllib.loads(capsys.readouterr().out))
    assert got.resolution == 0.3  # the flag wins over the file
    assert got.dim == 2
    assert got.online.n_jobs == 3
    assert got.online.halo == 0.25  # the file wins over the defaults
    assert got.online.learn_scans == 3
    assert main(["dump-config", "--config", str(path), "--learn-scans", "9"]) == 0
    assert tomllib.loads(capsys.readouterr().out)["online"]["learn_scans"] == 9


def test_bad_config_exits_2_with_one_line(tmp_path: Path, cli_exit_2: Callable[..., str]) -> None:
    _write(tmp_path / "bad.toml", "resolution = 0.1\n[online]\nclear_scan = 3\n")
    argv = ["run", str(INTEL20), "--out", "m.octolgp", "--config", "bad.toml"]
    line = cli_exit_2(argv, tmp_path)
    assert line.startswith("octolgp: error: config file 'bad.toml': online.clear_scan: ")
    assert not (tmp_path / "m.octolgp").exists()


@pytest.mark.parametrize(
    ("argv", "why"),
    [
        (["dump-config", "--config", "bad.toml"], "bad.toml': online.clear_scan: unknown key"),
        (["dump-config", "--config", "missing.toml"], "'missing.toml' does not exist"),
        (["build", str(INTEL20), "--out", "m.octolgp", "--config", "bad.toml"], "unknown key"),
        (["eval", str(INTEL20), "--out", "ev", "--config", "bad.toml"], "unknown key"),
        (
            [
                "run",
                str(INTEL20),
                "--out",
                "m.octolgp",
                "--resolution",
                "0.1",
                "--config",
                "bad.toml",
            ],
            "unknown key",
        ),
    ],
)
def test_bad_config_is_one_line_naming_the_key(
    argv: list[str],
    why: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.chdir(tmp_path)
    _write(tmp_path / "bad.toml", "resolution = 0.1\n[online]\nclear_scan = 3\n")
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("octolgp: error:")
    assert why in lines[0]
    assert not (tmp_path / "m.octolgp").exists()
    assert not (tmp_path / "ev").exists()


def test_run_and_replay_take_the_file_and_write_the_resolved_config(tmp_path: Path) -> None:
    cfg = _write(tmp_path / "c.toml", FILE)
    out = tmp_path / "m.octolgp"
    rec = tmp_path / "m.rrd"
    argv = ["run", str(INTEL20), "--out", str(out), "--config", str(cfg), "--quiet"]
    assert main([*argv, "--resolution", "0.15", "--limit", "3", "--rerun-save", str(rec)]) == 0
    with OnlineMap.open(out) as m:
        stored = m.config
    assert stored.resolution == 0.15  # the flag
    assert stored.online.halo == 0.25  # the file
    assert stored.online.learn_scans == 3
    assert stored.dim == 2  # the data
    assert MapConfig.from_toml(tmp_path / "m.octolgp.toml") == stored

    replayed = tmp_path / "r.octolgp"
    assert main(["replay", str(rec), "--out", str(replayed), "--config", str(cfg), "--quiet"]) == 0
    written = MapConfig.from_toml(tmp_path / "r.octolgp.toml")
    assert written.resolution == 0.2
    assert written.online.halo == 0.25


def test_the_users_config_file_is_never_rewritten(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, written = tmp_path / "m.octolgp", tmp_path / "m.octolgp.toml"
    argv = ["run", str(INTEL20), "--out", str(out), "--limit", "3", "--quiet", "--overwrite"]
    assert main([*argv, "--config", str(_write(tmp_path / "c.toml", FILE))]) == 0
    text = written.read_text()
    # reproducing a map from the config written beside it leaves that file as it is
    assert main([*argv, "--config", str(written)]) == 0
    assert written.read_text() == text
    capsys.readouterr()
    assert main([*argv, "--config", str(written), "--resolution", "0.3"]) == 2
    assert "would overwrite --config" in capsys.readouterr().err
    assert written.read_text() == text


def test_build_and_eval_write_the_resolved_config(tmp_path: Path) -> None:
    cfg = _write(tmp_path / "c.toml", FILE)
    out = tmp_path / "b.octolgp"
    argv = ["build", str(INTEL20), "--out", str(out), "--config", str(cfg), "--method", "ogm"]
    assert main([*argv, "--limit", "3", "--quiet"]) == 0
    built = MapConfig.from_toml(tmp_path / "b.octolgp.toml")
    assert built.resolution == 0.2
    assert built.online.halo == 0.25
    folder = tmp_path / "ev"
    argv = ["eval", str(INTEL20), "--out", str(folder), "--config", str(cfg), "--quiet"]
    argv += ["--limit", "12", "--seeds", "1", "--methods", "grid", "--resolution", "0.25"]
    assert main(argv) == 0
    evaluated = MapConfig.from_toml(folder / "config.toml")
    assert evaluated.resolution == 0.25
    assert evaluated.online.learn_scans == 3
