"""The quality table from ``octolgp eval --out`` folders, one per log.

Figures: BENCHMARKS.md, "Map quality on every log".

Reads each folder's ``results.json`` (written by ``octolgp eval``) and prints, per log and
method, AUC mean ± std and the worst split, then per log the splits below 0.95 with the share
of their held-out returns that no training return lies within 0.3 m of, and the learnt
hyperparameters' mean ± std over the splits. Several folders may hold the methods of one
log (``NAME=DIR[,DIR...]``), for example the online map re-run after a change beside the
peers run once::

    python tools/quality_table.py intel=eval/intel orebro=eval/orebro,peers/orebro
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

LABELS = {
    "online": "octolgp online",
    "batch": "octolgp batch",
    "grid": "grid",
    "octomap": "OctoMap",
}


def main() -> None:
    """Print the tables."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("logs", nargs="+", help="NAME=DIR[,DIR...]: eval --out folders of one log")
    args = ap.parse_args()
    rows, fails, hps = [], [], []
    for item in args.logs:
        name, _, dirs = item.partition("=")
        merged: dict = {"per_split": {}, "novel": None, "hyperparameters": None}
        for d in dirs.split(","):  # the first folder holding a method wins
            res = json.loads((Path(d) / "results.json").read_text())
            for method, splits in res["per_split"].items():
                merged["per_split"].setdefault(method, splits)
            if merged["novel"] is None:
                merged["novel"] = res.get("novel")
            if merged["hyperparameters"] is None:
                merged["hyperparameters"] = res.get("hyperparameters")
        cells = []
        for method in ("online", "grid", "octomap"):
            aucs = np.array([r["auc"] for r in merged["per_split"].get(method, [])])
            cells.append(
                f"{aucs.mean():.4f} ± {aucs.std():.4f} (worst {aucs.min():.4f})"
                if aucs.size
                else "not run"
            )
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
        online = [r["auc"] for r in merged["per_split"].get("online", [])]
        novel = merged["novel"] or [float("nan")] * len(online)
        for i, (a, n) in enumerate(zip(online, novel, strict=True)):
            if a < 0.95:
                fails.append(f"| {name} | seed {i} | {a:.4f} | {n:.2f} |")
        if merged["hyperparameters"]:
            hp = merged["hyperparameters"]
            cols = [
                f"{np.mean([h[k] for h in hp]):.3g} ± {np.std([h[k] for h in hp]):.2g}"
                for k in ("length_scale", "signal_variance", "noise_variance", "alpha", "beta")
            ]
            hps.append(f"| {name} | " + " | ".join(cols) + " |")
    print("| log | octolgp online | grid | OctoMap |\n|---|---|---|---|")
    print("\n".join(rows))
    print("\n| log | split | online AUC | held-out returns with no training return within 0.3 m |")
    print("|---|---|---|---|")
    print("\n".join(fails))
    print("\n| log | length scale (m) | σf² | σn² | α | β |\n|---|---|---|---|---|---|")
    print("\n".join(hps))


if __name__ == "__main__":
    main()
