"""``octolgp eval`` and :mod:`octolgp.bench.evaluation`: the held-out protocol for all methods."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from octolgp import (
    MapConfig,
    OctolgpError,
    TrainingConfig,
    build_map,
    learn_hyperparameters,
    load_scans,
)
from octolgp.bench.evaluation import METHODS, evaluate_log, plot_roc
from octolgp.bench.heldout import auc, heldout_points, heldout_split, unknown_fraction
from octolgp.bench.octomap_ref import octomap_available
from octolgp.cli import main
from octolgp.mapping.evidence import map_scans

DATA = Path(__file__).parent / "data"
INTEL20 = DATA / "intel_first20.log"


@pytest.fixture(scope="module")
def intel20() -> list:
    return list(load_scans(INTEL20))


@pytest.fixture(scope="module")
def report(intel20: list):
    config = MapConfig(dim=2, resolution=0.2)
    return evaluate_log(intel20, config, seeds=2, fraction=0.2, run=2, methods=METHODS)


def test_report_holds_every_method_and_split(intel20: list, report) -> None:
    expected = ["online", "batch", "grid"] + (["octomap"] if octomap_available() else [])
    assert list(report.results) == expected
    assert report.splits == ["seed 0", "seed 1"]
    for rows in report.results.values():
        assert len(rows) == 2
        for r in rows:
            assert 0.5 < r.auc <= 1.0
            assert 0.0 <= r.unknown_fraction < 0.5
            assert r.seconds >= 0.0
            assert np.all(np.diff(r.tpr) >= 0)
            assert r.fpr[0] == 0.0
            assert r.fpr[-1] == 1.0
    s = report.summary()
    aucs = [r.auc for r in report.results["online"]]
    assert s["online"]["auc_mean"] == pytest.approx(np.mean(aucs))
    assert s["online"]["auc_std"] == pytest.approx(np.std(aucs))
    # with the grid's sensor model (no-returns whole) the GP maps fill gaps a grid leaves
    # unknown; the default no-return range (10 m) leaves more unknown than the grid there
    whole = MapConfig(dim=2, resolution=0.2, training=TrainingConfig(no_return_range=math.inf))
    like = evaluate_log(intel20, whole, seeds=2, fraction=0.2, run=2, methods=("batch", "grid"))
    t = like.summary()
    assert t["batch"]["unknown_mean"] <= t["grid"]["unknown_mean"]
    assert t["grid"]["unknown_mean"] == s["grid"]["unknown_mean"]  # the grid's own model


def test_grid_numbers_equal_the_protocol_done_by_hand(intel20: list, report) -> None:
    """Split, test points and scoring reproduce exactly from the documented protocol."""
    config = MapConfig(dim=2, resolution=0.2)
    for index, seed in enumerate((0, 1)):
        train_idx, test_idx = heldout_split(len(intel20), fraction=0.2, run=2, seed=seed)
        pts, labels = heldout_points(
            [intel20[i] for i in test_idx], np.random.default_rng(index), 1, 0.1
        )
        assert report.n_points[index] == labels.size
        assert report.n_occupied[index] == int(labels.sum())
        grid = build_map([intel20[i] for i in train_idx], config, method="ogm")
        probs = grid.occupancy(pts)
        assert report.results["grid"][index].auc == auc(labels, probs)
        assert report.results["grid"][index].unknown_fraction == unknown_fraction(probs)
        # every GP method used the hyperparameters learnt on the first training scans,
        # rounded as a map keeps them (OnlineConfig.scan_precision)
        first = [intel20[i] for i in train_idx][:40]
        hp = learn_hyperparameters(map_scans(first, config), config)
        assert report.hyperparameters[index] == hp
    assert len(report.novel) == len(report.splits)
    assert all(0.0 <= x <= 1.0 for x in report.novel)
    assert len(report.seen_free) == len(report.splits)
    assert all(0.0 <= s <= n for s, n in zip(report.seen_free, report.novel, strict=True))
    spread = report.hyperparameter_spread()
    lengths = [hp.length_scale for hp in report.hyperparameters]
    assert spread["length_scale"] == (np.mean(lengths), np.std(lengths))
    assert set(spread) == {"length_scale", "signal_variance", "noise_variance", "alpha", "beta"}
    assert "- length_scale: " in report.table()


def test_online_result_matches_a_direct_online_map(intel20: list, report) -> None:
    from octolgp import OnlineMap

    config = MapConfig(dim=2, resolution=0.2)
    train_idx, test_idx = heldout_split(len(intel20), fraction=0.2, run=2, seed=1)
    pts, labels = heldout_points([intel20[i] for i in test_idx], np.random.default_rng(1), 1, 0.1)
    m = OnlineMap(dataclasses.replace(config, hyperparameters=report.hyperparameters[1]))
    m.insert_scans([intel20[i] for i in train_idx])
    assert report.results["online"][1].auc == auc(labels, m.occupancy(pts))


def test_pictures_show_the_worst_split_of_the_first_gp_method(report) -> None:
    aucs = [r.auc for r in report.results["online"]]
    example = report.example
    assert example is not None
    assert example.method == "online"
    assert example.split == report.splits[int(np.argmin(aucs))]
    assert example.auc == min(aucs)
    assert auc(example.labels, example.scores) == example.auc


def test_leave_one_out_holds_out_each_scan_once(intel20: list) -> None:
    config = MapConfig(dim=2, resolution=0.2)
    rep = evaluate_log(intel20[:4], config, leave_one_out=True, methods=["grid"])
    assert rep.splits == ["scan 0", "scan 1", "scan 2", "scan 3"]
    for i, n in enumerate(rep.n_points):
        _, labels = heldout_points([intel20[i]], np.random.default_rng(i), 1, 0.1)
        assert n == labels.size


def test_roc_plot_is_written(report, tmp_path: Path) -> None:
    out = tmp_path / "sub" / "roc.png"
    plot_roc(report, out, title="intel 20")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    json.dumps(report.to_dict())  # serialisable


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"methods": ["online", "kriging"]}, "methods"),
        ({"methods": []}, "methods"),
        ({"methods": "online"}, "methods"),
        ({"seeds": 0}, "seeds"),
        ({"downsample": -1.0}, "downsample"),
        ({"fraction": 1.5}, "fraction"),
    ],
)
def test_bad_arguments_are_refused(intel20: list, kwargs: dict, field: str) -> None:
    with pytest.raises(OctolgpError, match=field):
        evaluate_log(intel20, MapConfig(dim=2, resolution=0.2), **kwargs)


def test_too_few_or_wrong_dimension_scans_are_refused(intel20: list) -> None:
    with pytest.raises(OctolgpError, match="at least 2 scans"):
        evaluate_log(intel20[:1], MapConfig(dim=2))
    with pytest.raises(OctolgpError, match="dimension 3"):
        evaluate_log(intel20, MapConfig(dim=3))


def test_cli_eval_writes_table_roc_and_json(tmp_path: Path, capsys) -> None:
    out = tmp_path / "ev"
    argv = ["eval", str(INTEL20), "--seeds", "1", "--methods", "grid,batch", "--quiet"]
    assert main([*argv, "--resolution", "0.2", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "| grid (ogm) |" in table
    assert "| octolgp batch (lgp) |" in table
    assert (out / "roc.png").is_file()
    data = json.loads((out / "results.json").read_text())
    assert set(data["summary"]) == {"batch", "grid"}


def test_cli_eval_hilbert_protocol(tmp_path: Path, capsys) -> None:
    out = tmp_path / "ev"
    argv = ["eval", str(INTEL20), "--seeds", "2", "--methods", "grid", "--quiet"]
    assert main([*argv, "--protocol", "hilbert", "--resolution", "0.2", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "hilbert protocol" in table
    assert "worst split" in table
    data = json.loads((out / "results.json").read_text())
    assert data["summary"]["grid"]["auc_worst"] <= data["summary"]["grid"]["auc_mean"]
    # more free points than the endpoint protocol: max(1, int(d/2)) per return
    endpoint = tmp_path / "ep"
    assert main([*argv, "--resolution", "0.2", "--out", str(endpoint)]) == 0
    capsys.readouterr()
    points = json.loads((endpoint / "results.json").read_text())["n_points"]
    assert sum(data["n_points"]) > sum(points)


def test_cli_eval_draws_the_map_and_its_errors(tmp_path: Path, capsys) -> None:
    from octolgp.bench.evaluation import plot_errors

    out = tmp_path / "ev"
    argv = ["eval", str(INTEL20), "--seeds", "1", "--methods", "online,grid", "--quiet"]
    assert main([*argv, "--fast-online", "--resolution", "0.2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for picture in ("roc.png", "map.png", "errors.png"):
        assert (out / picture).stat().st_size > 10_000
        assert picture in printed
    # a 3D example is drawn as a slice
    from octolgp.bench.evaluation import ExampleSplit

    rng = np.random.default_rng(0)
    centres = (np.stack(np.meshgrid(*[np.arange(10)] * 3), -1).reshape(-1, 3) + 0.5) * 0.2
    points = rng.uniform(0, 2, (200, 3))
    labels = (points[:, 0] > 1).astype(np.int8)
    example = ExampleSplit(
        "seed 0", "online", 0.2, centres, rng.random(1000), points, labels, rng.random(200)
    )
    plot_errors(example, tmp_path / "e3.png")
    assert (tmp_path / "e3.png").stat().st_size > 10_000


def _exit_code(argv: list[str]) -> int:
    """``main``'s status, whether it returns it or argparse raises SystemExit."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--methods", "grid,kriging"], "methods"),
        (["--fraction", "1.0"], "--fraction"),
        (["--short", "nan"], "--short"),
        (["--seeds", "0"], "--seeds"),
        (["--protocol", "grid"], "--protocol"),
    ],
)
def test_cli_eval_bad_input_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], needle: str
) -> None:
    assert _exit_code(["eval", str(INTEL20), "--out", str(tmp_path / "x"), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert needle in err[0]
    assert "Traceback" not in err[0]
    assert not (tmp_path / "x").exists()


def test_fast_online_gives_the_online_numbers(intel20: list, report) -> None:
    config = MapConfig(dim=2, resolution=0.2)
    fast = evaluate_log(
        intel20, config, seeds=2, fraction=0.2, run=2, methods=["online"], fast_online=True
    )
    for a, b in zip(fast.results["online"], report.results["online"], strict=True):
        assert a.auc == b.auc
        assert a.unknown_fraction == b.unknown_fraction
