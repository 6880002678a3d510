"""A map that follows a changing world: octolgp and the real OctoMap on moved objects.

Figures: BENCHMARKS.md, "Moved objects, against the real OctoMap".

Scenes (``octolgp.sim.dynamic``, exact geometry, no noise):

- 2D office at 0.1 m (``simulate_dynamic_office``): 140 scans of a 180-beam 360° laser
  (8 m range) from a robot circling the room, 40 scans a lap. A 0.8 m crate stands at A
  until scan 45, then at B; the door (0.1 m thick, in a 0.9 m wall gap) is closed until
  scan 60, then open; person 1 walks across the room from scan 70 (15 scans), person 2
  along its east side from scan 96 (12 scans), 0.6 m a scan.
- 3D room at 0.2 m (``simulate_dynamic_room3d``): 48 scans of a 16 x 360 lidar, each
  through ``Scan.downsample(0.2)``; a 1 m cube at A until scan 16, then at B.

Maps, all fed the same scans in the same run: octolgp as a user gets it
(``OnlineMap(MapConfig(dim=2, resolution=0.1))`` / ``(dim=3, resolution=0.2)``, changed
only by ``--set`` and the hyperparameters), the same with ``online.clear_scans=0`` (a
static world, the reference), or with each ``--sweep`` value; and OctoMap's ``OcTree`` at
the same resolution with its default sensor model (``octolgp.bench.octomap_ref``; 2D
scans go in as the voxel layer ``0 <= z < resolution``).

Hyperparameters: given by default (``HP_2D`` / ``HP_3D``: what the default learning
finds on these scenes, rounded), so no map spends its first scans buffering; ``--learn``
learns them as a user's map does (on the first 40 / 5 scans; the events come later).

Measures (per map, after every insert, P(occupied) read at the voxel centres involved):

- **left** (an object's former cells): the voxels an object covered (its box overlaps
  them) or put returns in, once it has left them, excluding any voxel another box
  covers or a return lands in afterwards, and kept when *observed*: seen free afterwards
  by at least one scan (a beam's free part, ``DynamicScene.free_voxels``). Reported: the
  fraction of them reading P < 0.5 at the end; how many read P > 0.5 just before the
  object left (the map had them: a ghost if they stay) and the fraction of those cleared
  at the end; per such voxel, *scans to clear* = scans from the first one after it was
  vacated until the map reads P < 0.5 there from then to the end (1: the first scan after
  did it), median / max (max "—" when some never clear), and *looks* = how many of those
  scans saw it free, median. The box of an object covers voxels it only half fills
  (faces lie on voxel centres), and the voxels inside it were never observed.
- **appeared** (a new position: the crate at B, each step of a person, the cube at B):
  the voxels its returns fell in during that stay; per voxel the scans from its first
  return until the map reads P > 0.5 there (1: at once). Reported: the fraction occupied
  at once, the fraction occupied at the end of the stay, median / max scans (over those
  that registered; max "—" when some never do).
- **static scene** at the end: voxel centres of the scene's extent labelled by the static
  geometry, occupied = overlapping a static box and holding a return of some scan, free =
  seen free by some scan and never covered by any box or holding a return. Cells a moving
  object ever covered or put a return in are left out (the moved objects are measured
  above). AUC with unknown points at 0.5 (``octolgp.bench.heldout.evaluate``), the
  unknown fraction, and at the 0.5 threshold the fractions of free cells read occupied
  and of occupied cells read free.

Timing: ``insert_scan`` wall clock per scan (median / max) of each map; the reads are not
timed. octolgp uses the machine's cores (``online.n_jobs``), OctoMap one.

Run from the repository root::

    .venv/bin/python tools/bench_dynamic.py                      # default vs clear_scans=0 vs OctoMap
    .venv/bin/python tools/bench_dynamic.py --sweep 0,2,3,5,8    # several clear_scans in one run
    .venv/bin/python tools/bench_dynamic.py --set online.clear_scans=3 --learn
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import os
import platform
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

import octolgp
from octolgp import Hyperparameters, MapConfig, OnlineMap
from octolgp.bench.heldout import evaluate
from octolgp.bench.octomap_ref import OctomapReference, octomap_available
from octolgp.scan import Scan
from octolgp.sim.dynamic import (
    NO_RETURN,
    DynamicScene,
    footprint_voxels,
    simulate_dynamic_office,
    simulate_dynamic_room3d,
    voxel_keys,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling tool's helpers
from bench_3d import apply_setting, cpu_model, git_revision

HP_2D = Hyperparameters(
    length_scale=0.85, signal_variance=1.8, noise_variance=0.01, alpha=4.3, beta=0.0
)
"""Given 2D hyperparameters: the default learning on the office's first 40 scans, rounded."""
HP_3D = Hyperparameters(
    length_scale=3.4, signal_variance=71.0, noise_variance=0.01, alpha=4.8, beta=0.11
)
"""Given 3D hyperparameters: the default learning on the room's first 5 scans, rounded."""

_BITS = 21  # bits per axis of a packed voxel key
_OFF = 1 << (_BITS - 1)


class Peer(Protocol):
    """A map: ``insert_scan`` and ``occupancy``."""

    def insert_scan(self, scan: Scan) -> Any:
        """Insert one scan."""

    def occupancy(self, points: np.ndarray) -> np.ndarray:
        """P(occupied) at points ``(q, d)``."""


# ----------------------------------------------------------------------------- truth
def _pack(keys: np.ndarray) -> np.ndarray:
    """One int64 per voxel index row ``(n, d)``."""
    out = np.zeros(keys.shape[0], dtype=np.int64)
    for a in range(keys.shape[1]):
        out |= (keys[:, a] + _OFF) << (_BITS * a)
    return out


def _unpack(packed: np.ndarray, dim: int) -> np.ndarray:
    return np.column_stack(
        [((packed >> (_BITS * a)) & ((1 << _BITS) - 1)) - _OFF for a in range(dim)]
    )


def _member(packed: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of ``packed`` in the sorted ``table`` and whether each is there."""
    pos = np.searchsorted(table, packed)
    pos_c = np.minimum(pos, table.size - 1)
    return pos_c, table[pos_c] == packed


@dataclass
class Truth:
    """Ground truth of a scene at one resolution, over the voxels the measures track.

    ``tracked`` are the voxels any object covers or puts a return in; the boolean arrays
    are ``(n_scans, n_tracked)``.
    """

    scene: DynamicScene
    resolution: float
    scans: list[Scan]
    tracked: np.ndarray  # packed keys, sorted
    centres: np.ndarray  # (T, d)
    covered: list[np.ndarray]  # per object: its box overlaps the voxel, or it returned there
    covered_any: np.ndarray  # any box overlaps the voxel
    returned: np.ndarray  # any return of the scan in the voxel
    returned_by: list[np.ndarray]  # per object: a return of that object in the voxel
    seen_free: np.ndarray
    test_points: np.ndarray
    test_labels: np.ndarray


def build_truth(scene: DynamicScene, resolution: float) -> Truth:
    """Everything the measures need from the exact geometry (see the module docstring)."""
    d, n = scene.dim, scene.n_scans
    cast = [scene.cast(i) for i in range(n)]
    hit_keys = [_pack(voxel_keys(s.points[own != NO_RETURN], resolution)) for s, own in cast]
    hit_owner = [own[own != NO_RETURN] for _, own in cast]
    free = [_pack(scene.free_voxels(i, resolution)) for i in range(n)]
    parts = []
    for j, obj in enumerate(scene.objects):
        parts += [_pack(footprint_voxels(box, resolution)) for _, _, box in obj.stints]
        parts += [h[o == j] for h, o in zip(hit_keys, hit_owner, strict=True)]
    tracked = np.unique(np.concatenate(parts))
    T = tracked.size
    centres = (_unpack(tracked, d) + 0.5) * resolution

    def mark(rows: list[np.ndarray]) -> np.ndarray:
        out = np.zeros((n, T), dtype=bool)
        for i, keys in enumerate(rows):
            pos, ok = _member(keys, tracked)
            out[i, pos[ok]] = True
        return out

    static_fp = np.zeros(T, dtype=bool)
    for box in scene.static_boxes:
        pos, ok = _member(_pack(footprint_voxels(box, resolution)), tracked)
        static_fp[pos[ok]] = True
    covered, returned_by = [], []
    covered_any = np.repeat(static_fp[None, :], n, axis=0)
    for j, obj in enumerate(scene.objects):
        fp = np.zeros((n, T), dtype=bool)
        for first, end, box in obj.stints:
            pos, ok = _member(_pack(footprint_voxels(box, resolution)), tracked)
            fp[first:end, pos[ok]] = True
        covered_any |= fp
        by = mark([h[o == j] for h, o in zip(hit_keys, hit_owner, strict=True)])
        returned_by.append(by)
        covered.append(fp | by)
    returned = mark(hit_keys)
    seen_free = mark(free)

    # static test cells over the extent
    lo = np.floor(scene.extent[0] / resolution + 1e-9).astype(np.int64)
    hi = np.ceil(scene.extent[1] / resolution - 1e-9).astype(np.int64)
    all_free = np.unique(np.concatenate(free))
    all_hits = np.unique(np.concatenate(hit_keys))
    static_hits = np.unique(
        np.concatenate([h[o == -1] for h, o in zip(hit_keys, hit_owner, strict=True)])
    )
    static_cells = np.unique(
        np.concatenate([_pack(footprint_voxels(b, resolution)) for b in scene.static_boxes])
    )
    occupied = np.intersect1d(static_cells, static_hits)
    ever_dynamic = tracked  # every voxel an object covered or returned in
    free_cells = np.setdiff1d(all_free, np.concatenate([static_cells, all_hits, ever_dynamic]))
    occupied = np.setdiff1d(occupied, ever_dynamic)
    keys = _unpack(np.concatenate([occupied, free_cells]), d)
    inside = np.all((keys >= lo) & (keys < hi), axis=1)
    labels = np.concatenate([np.ones(occupied.size, np.int8), np.zeros(free_cells.size, np.int8)])
    return Truth(
        scene=scene,
        resolution=resolution,
        scans=[s for s, _ in cast],
        tracked=tracked,
        centres=centres,
        covered=covered,
        covered_any=covered_any,
        returned=returned,
        returned_by=returned_by,
        seen_free=seen_free,
        test_points=(keys[inside] + 0.5) * resolution,
        test_labels=labels[inside],
    )


# ----------------------------------------------------------------------------- runs
@dataclass
class Run:
    """One map's pass over a scene."""

    label: str
    probs: np.ndarray  # (n_scans, T), NaN while the map only buffers
    insert_s: list[float]
    auc: dict[str, float | int]
    note: str = ""


def run_map(label: str, make: Callable[[], Peer], truth: Truth) -> Run:
    """Insert every scan, reading the tracked voxels after each; score the static test cells."""
    peer = make()
    n = len(truth.scans)
    probs = np.full((n, truth.tracked.size), np.nan)
    seconds = []
    for i, scan in enumerate(truth.scans):
        t = time.perf_counter()
        peer.insert_scan(scan)
        seconds.append(time.perf_counter() - t)
        if isinstance(peer, OnlineMap) and peer.provisional:
            continue  # a read would fit the buffered scans and throw the fit away
        probs[i] = peer.occupancy(truth.centres)
    note = "—"
    if isinstance(peer, OnlineMap):
        if peer.provisional:
            peer.flush()
        hp = peer.hyperparameters
        note = (
            "—"
            if hp is None
            else f"l={hp.length_scale:.3g} σf²={hp.signal_variance:.3g} α={hp.alpha:.3g} β={hp.beta:.3g}"
        )
    scores = evaluate(peer, truth.test_points, truth.test_labels)
    p = peer.occupancy(truth.test_points)
    free, occ = truth.test_labels == 0, truth.test_labels == 1
    scores["free read occupied"] = float(np.mean(p[free] > 0.5))
    scores["occupied read free"] = float(np.mean(p[occ] < 0.5))
    return Run(label, probs, seconds, scores, note)


def _fmt_scans(values: list[int], complete: bool) -> str:
    if not values:
        return "—"
    med = float(np.median(values))
    top = str(max(values)) if complete else "—"
    return f"{med:g} / {top}"


def left_measures(truth: Truth, run: Run, j: int) -> dict[str, str] | None:
    """The "left" measures of object ``j`` (None where it never vacates a voxel)."""
    cov = truth.covered[j]
    n = cov.shape[0]
    rows = []
    for v in np.flatnonzero(cov.any(axis=0)):
        t = int(np.flatnonzero(cov[:, v])[-1]) + 1  # the first scan after it left v
        if t >= n or truth.covered_any[t:, v].any() or truth.returned[t:, v].any():
            continue
        if truth.seen_free[t:, v].any():
            rows.append((v, t))
    if not rows:
        return None
    ghost, cleared, scans, looks, ghost_cleared = [], [], [], [], []
    for v, t in rows:
        p = run.probs[:, v]
        was = bool(p[t - 1] > 0.5)  # NaN (buffering) is not occupied
        ghost.append(was)
        post = p[t:]
        ok = bool(post[-1] < 0.5)
        cleared.append(ok)
        if not was:
            continue
        ghost_cleared.append(ok)
        if ok:
            bad = np.flatnonzero(~(post < 0.5))  # NaN counts as not free
            c = 0 if bad.size == 0 else int(bad[-1]) + 1
            scans.append(c + 1)
            looks.append(int(truth.seen_free[t : t + c + 1, v].sum()))
    return {
        "cells": str(len(rows)),
        "cleared at end": f"{np.mean(cleared):.2f}",
        "occupied before": str(sum(ghost)),
        "of those cleared at end": f"{np.mean(ghost_cleared):.2f}" if ghost_cleared else "—",
        "scans to clear (median / max)": _fmt_scans(scans, all(ghost_cleared)),
        "looks to clear (median)": f"{np.median(looks):g}" if looks else "—",
    }


def appear_measures(truth: Truth, run: Run, j: int) -> dict[str, str] | None:
    """The "appeared" measures of object ``j``: its stays that start after scan 0."""
    obj = truth.scene.objects[j]
    by = truth.returned_by[j]
    at_once, at_end, scans, n_cells = [], [], [], 0
    for first, end, _ in obj.stints:
        if first == 0:
            continue
        for v in np.flatnonzero(by[first:end].any(axis=0)):
            h = first + int(np.flatnonzero(by[first:end, v])[0])
            p = run.probs[h:end, v]
            occ = np.flatnonzero(p > 0.5)
            n_cells += 1
            at_once.append(bool(occ.size and occ[0] == 0))
            at_end.append(bool(p[-1] > 0.5))
            if occ.size:
                scans.append(int(occ[0]) + 1)
    if not n_cells:
        return None
    return {
        "cells": str(n_cells),
        "occupied at once": f"{np.mean(at_once):.2f}",
        "occupied at end of stay": f"{np.mean(at_end):.2f}",
        "scans to occupy (median / max)": _fmt_scans(scans, len(scans) == n_cells),
    }


def print_tables(truth: Truth, runs: list[Run]) -> None:
    """The left / appeared / static tables of one scene."""
    scene = truth.scene
    print(f"\n## {scene.name} ({scene.n_scans} scans, {truth.resolution:g} m)\n")
    events = []
    for obj in scene.objects:
        starts = [f for f, _, _ in obj.stints]
        events.append(
            f"{obj.name}: stays start at scans {starts[:3]}{' ...' if len(starts) > 3 else ''}"
        )
    print("Objects: " + "; ".join(events) + ".\n")
    print("### Left: former cells reading free (P < 0.5)\n")
    print(
        "Scans and looks to clear: over the cells that read occupied just before the object "
        "left them (the ghost that forgetting must clear).\n"
    )
    cols = [
        "cells",
        "cleared at end",
        "occupied before",
        "of those cleared at end",
        "scans to clear (median / max)",
        "looks to clear (median)",
    ]
    print("| object | map | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for j, obj in enumerate(scene.objects):
        for run in runs:
            m = left_measures(truth, run, j)
            if m is not None:
                print(f"| {obj.name} | {run.label} | " + " | ".join(m[c] for c in cols) + " |")
    print("\n### Appeared: new cells reading occupied (P > 0.5)\n")
    cols = [
        "cells",
        "occupied at once",
        "occupied at end of stay",
        "scans to occupy (median / max)",
    ]
    print("| object | map | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for j, obj in enumerate(scene.objects):
        for run in runs:
            m = appear_measures(truth, run, j)
            if m is not None:
                print(f"| {obj.name} | {run.label} | " + " | ".join(m[c] for c in cols) + " |")
    n_occ = int(truth.test_labels.sum())
    print(
        f"\n### Static scene at the end ({truth.test_labels.size} test cells, {n_occ} occupied)\n"
    )
    print(
        "| map | AUC (unknown = 0.5) | AUC on known | unknown fraction | free cells P > 0.5 "
        "| occupied cells P < 0.5 | insert ms median / max | hyperparameters |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for run in runs:
        a = run.auc
        ms = np.array(run.insert_s) * 1e3
        print(
            f"| {run.label} | {a['auc']:.4f} | {a['auc_known']:.4f} | {a['unknown_fraction']:.3f} "
            f"| {a['free read occupied']:.3f} | {a['occupied read free']:.3f} "
            f"| {np.median(ms):.1f} / {ms.max():.0f} | {run.note} |"
        )


# ----------------------------------------------------------------------------- main
def octolgp_configs(
    args: argparse.Namespace, dim: int, resolution: float
) -> list[tuple[str, MapConfig]]:
    """``(label, config)`` of every octolgp map of one scene."""
    base = MapConfig(dim=dim, resolution=resolution)
    if not args.learn:
        base = dataclasses.replace(base, hyperparameters=HP_2D if dim == 2 else HP_3D)
    for setting in args.set:
        base = apply_setting(base, setting)
    if args.sweep is not None:
        return [
            (f"octolgp clear_scans={k}", apply_setting(base, f"online.clear_scans={k}"))
            for k in args.sweep
        ]
    label = "octolgp" + (" " + " ".join(args.set) if args.set else " default")
    return [
        (f"{label} (clear_scans={base.clear_scans})", base),
        ("octolgp clear_scans=0 (static)", apply_setting(base, "online.clear_scans=0")),
    ]


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="change one MapConfig setting of every octolgp map (repeatable)",
    )
    parser.add_argument(
        "--sweep",
        type=lambda s: [int(k) for k in s.split(",") if k.strip()],
        default=None,
        metavar="K,K,...",
        help="run one octolgp map per online.clear_scans value (instead of default + 0)",
    )
    parser.add_argument(
        "--learn", action="store_true", help="learn the hyperparameters as a user's map does"
    )
    parser.add_argument("--no-2d", action="store_true", help="skip the 2D office")
    parser.add_argument("--no-3d", action="store_true", help="skip the 3D room")
    parser.add_argument("--no-octomap", action="store_true", help="skip OctoMap")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print its Markdown tables; return the exit status."""
    args = parse_args(argv)
    words = sys.argv[1:] if argv is None else list(argv)
    start = time.perf_counter()
    print("# A changing world: octolgp vs OctoMap (issue #15)\n")
    command = f".venv/bin/python tools/bench_dynamic.py {shlex.join(words)}".rstrip()
    print(f"Command: `{command}`")
    print(
        f"Machine: {cpu_model()}, {os.cpu_count()} cores ({len(os.sched_getaffinity(0))} usable); "
        f"{platform.system()} {platform.release()}; Python {platform.python_version()}, "
        f"numpy {np.__version__}; octolgp {octolgp.__version__} from {git_revision()}; "
        f"{datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}"
    )
    print(
        "Hyperparameters: "
        + (
            "learnt by each octolgp map on its first learn_scans scans (as a user's map does)."
            if args.learn
            else f"given (2D {HP_2D}; 3D {HP_3D}); --learn learns them."
        )
    )
    use_octomap = octomap_available() and not args.no_octomap
    if not octomap_available():
        print("OctoMap: pyoctomap is not installed; its rows are missing.")
    scenes: list[tuple[DynamicScene, float]] = []
    if not args.no_2d:
        scenes.append((simulate_dynamic_office(), 0.1))
    if not args.no_3d:
        scenes.append((simulate_dynamic_room3d(), 0.2))
    for scene, res in scenes:
        truth = build_truth(scene, res)
        runs = []
        for label, config in octolgp_configs(args, scene.dim, res):
            runs.append(run_map(label, functools.partial(OnlineMap, config), truth))
        if use_octomap:
            make = functools.partial(OctomapReference, res, scene.dim)
            runs.append(run_map("OctoMap", make, truth))
        print_tables(truth, runs)
    print(f"\nTotal {time.perf_counter() - start:.0f} s.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
