"""Planning queries: raycast, segment checks, gradients, distance, coarse-depth and box reads.

Each is checked against a brute-force answer from the map's own reads on small maps
built from simulated scans (the 2D paper world, the 3D lidar room): raycast and
segment checks against dense sampling of ``occupancy`` along the ray, gradients
against central finite differences, distance against every occupied voxel cube,
depth reads against OctoMap's max-of-children definition.
"""

from __future__ import annotations

import re
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OctolgpError, OnlineMap
from octolgp.geometry.keys import pack_keys
from octolgp.sim.lidar3d import simulate_lidar_room
from octolgp.sim.scenes import simulate_paper2d

HP2 = Hyperparameters(length_scale=0.4, signal_variance=1.0, noise_variance=0.01, alpha=5.0)
HP3 = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
DENSE = 5e-4
"""Spacing, metres, of the brute-force samples along a ray."""


@pytest.fixture(scope="module")
def map2d() -> OnlineMap:
    data = simulate_paper2d(0, noise=False, n_poses=14, n_beams=90)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2))
    m.insert_scans(data.scans)
    return m


@pytest.fixture(scope="module")
def map3d() -> OnlineMap:
    room = simulate_lidar_room(2, seed=3, n_azimuth=256, n_elevation=16, max_range=20.0)
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=HP3))
    m.insert_scans([s.downsample(0.2) for s in room.scans()])
    return m


@pytest.fixture(params=["2d", "3d"])
def any_map(request: pytest.FixtureRequest, map2d: OnlineMap, map3d: OnlineMap) -> OnlineMap:
    return map2d if request.param == "2d" else map3d


def rays(m: OnlineMap, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from known free voxels near the middle of the map, in random directions."""
    rng = np.random.default_rng(seed)
    centres, prob = m.voxels()
    free = centres[prob < 0.2]
    middle = np.median(free, axis=0)
    near = free[np.argsort(np.linalg.norm(free - middle, axis=1))[: 50 * n]]
    origins = near[rng.choice(near.shape[0], n, replace=False)]
    origins = origins + rng.uniform(-0.3, 0.3, origins.shape) * m.config.resolution
    u = rng.normal(size=origins.shape)
    return origins, u / np.linalg.norm(u, axis=1, keepdims=True)


def dense_first_event(
    m: OnlineMap, o: np.ndarray, u: np.ndarray, max_range: float, unknown: str
) -> np.ndarray:
    """Brute force: the first of dense samples along each ray where the ray stops."""
    s = np.arange(0.0, max_range + DENSE / 2, DENSE)
    out = np.full(o.shape[0], np.inf)
    for i in range(o.shape[0]):  # a test's brute force: one ray at a time
        pts = o[i] + s[:, None] * u[i]
        prob = m.occupancy(pts)
        known = m.occupancy(pts, interpolate=False) != 0.5
        event = np.where(known, prob >= 0.5, unknown != "free")
        if event.any():
            j = int(np.argmax(event))
            out[i] = s[j] if known[j] or unknown == "occupied" else np.nan
    return out


@pytest.fixture(params=["numpy", "compiled"])
def march(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The numpy march (reading the store or a table), or the compiled one (a table always)."""
    from octolgp.mapping import planning, voxel_table

    if request.param == "compiled":
        monkeypatch.setattr(voxel_table, "LOOKUPS_PER_VOXEL", 0.0)
    monkeypatch.setattr(planning, "COMPILED", request.param == "compiled")
    return str(request.param)


@pytest.mark.parametrize("unknown", ["stop", "free", "occupied"])
def test_raycast_matches_dense_sampling_of_occupancy(
    any_map: OnlineMap, unknown: str, march: str
) -> None:
    m = any_map
    o, u = rays(m, 60, seed=1)
    max_range = 6.0 if m.config.dim == 2 else 8.0
    got = m.raycast(o, u, max_range, unknown=unknown)
    want = dense_first_event(m, o, u, max_range, unknown)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    hit = np.isfinite(want)
    assert hit.sum() >= (3 if unknown == "stop" else 10)  # the rays do reach surfaces
    # bisection to a thousandth of a voxel; the dense samples lie DENSE apart
    np.testing.assert_allclose(got[hit], want[hit], atol=DENSE + 1e-3 * m.config.resolution)
    # at each hit the field reaches the threshold, just before it it does not
    known_hits = hit & ~np.isnan(got) & (got > 0)
    at = o[known_hits] + got[known_hits, None] * u[known_hits]
    assert (m.occupancy(at) >= 0.5).all() or unknown != "free"


def test_raycast_modes_differ_where_rays_meet_unknown_space(map3d: OnlineMap, march: str) -> None:
    """Rays into unobserved space: NaN (stop), a hit where it starts (occupied), or pass."""
    o, u = rays(map3d, 40, seed=2)
    stop = map3d.raycast(o, u, 30.0)
    occ = map3d.raycast(o, u, 30.0, unknown="occupied")
    free = map3d.raycast(o, u, 30.0, unknown="free")
    assert 0 < np.isnan(stop).sum() < stop.size
    np.testing.assert_array_equal(np.isnan(stop), np.isfinite(occ) & (occ != free))
    np.testing.assert_array_equal(stop[~np.isnan(stop)], free[~np.isnan(stop)])
    assert not np.isnan(occ).any()
    assert not np.isnan(free).any()
    assert (occ <= free).all()
    short = map3d.raycast(o, u, 0.01)  # nothing within a centimetre of free origins
    assert np.isinf(short).all()
    assert (map3d.raycast(o, u, 0.0) == np.inf).all()


def test_raycast_from_inside_an_obstacle_is_zero(any_map: OnlineMap, march: str) -> None:
    centres, prob = any_map.voxels()
    inside = centres[prob > 0.9][:5]
    d = any_map.raycast(inside, np.ones_like(inside), 3.0)
    np.testing.assert_array_equal(d, 0.0)


def test_segment_free_matches_dense_sampling(any_map: OnlineMap, march: str) -> None:
    m = any_map
    o, u = rays(m, 60, seed=3)
    rng = np.random.default_rng(4)
    b = o + u * rng.uniform(0.2, 4.0, (o.shape[0], 1))
    for unknown_is_free in (False, True):
        got = m.segment_free(o, b, unknown_is_free=unknown_is_free)
        mode = "free" if unknown_is_free else "occupied"
        length = np.linalg.norm(b - o, axis=1)
        want = np.array(
            [
                np.isinf(dense_first_event(m, o[i : i + 1], u[i : i + 1], length[i], mode)[0])
                for i in range(o.shape[0])
            ]
        )
        np.testing.assert_array_equal(got, want)
        assert 0 < got.sum() < got.size  # some free, some blocked
    np.testing.assert_array_equal(m.segment_free(o, o), True)  # zero-length segments


def fd_points(m: OnlineMap, n: int, seed: int) -> np.ndarray:
    """Points in known space near surfaces, away from cell faces and the unknown edge."""
    rng = np.random.default_rng(seed)
    res = m.config.resolution
    centres, prob = m.voxels()
    edge = centres[(prob > 0.05) & (prob < 0.95)]
    p = edge[rng.choice(edge.shape[0], 4 * n, replace=False)]
    p = p + rng.uniform(-0.4, 0.4, p.shape) * res
    frac = (p / res - 0.5) % 1.0
    ok = ((frac > 0.02) & (frac < 0.98)).all(axis=1)
    # the whole 2**d cell of voxel centres around the point holds values
    corners = np.array(list(np.ndindex(*(2,) * m.config.dim)))
    base = np.floor(p / res - 0.5)
    cell = ((base[:, None, :] + corners[None] + 0.5) * res).reshape(-1, m.config.dim)
    held = (m.occupancy(cell, interpolate=False) != 0.5).reshape(p.shape[0], -1).all(axis=1)
    return p[ok & held][:n]


def test_gradient_matches_central_differences_of_occupancy(any_map: OnlineMap) -> None:
    m = any_map
    p = fd_points(m, 200, seed=5)
    assert p.shape[0] >= 100
    h = 1e-6
    eye = np.eye(m.config.dim)
    fd = np.stack(
        [(m.occupancy(p + h * e) - m.occupancy(p - h * e)) / (2 * h) for e in eye], axis=1
    )
    g = m.gradient(p)
    assert np.abs(g).max() > 1.0  # steep near surfaces: per metre
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-5)
    g_mean, g_var = m.latent_gradient(p)
    for k, grad in enumerate((g_mean, g_var)):
        fd_latent = np.stack(
            [(m.latent(p + h * e)[k] - m.latent(p - h * e)[k]) / (2 * h) for e in eye], axis=1
        )
        np.testing.assert_allclose(grad, fd_latent, rtol=1e-4, atol=1e-5)


def test_normals_point_out_of_obstacles(any_map: OnlineMap) -> None:
    m = any_map
    p = fd_points(m, 100, seed=6)
    n = m.normals(p)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    step = 0.2 * m.config.resolution
    assert (m.occupancy(p + step * n) < m.occupancy(p)).mean() > 0.95


def test_gradient_is_zero_in_unknown_space(any_map: OnlineMap) -> None:
    far = np.full((3, any_map.config.dim), 500.0)
    np.testing.assert_array_equal(any_map.gradient(far), 0.0)
    assert np.isnan(any_map.normals(far)).all()


def brute_distance(m: OnlineMap, X: np.ndarray, threshold: float) -> np.ndarray:
    """Distance from each point to every occupied voxel's cube, the minimum."""
    centres, prob = m.voxels()
    cubes = centres[prob >= threshold]
    half = m.config.resolution / 2
    out = np.empty(X.shape[0])
    for i in range(X.shape[0]):  # a test's brute force: one point at a time
        gap = np.maximum(np.abs(cubes - X[i]) - half, 0.0)
        out[i] = np.sqrt((gap * gap).sum(axis=1)).min()
    return out


@pytest.mark.parametrize(
    "search", ["shells", "tree", "few shells, then the tree", "3d shells", "no room for a grid"]
)
@pytest.mark.parametrize("threshold", [0.5, 0.8])
def test_distance_matches_brute_force(
    any_map: OnlineMap, threshold: float, search: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    from octolgp.mapping import distance

    monkeypatch.setattr(distance, "COMPILED", search != "tree")
    if search == "no room for a grid":
        monkeypatch.setattr(distance, "GRID_CELLS", 1)
    if search == "3d shells":  # as many shells in 3D as in 2D
        monkeypatch.setattr(distance, "SHELLS", MappingProxyType({2: 10, 3: 10}))
        monkeypatch.setattr(distance, "BOUNDED_SHELLS", MappingProxyType({2: 32, 3: 32}))
    if search.startswith("few"):
        monkeypatch.setattr(distance, "SHELLS", MappingProxyType({2: 2, 3: 1}))
        monkeypatch.setattr(distance, "BOUNDED_SHELLS", MappingProxyType({2: 2, 3: 1}))
    m = any_map
    m._occupied = None  # nothing kept from other tests' reads
    rng = np.random.default_rng(7)
    centres, _ = m.voxels()
    lo, hi = centres.min(axis=0) - 1.0, centres.max(axis=0) + 1.0
    X = np.concatenate([rng.uniform(lo, hi, (300, m.config.dim)), centres[::97]])
    want = brute_distance(m, X, threshold)
    got = m.distance(X, threshold)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert (got == 0).any()
    assert (got > 1.0).any()
    capped = m.distance(X, threshold, max_distance=0.7)
    near, far = want <= 0.7 - 1e-9, want > 0.7 + 1e-9  # rounding aside
    np.testing.assert_allclose(capped[near], got[near], rtol=0, atol=1e-9)
    assert np.isinf(capped[far]).all()


def test_distance_of_an_empty_map_is_inf() -> None:
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2))
    np.testing.assert_array_equal(m.distance([[0.0, 0.0]]), np.inf)


def octomap_max_of_children(
    m: OnlineMap, X: np.ndarray, depth: int
) -> tuple[np.ndarray, dict[int, float]]:
    """OctoMap's node value at ``depth``: the max over the voxels below it, by brute force."""
    centres, prob = m.voxels()
    c = m.config
    edge = c.resolution * 2 ** (c.tree_depth - depth)
    origin = -(2 ** (c.tree_depth - 1)) * c.resolution
    nodes: dict[int, float] = {}
    for key, p in zip(
        pack_keys(np.floor((centres - origin) / edge).astype(np.int64)), prob, strict=True
    ):
        nodes[int(key)] = max(nodes.get(int(key), 0.0), float(p))
    keys = pack_keys(np.floor((X - origin) / edge).astype(np.int64))
    return np.array([nodes.get(int(k), 0.5) for k in keys]), nodes


@pytest.mark.parametrize("coarser", [1, 2, 4, 6])
def test_occupancy_and_voxels_at_depth_are_octomap_max_of_children(
    any_map: OnlineMap, coarser: int
) -> None:
    m = any_map
    depth = m.config.tree_depth - coarser
    rng = np.random.default_rng(8)
    centres, _ = m.voxels()
    X = rng.uniform(centres.min(axis=0) - 2, centres.max(axis=0) + 2, (2000, m.config.dim))
    want, nodes = octomap_max_of_children(m, X, depth)
    np.testing.assert_array_equal(m.occupancy(X, depth=depth), want)
    assert (want == 0.5).any()
    assert (want > 0.9).any()
    c, p = m.voxels(depth=depth)
    edge = m.config.resolution * 2**coarser
    origin = -(2 ** (m.config.tree_depth - 1)) * m.config.resolution
    got = dict(
        zip(pack_keys(np.floor((c - origin) / edge).astype(np.int64)).tolist(), p, strict=True)
    )
    assert got == nodes
    np.testing.assert_allclose((c - origin) / edge % 1.0, 0.5)  # node centres
    # a voxel-depth read is the voxels' own read
    np.testing.assert_array_equal(
        m.occupancy(X, depth=m.config.tree_depth), m.occupancy(X, interpolate=True)
    )


@pytest.mark.parametrize("depth", [None, 13])
def test_box_read_is_the_cells_overlapping_the_box(any_map: OnlineMap, depth: int | None) -> None:
    m = any_map
    centres, _ = m.voxels(depth=depth)
    lo = np.quantile(centres, 0.3, axis=0) + 0.013
    hi = np.quantile(centres, 0.6, axis=0) - 0.011
    c, p = m.voxels(depth=depth, bbox=(lo, hi))
    all_c, all_p = m.voxels(depth=depth)
    res = m.config.resolution * 2 ** (m.config.tree_depth - (depth or m.config.tree_depth))
    overlap = ((all_c + res / 2 > lo) & (all_c - res / 2 <= hi)).all(axis=1)
    assert 0 < overlap.sum() < all_c.shape[0]
    order = np.lexsort(c.T)
    want = np.lexsort(all_c[overlap].T)
    np.testing.assert_array_equal(c[order], all_c[overlap][want])
    np.testing.assert_array_equal(p[order], all_p[overlap][want])


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda m: m.raycast([[0.0, 0.0]], [[0.0, 0.0]], 1.0), "directions"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0, 0.0]], 1.0), "directions"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0]], -1.0), "max_range"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0]], np.inf), "max_range"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0]], [1.0, 2.0]), "max_range"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0]], 1.0, 1.0), "threshold"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0]], 1.0, unknown="maybe"), "unknown"),
        (lambda m: m.raycast([[0.0, 0.0]], [[1.0, 0.0]], 1.0, step=0.5), "step"),
        (lambda m: m.raycast([[np.nan, 0.0]], [[1.0, 0.0]], 1.0), "origins"),
        (lambda m: m.raycast([[1e9, 0.0]], [[1.0, 0.0]], 1.0), "origins row 0 .* addressable"),
        (lambda m: m.segment_free([[0.0, 0.0]], [[np.inf, 0.0]]), "^b "),
        (lambda m: m.segment_free([[0.0, 0.0]], [[1.0, 0.0], [2.0, 0.0]]), "b must"),
        (
            lambda m: m.segment_free([[0.0, 0.0]], [[1.0, 0.0]], unknown_is_free=1),
            "unknown_is_free",
        ),
        (lambda m: m.distance([[0.0, 0.0]], max_distance=0), "max_distance"),
        (lambda m: m.distance([[0.0, 0.0]], threshold=True), "threshold"),
        (lambda m: m.occupancy([[0.0, 0.0]], depth=0), "depth"),
        (lambda m: m.occupancy([[0.0, 0.0]], depth=17), "depth"),
        (lambda m: m.voxels(depth=2.0), "depth"),
        (lambda m: m.voxels(bbox=([0.0, 0.0], [1.0])), "bbox"),
        (lambda m: m.voxels(bbox=([1.0, 1.0], [0.0, 2.0])), "bbox"),
        (lambda m: m.gradient([[0.0, 0.0, 0.0]]), "points"),
    ],
)
def test_bad_inputs_name_the_field(map2d: OnlineMap, call: object, field: str) -> None:
    with pytest.raises(OctolgpError, match=field):
        call(map2d)  # type: ignore[operator]


@pytest.fixture(scope="module")
def map_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cli") / "paper.octolgp"
    data = simulate_paper2d(0, noise=False, n_poses=14, n_beams=90)
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2), path=path) as m:
        m.insert_scans(data.scans)
    return path


def test_cli_query_raycast_and_distance_write_npy_and_csv(
    map_file: Path, map2d: OnlineMap, tmp_path: Path
) -> None:
    from octolgp.cli.main import main

    o, u = rays(map2d, 30, seed=9)
    np.save(tmp_path / "rays.npy", np.hstack([o, 3.0 * u]))  # directions need not be unit
    np.save(tmp_path / "pts.npy", o)
    argv = ["query", str(map_file), "--raycast", str(tmp_path / "rays.npy"), "--max-range", "5"]
    assert main([*argv, "--out", str(tmp_path / "hits.npy")]) == 0
    want = map2d.raycast(o, u, 5.0)
    np.testing.assert_allclose(np.load(tmp_path / "hits.npy"), want, rtol=1e-12, atol=1e-12)
    assert np.isfinite(want).sum() >= 5
    assert main([*argv, "--unknown", "occupied", "--out", str(tmp_path / "hits.csv")]) == 0
    csv = np.loadtxt(tmp_path / "hits.csv", skiprows=1)
    want = map2d.raycast(o, u, 5.0, unknown="occupied")
    np.testing.assert_allclose(csv, want, rtol=1e-8)
    assert (tmp_path / "hits.csv").read_text().splitlines()[0] == "distance"
    dist = ["query", str(map_file), "--distance", str(tmp_path / "pts.npy")]
    assert main([*dist, "--out", str(tmp_path / "d.npy"), "--max-distance", "2"]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), map2d.distance(o, max_distance=2.0))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--raycast", "rays.npy", "--out", "h.npy"], "--max-range"),
        (["--raycast", "pts.npy", "--max-range", "5", "--out", "h.npy"], r"--raycast .*\(n, 4\)"),
        (["--raycast", "zero.npy", "--max-range", "5", "--out", "h.npy"], "--raycast: directions"),
        (["--raycast", "rays.npy", "--max-range", "-1", "--out", "h.npy"], "max_range"),
        (["--raycast", "missing.npy", "--max-range", "5", "--out", "h.npy"], "--raycast"),
        (["--distance", "rays.npy", "--out", "d.npy"], "--distance: points must have shape"),
        (["--distance", "pts.npy", "--max-distance", "0", "--out", "d.npy"], "max_distance"),
        (["--distance", "pts.npy", "--max-range", "2", "--out", "d.npy"], "--max-range"),
        (["--points", "pts.npy", "--max-distance", "2", "--out", "d.npy"], "--max-distance"),
        (["--distance", "pts.npy", "--out", "d.txt"], "--out"),
        (["--distance", "pts.npy", "--nearest", "--out", "d.npy"], "--nearest"),
        (["--distance", "pts.npy", "--unknown", "free", "--out", "d.npy"], "--unknown"),
        (["--points", "pts.npy", "--threshold", "0.7", "--out", "d.npy"], "--threshold"),
    ],
)
def test_cli_query_bad_input_exits_2_naming_the_field(
    map_file: Path,
    tmp_path: Path,
    argv: list[str],
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from octolgp.cli.main import main

    np.save(tmp_path / "rays.npy", np.array([[0.5, 0.5, 1.0, 0.0]]))
    np.save(tmp_path / "zero.npy", np.array([[0.5, 0.5, 0.0, 0.0]]))
    np.save(tmp_path / "pts.npy", np.array([[0.5, 0.5]]))
    here = [str(tmp_path / a) if a.endswith((".npy", ".txt")) else a for a in argv]
    assert main(["query", str(map_file), *here]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert re.search(message, err[0])


@pytest.mark.parametrize("dense", [True, False])
def test_raycast_reads_the_same_from_a_voxel_table_as_from_the_store(
    any_map: OnlineMap, monkeypatch: pytest.MonkeyPatch, dense: bool
) -> None:
    """Many rays read a table of the voxels (dense or by key); few read the store: one answer."""
    from octolgp.mapping import planning, voxel_table

    monkeypatch.setattr(planning, "COMPILED", False)  # the numpy march, from either

    o, u = rays(any_map, 60, seed=10)
    monkeypatch.setattr(voxel_table, "LOOKUPS_PER_VOXEL", 0.0)  # always a table
    monkeypatch.setattr(voxel_table, "DENSE_FILL", 0.0 if dense else 2.0)
    table = [any_map.raycast(o, u, 6.0, unknown=mode) for mode in ("stop", "free", "occupied")]
    monkeypatch.setattr(voxel_table, "LOOKUPS_PER_VOXEL", np.inf)  # never
    store = [any_map.raycast(o, u, 6.0, unknown=mode) for mode in ("stop", "free", "occupied")]
    for a, b in zip(table, store, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("dense", [True, False])
@pytest.mark.parametrize("threshold", [0.5, 0.8])
def test_compiled_raycast_answers_as_the_numpy_march(
    any_map: OnlineMap, monkeypatch: pytest.MonkeyPatch, dense: bool, threshold: float
) -> None:
    """The compiled march and the numpy one: the same misses and NaNs, hits within the bisection."""
    from octolgp.mapping import planning, voxel_table

    o, u = rays(any_map, 300, seed=11)
    monkeypatch.setattr(voxel_table, "LOOKUPS_PER_VOXEL", 0.0)  # a table, for both
    monkeypatch.setattr(voxel_table, "DENSE_FILL", 0.0 if dense else 2.0)
    tol = planning.BISECTION_TOL * any_map.config.resolution
    for mode in ("stop", "free", "occupied"):  # each unknown mode
        monkeypatch.setattr(planning, "COMPILED", True)
        fast = any_map.raycast(o, u, 12.0, threshold, unknown=mode)
        monkeypatch.setattr(planning, "COMPILED", False)
        slow = any_map.raycast(o, u, 12.0, threshold, unknown=mode)
        np.testing.assert_array_equal(np.isnan(fast), np.isnan(slow))
        np.testing.assert_array_equal(np.isinf(fast), np.isinf(slow))
        hit = np.isfinite(slow)
        assert hit.sum() > 50
        np.testing.assert_allclose(fast[hit], slow[hit], rtol=0, atol=tol)


def test_compiled_raycast_reads_stored_values_before_hyperparameters(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A map still learning reads the stored P of each voxel: both marches agree there too."""
    from octolgp.mapping import planning, voxel_table

    data = simulate_paper2d(0, noise=False, n_poses=3, n_beams=90)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1))
    m.insert_scans(data.scans)
    assert m.hyperparameters is None
    o, u = rays(m, 200, seed=12)
    monkeypatch.setattr(voxel_table, "LOOKUPS_PER_VOXEL", 0.0)
    out = []
    for compiled in (True, False):  # the compiled march, then numpy's
        monkeypatch.setattr(planning, "COMPILED", compiled)
        out.append(m.raycast(o, u, 8.0, unknown="free"))
    np.testing.assert_array_equal(np.isinf(out[0]), np.isinf(out[1]))
    hit = np.isfinite(out[1])
    assert hit.sum() > 50
    np.testing.assert_allclose(out[0][hit], out[1][hit], rtol=0, atol=1e-3 * 0.1)


def test_surface_vertices_lie_on_the_level_set_and_faces_face_out(any_map: OnlineMap) -> None:
    m = any_map
    v, f = m.surface()
    d = m.config.dim
    assert v.shape[1] == d
    assert f.shape[1] == d
    assert f.shape[0] > 500
    np.testing.assert_allclose(m.occupancy(v), 0.5, atol=5e-3)
    assert f.min() >= 0
    assert f.max() < v.shape[0]
    if d == 3:
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        normal, mid = np.cross(b - a, c - a), (a + b + c) / 3
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    else:
        a, b = v[f[:, 0]], v[f[:, 1]]
        normal, mid = np.c_[(b - a)[:, 1], -(b - a)[:, 0]], (a + b) / 2
        edges = f.reshape(-1, 1)
    assert (np.linalg.norm(normal, axis=1) > 0).all()  # no degenerate face
    assert ((normal * m.gradient(mid)).sum(axis=1) < 0).mean() > 0.99  # out of obstacles
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert uses.max() == 2  # no crack, no fold: a face edge is shared by at most two faces
    if d == 2:  # the paper's world is closed: every polyline is a loop
        assert (uses == 2).all()
    lo, hi = np.quantile(v, 0.3, axis=0), np.quantile(v, 0.7, axis=0)
    vb, fb = m.surface(bbox=(lo, hi))
    assert 0 < vb.shape[0] < v.shape[0]
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(v).query(vb)  # a box's surface is part of the whole one
    assert gap.max() < 2e-3 * m.config.resolution
    cells = np.floor(vb[fb].min(axis=1) / m.config.resolution - 0.5)  # faces' cells' lower corners
    res = m.config.resolution
    assert ((cells + 0.5) * res >= lo - 1e-9).all()
    assert ((cells + 0.5) * res <= hi + 1e-9).all()


def test_export_writes_the_surface_as_obj_and_ply(map_file: Path, tmp_path: Path) -> None:
    from octolgp.cli.main import main

    assert main(["export", str(map_file), "--out", str(tmp_path / "s.obj")]) == 0
    lines = (tmp_path / "s.obj").read_text().splitlines()
    with OnlineMap.open(map_file, read_only=True) as m:
        v, f = m.surface()
    assert sum(line.startswith("v ") for line in lines) == v.shape[0]
    assert sum(line.startswith("l ") for line in lines) == f.shape[0]
    assert main(["export", str(map_file), "--out", str(tmp_path / "s.ply"), "--mesh"]) == 0
    head = (tmp_path / "s.ply").read_bytes().split(b"end_header\n")
    assert f"element vertex {v.shape[0]}".encode() in head[0]
    assert f"element edge {f.shape[0]}".encode() in head[0]
    assert len(head[1]) == v.shape[0] * 12 + f.shape[0] * 8
    assert main(["export", str(map_file), "--out", str(tmp_path / "s.png"), "--mesh"]) == 2


def test_the_path_check_example_finds_the_robots_own_legs_free() -> None:
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(root)}  # this checkout's octolgp
    out = subprocess.run(
        [sys.executable, str(root / "examples" / "path_check.py"), "--limit", "80"],
        capture_output=True,
        text=True,
        check=True,
        cwd=root,
        env=env,
    ).stdout
    legs = re.search(r"trajectory legs: (\d+) of (\d+) free", out)
    assert legs is not None
    assert int(legs.group(1)) >= 0.9 * int(legs.group(2)) > 0
    shortcuts = re.search(r"shortcuts from the start: (\d+) of (\d+) free", out)
    assert shortcuts is not None
    assert int(shortcuts.group(1)) < int(shortcuts.group(2))  # some cross a wall


def test_a_map_under_a_memory_budget_answers_the_same(map2d: OnlineMap, tmp_path: Path) -> None:
    """Evicted leaves are read back for the queries (and stay evicted): the same answers."""
    data = simulate_paper2d(0, noise=False, n_poses=14, n_beams=90)
    config = MapConfig(dim=2, resolution=0.1, hyperparameters=HP2, memory_budget_mb=0.3)
    with OnlineMap(config, path=tmp_path / "budget.octolgp") as m:
        m.insert_scans(data.scans)
        m.settle()
        assert m.store.resident < len(m.store)  # some leaves live only in the file
        o, u = rays(map2d, 30, seed=11)
        X = o + 0.5 * u
        np.testing.assert_array_equal(m.raycast(o, u, 6.0), map2d.raycast(o, u, 6.0))
        np.testing.assert_array_equal(m.segment_free(o, X), map2d.segment_free(o, X))
        np.testing.assert_array_equal(m.gradient(X), map2d.gradient(X))
        np.testing.assert_array_equal(m.distance(X), map2d.distance(X))
        np.testing.assert_array_equal(m.occupancy(X, depth=12), map2d.occupancy(X, depth=12))
        for a, b in zip(m.surface(), map2d.surface(), strict=True):
            np.testing.assert_array_equal(a, b)
        resident = m.store.resident
        m.distance(X)
        assert m.store.resident == resident  # reads do not change which leaves stay in RAM


def test_large_queries_in_chunks_answer_as_one(
    map3d: OnlineMap, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Rays and distance points run in bounded chunks: the same answers as in one piece."""
    from octolgp.mapping import distance, planning

    o, u = rays(map3d, 50, seed=12)
    X = o + u
    whole = (map3d.raycast(o, u, 8.0), map3d.distance(X))
    monkeypatch.setattr(planning, "RAY_CHUNK", 7)
    monkeypatch.setattr(distance, "QUERY_CHUNK", 9)
    parts = (map3d.raycast(o, u, 8.0), map3d.distance(X))
    for a, b in zip(whole, parts, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_3d_mesh_writes_as_ply_and_obj(map3d: OnlineMap, tmp_path: Path) -> None:
    from octolgp.export.mesh import write_mesh

    v, f = map3d.surface(bbox=(np.array([0.0, 0.0, 0.0]), np.array([6.0, 6.0, 3.0])))
    assert f.shape[0] > 100
    write_mesh(tmp_path / "m.ply", v, f)
    head, body = (tmp_path / "m.ply").read_bytes().split(b"end_header\n")
    assert f"element face {f.shape[0]}".encode() in head
    assert len(body) == v.shape[0] * 12 + f.shape[0] * 13
    faces = np.frombuffer(body[v.shape[0] * 12 :], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    assert (faces["n"] == 3).all()
    np.testing.assert_array_equal(faces["i"], f)
    np.testing.assert_allclose(
        np.frombuffer(body[: v.shape[0] * 12], "<f4").reshape(-1, 3), v, atol=1e-5
    )
    write_mesh(tmp_path / "m.obj", v, f)
    lines = (tmp_path / "m.obj").read_text().splitlines()
    got = np.array([[int(x) for x in line.split()[1:]] for line in lines if line.startswith("f ")])
    np.testing.assert_array_equal(got - 1, f)
    with pytest.raises(OctolgpError, match="mesh path"):
        write_mesh(tmp_path / "m.stl", v, f)


def test_the_room_mesh_example_writes_a_mesh(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    out = tmp_path / "room.obj"
    run = subprocess.run(
        [
            sys.executable,
            str(root / "examples" / "room_mesh.py"),
            "--out",
            str(out),
            "--poses",
            "1",
        ],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONPATH": str(root)},
    ).stdout
    assert "triangles" in run
    assert sum(line.startswith("f ") for line in out.read_text().splitlines()) > 1000


def test_distance_kept_between_inserts_matches_a_fresh_read() -> None:
    """The occupied centres kept between reads follow the inserts: windows and whole map."""
    from octolgp.mapping.distance import occupied_distance

    data = simulate_paper2d(1, noise=False, n_poses=10, n_beams=90)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2))
    rng = np.random.default_rng(3)
    for scan in data.scans:  # a planner: a window read and a whole-map read after each insert
        m.insert_scan(scan)
        X = scan.origin + rng.uniform(-1.5, 1.5, (200, 2))
        for cap in (1.0, None):
            got = m.distance(X, max_distance=cap)
            again = m.distance(X, max_distance=cap)  # the kept tree
            with m._reading() as fresh:
                want = occupied_distance(fresh, X, 0.5, np.inf if cap is None else cap)
            np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(again, want)
    want = brute_distance(m, X, 0.5)
    np.testing.assert_allclose(m.distance(X), want, rtol=0, atol=1e-9)
