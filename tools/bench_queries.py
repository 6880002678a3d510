"""Planning queries: raycast, segment checks, distance and gradient, beside OctoMap's castRay.

Figures: BENCHMARKS.md, "Planning queries".

Scenes:

- ``room``: ``octolgp.sim.lidar3d.simulate_lidar_room`` (20 x 20 x 5 m, 22 boxes), a
  32 x 1024 lidar at ``--room-poses`` poses, each scan ``downsample(0.2)``-ed, mapped at
  0.2 m with hyperparameters given (length scale 0.8 m, as ``tools/bench_window_query.py``)
  and, on the same points, by OctoMap (``pyoctomap``, ``insertPointCloud``). Rays: the
  beams of the held-out poses (never mapped; ``--rays`` of them drawn), whose exact first
  hits the room knows (``LidarRoom.ranges``). A ray "hits an observed surface" when its
  exact hit lies within one voxel of a mapped endpoint; the first-hit error is
  ``|distance - exact|`` over those rays. Distance points: the held-out free test points
  (``LidarRoom.heldout_points``), whose exact distance to the boxes is computed in closed
  form; the RMS error is over points at most 2 m from a box.
- ``intel``: the bundled Intel lab log, every scan mapped at 0.1 m at the defaults
  (hyperparameters learnt), and by OctoMap in the layer ``0 <= z < 0.1``. Rays: the beams
  of every tenth scan that returned (mapped scans, so the error is self-consistency with
  the measured ranges, not ground truth). Distance and gradient points: uniform in the
  box of the map's voxels.
- ``street`` (rays only): the simulated street (``simulate_car_street``, a 64 x 1024 lidar
  to 80 m), 7 scans 1 m apart mapped; the scan 1 m past them held out, its returns' exact
  ranges scored; true surfaces the boxes and the ground.
- ``office`` (rays only): the paper's 2D world (``simulate_paper2d``, no noise, 56 poses of
  361 beams) at 0.1 m at the defaults; every fourth pose held out.

``--learn``: the room and the street learn their hyperparameters (the default config)
instead of taking length scale 0.8 m.

Online (room and intel): the scans inserted one by one into a fresh map, each followed by a
settle (the deferred fits a read pays first) and a planner's ``distance`` reads at
``--window-points`` points in a box of ``2 * --window`` m around the sensor: with
``max_distance=--window``, the same again (nothing changed), and without a bound; each
against the insert and settle of its scan.

octolgp's raycast marches the interpolated field at half-voxel steps with a sample in
every voxel it passes, then bisects (``unknown="stop"``: a ray entering unknown space
ends with NaN; ``"free"``: it passes). OctoMap's ``castRay`` (C++, one Python call per
ray through the binding) returns the centre of the first occupied voxel; its distance is
``|centre - origin|`` (``ignoreUnknownCells`` False for "stop", True for "free").

Run from the repository root::

    .venv/bin/python tools/bench_queries.py
    .venv/bin/python tools/bench_queries.py --scenes room --rays 5000
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
from octolgp.bench.octomap_ref import OctomapReference
from octolgp.scan import Scan
from octolgp.sim.lidar3d import simulate_lidar_room
from octolgp.sim.mission import simulate_car_street
from octolgp.sim.scenes import simulate_paper2d

HP3 = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
INTEL = Path(__file__).resolve().parent.parent / "data/intel_lab/intel-corrected.log.gz"


def timed(call: Callable[[], object]) -> tuple[object, float]:
    """``call()`` and its wall-clock seconds."""
    t0 = time.perf_counter()
    out = call()
    return out, time.perf_counter() - t0


def map_both(m: OnlineMap, ref: OctomapReference, scans: list[Scan]) -> float:
    """Map ``scans`` with octolgp and OctoMap; octolgp's seconds.

    ``m`` takes them one at a time, then learns if it still must, and settles.
    """

    def build() -> None:
        for s in scans:  # one scan at a time, as a robot inserts them
            m.insert_scan(s)
        m.flush()  # learns, should the scans be fewer than the learning phase's
        m.settle()

    _, seconds = timed(build)
    for s in scans:  # the same points into OctoMap
        ref.insert_scan(s)
    return seconds


def octomap_cast(
    ref: OctomapReference, origins: np.ndarray, dirs: np.ndarray, max_range: float, free: bool
) -> tuple[np.ndarray, float]:
    """OctoMap's castRay per ray: distance to the hit voxel's centre (NaN where none)."""
    if origins.shape[1] == 2:  # the reference's 2D layer: z = resolution / 2
        origins = np.hstack([origins, np.full((origins.shape[0], 1), 0.5 * ref.resolution)])
    lift = np.ascontiguousarray(origins, dtype=np.float64)
    udir = dirs if dirs.shape[1] == 3 else np.hstack([dirs, np.zeros((dirs.shape[0], 1))])
    udir = np.ascontiguousarray(udir)
    out = np.full(origins.shape[0], np.nan)
    end = np.zeros(3)
    t0 = time.perf_counter()
    for i in range(origins.shape[0]):  # the binding casts one ray per call
        if ref.tree.castRay(lift[i], udir[i], end, free, max_range):
            out[i] = float(np.linalg.norm(end - lift[i]))
    return out, time.perf_counter() - t0


def box_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Exact distance from points outside every box to the union of boxes ``(k, 2d)``."""
    d = points.shape[1]
    gap = np.maximum(
        np.maximum(
            boxes[None, :, :d] - points[:, None, :], points[:, None, :] - boxes[None, :, d:]
        ),
        0.0,
    )
    return np.asarray(np.sqrt((gap * gap).sum(axis=2)).min(axis=1))


def surface_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance from points to the nearest box face: outside or inside the boxes."""
    d = points.shape[1]
    lo, hi = boxes[None, :, :d], boxes[None, :, d:]
    p = points[:, None, :]
    inside = ((p > lo) & (p < hi)).all(axis=2)
    depth = np.minimum(p - lo, hi - p).min(axis=2)  # to the faces, for points inside
    within = np.where(inside, depth, np.inf).min(axis=1)
    return np.where(inside.any(axis=1), within, box_distance(points, boxes))


def ray_rows(
    name: str,
    m: OnlineMap,
    ref: OctomapReference,
    origins: np.ndarray,
    dirs: np.ndarray,
    max_range: float,
    exact: np.ndarray,
    observed: np.ndarray,
    boxes: np.ndarray | None,
) -> list[str]:
    """Table rows: raycast speed and first-hit error of octolgp and OctoMap."""
    res = m.config.resolution
    rows = []
    m.raycast(origins[:4000], dirs[:4000], max_range)  # compiles the march (or loads it), untimed
    runs = [("stop", 0.5, False), ("free", 0.5, True), ("free", 0.9, None)]
    for mode, thr, free in runs:  # octolgp in each mode; OctoMap beside it
        ours, t_ours = timed(
            lambda mode=mode, thr=thr: m.raycast(origins, dirs, max_range, thr, unknown=mode)
        )
        casts = [("octolgp", np.asarray(ours), t_ours)]
        if free is not None:
            theirs, t_theirs = octomap_cast(ref, origins, dirs, max_range, free)
            casts.append(("OctoMap castRay", theirs, t_theirs))
        for who, d, t in casts:
            err = np.abs(d[observed] - exact[observed])
            hit = np.isfinite(err)
            within = float(np.mean(np.where(hit, err <= res, False)))
            surface = "n/a"
            if boxes is not None and hit.any():
                o, u = origins[observed][hit], dirs[observed][hit]
                gap = surface_distance(o + d[observed][hit, None] * u, boxes)
                surface = f"{np.median(gap):.3f} / {np.mean(gap <= res):.1%}"
            rows.append(
                f"| {name} | {who} | {mode} | {thr if who == 'octolgp' else 'occ. thres 0.5'} "
                f"| {origins.shape[0]} | {origins.shape[0] / t:,.0f} "
                f"| {observed.sum()} | {hit.mean():.1%} | {within:.1%} "
                f"| {np.median(err[hit]) if hit.any() else np.nan:.3f} "
                f"| {np.quantile(err[hit], 0.99) if hit.any() else np.nan:.3f} | {surface} |"
            )
    return rows


def mesh_rows(
    m: OnlineMap, ref: OctomapReference, hits: np.ndarray, boxes: np.ndarray
) -> list[str]:
    """Rows: Chamfer distance of octolgp's surface and OctoMap's occupied centres to the truth.

    Accuracy: each vertex's (centre's) distance to the nearest box face; completeness:
    each exact held-out hit's distance to the nearest vertex (centre).
    """
    rows = []
    occupied = [  # the binding's iterator is one object, moved along: read it in the loop
        list(leaf.getCoordinate())
        for leaf in ref.tree.begin_leafs()
        if ref.tree.isNodeOccupied(leaf)
    ]
    centres = np.array(occupied, dtype=np.float64)
    clouds: list[tuple[str, np.ndarray, float]] = [("OctoMap occupied centres", centres, 0.0)]
    for thr in (0.5, 0.9):  # the default level set and a stricter one
        (v, f), t = timed(lambda thr=thr: m.surface(thr))
        clouds.insert(-1, (f"octolgp surface() P = {thr} ({f.shape[0]:,} triangles)", v, t))
    for who, pts, t in clouds:
        acc = surface_distance(pts, boxes)
        comp, _ = cKDTree(pts).query(hits)
        rows.append(
            f"| room | {who} | {pts.shape[0]:,} | {t:.2f} | {np.median(acc):.3f} | {acc.mean():.3f} "
            f"| {np.median(comp):.3f} | {comp.mean():.3f} | {acc.mean() + comp.mean():.3f} |"
        )
    return rows


def room(args: argparse.Namespace) -> tuple[list[str], list[str], list[str]]:
    """The lidar room: ray, point and online rows."""
    sim = simulate_lidar_room(args.room_poses, seed=0, n_heldout=3)
    scans = [s.downsample(0.2) for s in sim.scans()]
    hp = None if args.learn else HP3  # learnt from the scans, as a user's map learns them
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp))
    ref = OctomapReference(0.2, 3)
    t_build = map_both(m, ref, scans)
    print(f"room: {len(scans)} scans mapped in {t_build:.1f} s")
    rng = np.random.default_rng(0)
    origins, dirs, exact = [], [], []
    for pose in sim.heldout_poses:  # the held-out poses' beams, exact ranges
        t, u = sim.ranges(pose)
        origins.append(np.broadcast_to(pose[:3], u.shape))
        dirs.append(u)
        exact.append(t)
    o, u, t = np.concatenate(origins), np.concatenate(dirs), np.concatenate(exact)
    pick = rng.choice(o.shape[0], min(args.rays, o.shape[0]), replace=False)
    o, u, t = o[pick], u[pick], t[pick]
    ends = np.concatenate([s.points for s in scans])
    gap, _ = cKDTree(ends).query(o + t[:, None] * u)
    observed = gap <= 0.2
    rows = ray_rows("room", m, ref, o, u, sim.max_range, t, observed, sim.boxes)
    hits = (o + t[:, None] * u)[observed & np.isfinite(t)]  # exact, observed surface points
    rows += mesh_rows(m, ref, hits, sim.boxes)
    # distance, gradient and segment checks on held-out free points
    pts, labels, _ = sim.heldout_points()
    free = pts[labels == 0]
    free = free[rng.choice(free.shape[0], min(args.points, free.shape[0]), replace=False)]
    online = online_rows("room", m.config, scans, args, clip=(0.05, 4.95))
    return rows, point_rows("room", m, free, box_distance(free, sim.boxes), rng), online


def point_rows(
    name: str,
    m: OnlineMap,
    pts: np.ndarray,
    exact: np.ndarray | None,
    rng: np.random.Generator,
) -> list[str]:
    """Table rows: distance, gradient and segment-check throughput (and distance error)."""
    rows = []
    n = pts.shape[0]
    _, t = timed(lambda: m.distance(pts[:1]))
    rows.append(
        f"| {name} | distance, 1 point (reads the voxels, builds the tree) | 1 | n/a | {t:.3f} | n/a |"
    )
    runs = (
        ("distance, whole map", None, 0.5),
        ("distance, max_distance=2", 2.0, 0.5),
        ("distance, threshold 0.9", None, 0.9),
    )
    for label, cap, thr in runs:  # whole map, cropped, stricter threshold
        d, t = timed(lambda cap=cap, thr=thr: m.distance(pts, thr, max_distance=cap))
        err = "n/a"
        if exact is not None:
            near = exact <= 2.0
            e = np.asarray(d)[near] - exact[near]
            e = e[np.isfinite(e)]
            err = f"RMS {np.sqrt(np.mean(e * e)):.3f} m, mean {e.mean():+.3f} m ({near.sum()} pts <= 2 m)"
        rows.append(f"| {name} | {label} | {n} | {n / t:,.0f} | {t:.2f} | {err} |")
    _, t = timed(lambda: m.gradient(pts))
    rows.append(f"| {name} | gradient | {n} | {n / t:,.0f} | {t:.2f} | n/a |")
    _, t = timed(lambda: m.occupancy(pts))
    rows.append(f"| {name} | occupancy (for scale) | {n} | {n / t:,.0f} | {t:.2f} | n/a |")
    b = pts[rng.permutation(n)]
    short = (
        pts
        + (b - pts)
        * np.minimum(1.0, 3.0 / np.maximum(np.linalg.norm(b - pts, axis=1), 1e-9))[:, None]
    )
    free, t = timed(lambda: m.segment_free(pts, short))
    rows.append(
        f"| {name} | segment_free (<= 3 m; {np.mean(np.asarray(free)):.0%} free) | {n} "
        f"| {n / t:,.0f} | {t:.2f} | n/a |"
    )
    return rows


def online_rows(
    name: str,
    config: MapConfig,
    scans: list[Scan],
    args: argparse.Namespace,
    clip: tuple[float, float] | None = None,
) -> list[str]:
    """Rows: a planner's distance reads after each insert, against the insert's time.

    After each scan is inserted the map is settled (the fits the insert deferred: a
    read pays them first), then ``distance`` is read at ``--window-points`` points
    uniform in a ``2 * --window`` m box around the sensor (the vertical axis clipped
    to ``clip``) with ``max_distance=--window``, read again (the kept tree), and read
    without a bound. Scans while the map learns its hyperparameters are left out.
    """
    m = OnlineMap(config)
    rng = np.random.default_rng(1)
    cols: dict[str, list[float]] = {k: [] for k in ("insert", "settle", "win", "again", "whole")}
    cap, d = args.window, config.dim
    for s in scans:  # a planner's loop: insert, then read around the robot
        _, t_insert = timed(lambda s=s: m.insert_scan(s))
        _, t_settle = timed(m.settle)
        if m.hyperparameters is None:
            continue
        pts = s.origin + rng.uniform(-cap, cap, (args.window_points, d))
        if clip is not None:
            pts[:, -1] = np.clip(pts[:, -1], *clip)
        _, t_win = timed(lambda pts=pts: m.distance(pts, max_distance=cap))
        _, t_again = timed(lambda pts=pts: m.distance(pts, max_distance=cap))
        _, t_whole = timed(lambda pts=pts: m.distance(pts))
        for k, t in zip(cols, (t_insert, t_settle, t_win, t_again, t_whole), strict=True):
            cols[k].append(t)
    tot = {k: float(np.sum(v)) for k, v in cols.items()}
    step = tot["insert"] + tot["settle"]
    n = len(cols["insert"])
    ms = {k: 1e3 * float(np.median(v)) for k, v in cols.items()}
    return [
        f"| {name} | {n} | {ms['insert']:.2f} + {ms['settle']:.2f} | {ms['win']:.2f} "
        f"({tot['win'] / step:.1%}) | {ms['again']:.2f} ({tot['again'] / step:.1%}) "
        f"| {ms['whole']:.2f} ({tot['whole'] / step:.1%}) |"
    ]


def intel(args: argparse.Namespace) -> tuple[list[str], list[str], list[str]]:
    """The Intel lab log: ray, point and online rows."""
    scans: list[Scan] = list(load_scans(INTEL))
    m = OnlineMap(MapConfig(dim=2, resolution=0.1))
    ref = OctomapReference(0.1, 2)
    _, t_build = timed(lambda: [m.insert_scan(s) for s in scans] and m.settle())
    for s in scans:
        ref.insert_scan(s)
    print(f"intel: {len(scans)} scans mapped in {t_build:.1f} s")
    o, u, t = [], [], []
    for s in scans[::10]:  # the returned beams of every tenth scan
        v = s.points - s.origin
        r = np.linalg.norm(v, axis=1)
        ok = (r > 0) & (r < (s.max_range if s.max_range is not None else np.inf))
        o.append(np.broadcast_to(s.origin, v[ok].shape))
        u.append(v[ok] / r[ok, None])
        t.append(r[ok])
    rng = np.random.default_rng(0)
    oo, uu, tt = np.concatenate(o), np.concatenate(u), np.concatenate(t)
    pick = rng.choice(oo.shape[0], min(args.rays, oo.shape[0]), replace=False)
    rows = ray_rows(
        "intel", m, ref, oo[pick], uu[pick], 30.0, tt[pick], np.ones(pick.size, dtype=bool), None
    )
    centres, _ = m.voxels()
    pts = rng.uniform(centres.min(axis=0), centres.max(axis=0), (args.points, 2))
    online = online_rows("intel", m.config, scans, args)
    return rows, point_rows("intel", m, pts, None, rng), online


def street(args: argparse.Namespace) -> tuple[list[str], list[str], list[str]]:
    """The simulated street (64 x 1024 lidar to 80 m, 7 scans 1 m apart): ray rows only.

    Held out: the scan 1 m past the last training one (never mapped); its returns' exact
    ranges (no range noise), those onto observed surfaces scored; the true surfaces are the
    street's boxes and the ground (``z = 0``).
    """
    mission = simulate_car_street()
    scans = [mission.scan(100 + k).downsample(0.2) for k in range(7)]
    hp = None if args.learn else HP3
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp))
    ref = OctomapReference(0.2, 3)
    t_build = map_both(m, ref, scans)
    print(f"street: {len(scans)} scans mapped in {t_build:.1f} s")
    held = mission.scan(107)
    delta = held.points - held.origin
    r = np.linalg.norm(delta, axis=1)
    ret = r < (held.max_range or np.inf) * (1 - 1e-9)  # returns: their ranges are exact
    u, t = delta[ret] / r[ret, None], r[ret]
    rng = np.random.default_rng(0)
    pick = rng.choice(t.size, min(args.rays, t.size), replace=False)
    o, u, t = np.broadcast_to(held.origin, (pick.size, 3)), u[pick], t[pick]
    ends = np.concatenate([s.points for s in scans])
    gap, _ = cKDTree(ends).query(o + t[:, None] * u)
    ground = np.array([[-1e5, -1e5, -10.0, 1e5, 1e5, 0.0]])
    boxes = np.vstack([mission.boxes, ground])
    rows = ray_rows("street", m, ref, o, u, 80.0, t, gap <= 0.2, boxes)
    return rows, [], []


def office(args: argparse.Namespace) -> tuple[list[str], list[str], list[str]]:
    """The paper's 2D world (22 x 18 m of boxes), 56 poses of 361 beams without noise: rays.

    Every fourth pose is held out (never mapped); its returns' exact ranges, those onto
    observed surfaces scored. The map is the default config at 0.1 m (hyperparameters
    learnt from the mapped scans).
    """
    sim = simulate_paper2d(0, noise=False, n_poses=56, n_beams=361)
    train = [s for i, s in enumerate(sim.scans) if i % 4]
    held = [s for i, s in enumerate(sim.scans) if i % 4 == 0]
    m = OnlineMap(MapConfig(dim=2, resolution=0.1))
    ref = OctomapReference(0.1, 2)
    t_build = map_both(m, ref, train)
    print(f"office: {len(train)} scans mapped in {t_build:.1f} s")
    o, u, t = [], [], []
    for s in held:  # the held-out returns and their exact ranges
        delta = s.points - s.origin
        r = np.linalg.norm(delta, axis=1)
        ret = r < (s.max_range or np.inf) * (1 - 1e-9)
        o.append(np.broadcast_to(s.origin, (int(ret.sum()), 2)))
        u.append(delta[ret] / r[ret, None])
        t.append(r[ret])
    oo, uu, tt = np.concatenate(o), np.concatenate(u), np.concatenate(t)
    rng = np.random.default_rng(0)
    pick = rng.choice(tt.size, min(args.rays, tt.size), replace=False)
    oo, uu, tt = oo[pick], uu[pick], tt[pick]
    ends = np.concatenate([s.points for s in train])
    gap, _ = cKDTree(ends).query(oo + tt[:, None] * uu)
    rows = ray_rows("office", m, ref, oo, uu, 30.0, tt, gap <= 0.1, sim.obstacles)
    return rows, [], []


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", default="room,intel")
    parser.add_argument("--room-poses", type=int, default=12)
    parser.add_argument("--rays", type=int, default=20_000)
    parser.add_argument("--points", type=int, default=20_000)
    parser.add_argument("--window", type=float, default=2.0, help="metres: half-box, max_distance")
    parser.add_argument("--window-points", type=int, default=1000)
    parser.add_argument(
        "--learn",
        action="store_true",
        help="room, street: learn the hyperparameters from the scans (the default config) "
        "instead of giving length scale 0.8 m",
    )
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}")
    mesh_table = [
        "| scene | surface | points | seconds | accuracy median (m) | accuracy mean (m) "
        "| completeness median (m) | completeness mean (m) | Chamfer (m) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    ray_table = [
        "| scene | mapper | unknown | threshold | rays | rays/s | rays onto observed surfaces "
        "| hit | within 1 voxel | median error (m) | p99 error (m) "
        "| hit point to true surface: median (m) / within 1 voxel |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    point_table = [
        "| scene | query | points | points/s | seconds | error vs exact |",
        "|---|---|---|---|---|---|",
    ]
    online_table = [
        "| scene | scans | insert + settle (ms, median) | window read (ms; share of insert + "
        "settle, sums) | again (kept) | unbounded read |",
        "|---|---|---|---|---|---|",
    ]
    for scene in args.scenes.split(","):  # room, intel, street, office
        rays, points, online = {"room": room, "intel": intel, "street": street, "office": office}[
            scene
        ](args)
        ray_table += [r for r in rays if "surface" not in r and "centres" not in r]
        mesh_table += [r for r in rays if "surface" in r or "centres" in r]
        point_table += points
        online_table += online
    print("\n".join(ray_table))
    print()
    print("\n".join(point_table))
    print()
    print("\n".join(mesh_table))
    print()
    print("\n".join(online_table))


if __name__ == "__main__":
    main()
