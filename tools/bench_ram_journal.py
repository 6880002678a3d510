"""The RAM a map without a file spends on its journal (``OnlineMap.journal_bytes``).

Figures: BENCHMARKS.md, "The journal of a map in memory".

A map made without a path keeps its journal in RAM so that ``correct_scans`` and
``correct_poses`` work on it (:class:`octolgp.persist.memory.MemoryJournal`): the latest
``journal_scans`` to twice that many scans as the map file stores them, and per
checkpoint the evidence records of the leaves changed since. Two missions, default
config (``scan_precision`` 1 cm, ``journal_scans`` 1,000 unless ``--window``):

- ``intel``: the Intel lab's CARMEN log (910 scans of 180 beams), a 2D map at 0.1 m,
  inserted in batches of 50 scans (checkpoints every ``--window`` scans);
- ``street``: the simulated 64-ring street filtered at 0.2 m (``--street`` scans), the
  journal's scans alone (no map: the scans are what grows with the window).

Printed per mission: scans, beams, journal bytes (scans and kept leaf records), bytes per
scan and per beam, and the seconds spent encoding scans per scan (what the in-memory
journal adds to an insert). With ``--insert`` also the insert itself with and without the
journal (``OnlineMap(config, journal=False)``): the 32 x 1024 lidar room, 12 scans filtered
at 0.1 m, 3D at 0.2 m, ``insert_scan`` then ``settle``, two rounds each.

    .venv/bin/python tools/bench_ram_journal.py
    .venv/bin/python tools/bench_ram_journal.py --window 200 --street 40
    .venv/bin/python tools/bench_ram_journal.py --insert
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

from octolgp import MapConfig, OnlineConfig, OnlineMap, load_scans
from octolgp.persist.journal import encode_points
from octolgp.persist.memory import MemoryJournal
from octolgp.scan import Scan

INTEL = Path(__file__).resolve().parent.parent / "data/intel_lab/intel-corrected.log.gz"


def encode_seconds(scans: list[Scan], precision: float) -> float:
    """Seconds per scan to encode the rounded scans as the journal does."""
    rounded = [s.rounded(precision) for s in scans]
    t = time.perf_counter()
    for s in rounded:  # one blob per scan
        encode_points(s, precision)
    return (time.perf_counter() - t) / len(rounded)


def scans_only(config: MapConfig, scans: list[Scan]) -> MemoryJournal:
    """A journal of these (rounded) scans alone, as the map keeps them."""
    journal = MemoryJournal(config.resolve(), lambda _: None)
    for i, s in enumerate(scans, start=1):  # one row per scan
        journal.record([], [(i, s)], None, i)
    return journal


def report(name: str, scans: list[Scan], journaled: list[Scan], total: int, rows: int) -> None:
    """One line: the mission, the journal's scans and leaf records, per scan and beam."""
    beams = sum(len(s) for s in scans)
    n = len(journaled)
    per_beam = rows / max(1, sum(len(s) for s in journaled))
    seconds = encode_seconds(scans, 0.01)
    print(
        f"{name}: {len(scans)} scans, {beams} beams; journal {n} scans: "
        f"{rows / 1e6:.2f} MB of scans + {(total - rows) / 1e6:.2f} MB of leaf records = "
        f"{total / 1e6:.2f} MB; {rows / max(1, n) / 1e3:.2f} kB per scan, "
        f"{per_beam:.2f} B per beam; encoding {seconds * 1e3:.2f} ms per scan"
    )


def insert_seconds() -> None:
    """Seconds per scan of ``insert_scan`` (then ``settle``) with and without the journal."""
    from octolgp import Hyperparameters
    from octolgp.sim.lidar3d import simulate_lidar_room

    room = simulate_lidar_room(12, n_azimuth=1024, n_elevation=32, n_heldout=0)
    scans = [s.downsample(0.1) for s in room.scans()]
    hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=hp)
    OnlineMap(config).insert_scan(scans[0])  # warm-up: imports, compiled kernels
    for rnd in range(2):  # two rounds, alternating
        for journal in (True, False):
            m = OnlineMap(config, journal=journal)
            t = time.perf_counter()
            for s in scans:  # one insert per scan
                m.insert_scan(s)
            m.settle()
            ms = (time.perf_counter() - t) / len(scans) * 1e3
            print(f"room insert, round {rnd + 1}, journal={journal}: {ms:.1f} ms a scan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--window", type=int, default=1000, help="journal_scans (1000)")
    parser.add_argument("--street", type=int, default=20, help="street scans (20)")
    parser.add_argument("--insert", action="store_true", help="time inserts, with and without")
    args = parser.parse_args()
    if args.insert:
        insert_seconds()
        return
    print(f"{platform.processor() or platform.machine()}, Python {platform.python_version()}")
    online = OnlineConfig(journal_scans=args.window)
    scans = list(load_scans(INTEL))
    config = MapConfig(dim=2, resolution=0.1, online=online)
    m = OnlineMap(config)
    for lo in range(0, len(scans), 50):  # batches: checkpoints advance between them
        m.insert_batch(scans[lo : lo + 50])
    journaled = list(m.scans())
    report("intel", scans, journaled, m.journal_bytes, scans_only(config, journaled).nbytes)

    from octolgp.sim.mission import simulate_car_street

    mission = simulate_car_street(range_noise=0.02)
    street = [mission.scan(k).downsample(0.2) for k in range(args.street)]
    config = MapConfig(dim=3, resolution=0.2, online=online)
    journal = scans_only(config, [s.rounded(0.01) for s in street])
    report("street", street, list(journal.scans()), journal.nbytes, journal.nbytes)


if __name__ == "__main__":
    main()
