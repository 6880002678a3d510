"""Kim & Kim Table II, Fig. 3 (c–f) and Fig. 4 on the paper's 2D simulation, in one run.

All four methods map the same simulated data set in one process. As in the paper,
the timed runs take the hyperparameters and α, β as given; learning them is timed
separately. Each method is run ``repeats`` times and the median is reported.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from sklearn.metrics import roc_auc_score, roc_curve

from octolgp.batch.build import build_map
from octolgp.bench.fig2 import Fig2Result, run_fig2
from octolgp.config import Hyperparameters, MapConfig, PartitionConfig
from octolgp.gp.learning import learn_hyperparameters
from octolgp.sim.scenes import simulate_paper2d

METHOD_NAMES = MappingProxyType({"lgp": "OM_LGP", "gp": "OM_GP", "mgp": "OM_MGP", "ogm": "OGM"})
"""The paper's name of each method, in Table II order."""
PAPER_HP = MappingProxyType(
    {"l": 2.66, "sigma_f": 2.81, "sigma_n": 0.99, "alpha": 7.94, "beta": -1.42}
)
"""The hyperparameters the paper reports for its 2D simulation."""


def paper2d_config() -> MapConfig:
    """The configuration used for the paper's 2D simulation (0.2 m grid)."""
    return MapConfig(dim=2, resolution=0.2, partition=PartitionConfig(max_cluster_size=100))


@dataclass(frozen=True)
class MethodResult:
    """Median timings (seconds) and AUC of one method."""

    method: str
    clustering: float
    mapping: float
    total: float
    auc: float
    probabilities: np.ndarray


@dataclass(frozen=True)
class Paper2dResult:
    """Everything ``octolgp bench paper2d`` measures."""

    hyperparameters: Hyperparameters
    learning_seconds: float
    methods: dict[str, MethodResult]
    fig2: Fig2Result
    n_beams: int
    n_items: int
    seed_aucs: dict[str, list[float]]


def _time_method(
    scans: list[Any], config: MapConfig, method: str, test: np.ndarray, repeats: int
) -> tuple[float, float, np.ndarray]:
    """Median (clustering, total) seconds over ``repeats`` builds + predictions."""
    clus, tot = [], []
    prob = np.empty(0)
    for _ in range(repeats):  # repeated timing runs
        t0 = time.perf_counter()
        # two cores: local GPs run two clusters at a time, the global GP uses 2 BLAS threads
        m = build_map(scans, config, method=method, n_jobs=2)
        prob = m.occupancy(test)
        tot.append(time.perf_counter() - t0)
        clus.append(float(getattr(m, "timings", {}).get("clustering", 0.0)))
    return statistics.median(clus), statistics.median(tot), prob


def _seed_aucs(seeds: list[int]) -> dict[str, list[float]]:
    """AUC of each method on further simulated data sets (hyperparameters learnt on each)."""
    aucs: dict[str, list[float]] = {m: [] for m in METHOD_NAMES}
    for s in seeds:  # one simulated data set per seed
        data = simulate_paper2d(seed=s)
        config = paper2d_config()
        fixed = dataclasses.replace(
            config, hyperparameters=learn_hyperparameters(data.scans, config)
        )
        for method in METHOD_NAMES:
            prob = build_map(data.scans, fixed, method=method).occupancy(data.truth_points)
            aucs[method].append(float(roc_auc_score(data.truth_labels, prob)))
    return aucs


def run_paper2d(
    out_dir: Path | None = None, seed: int = 0, repeats: int = 5, n_seeds: int = 1
) -> Paper2dResult:
    """Run the benchmark; write PNGs into ``out_dir`` when given.

    Timings come from the data set of ``seed``; AUCs are also given over ``n_seeds``
    simulated data sets (``seed, seed + 1, ...``).
    """
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    data = simulate_paper2d(seed=seed)
    config = paper2d_config()
    t0 = time.perf_counter()
    hp = learn_hyperparameters(data.scans, config)
    learning = time.perf_counter() - t0
    fixed = dataclasses.replace(config, hyperparameters=hp)
    labels = np.asarray(data.truth_labels)
    results = {}
    for method in ("lgp", "gp", "mgp", "ogm"):
        reps = repeats if method != "gp" else max(1, min(repeats, 2))
        clus, total, prob = _time_method(data.scans, fixed, method, data.truth_points, reps)
        auc = float(roc_auc_score(labels, prob))
        results[method] = MethodResult(method, clus, total - clus, total, auc, prob)
    fig2 = run_fig2(out_dir / "fig2_1d.png" if out_dir else None, seed=seed)
    from octolgp.training import make_training_data

    n_items = make_training_data(data.scans, fixed).n_items
    seed_aucs = _seed_aucs(list(range(seed + 1, seed + n_seeds)))
    for key, m in results.items():
        seed_aucs[key].insert(0, m.auc)
    result = Paper2dResult(
        hp, learning, results, fig2, sum(len(s) for s in data.scans), n_items, seed_aucs
    )
    if out_dir is not None:
        _plot(result, data.truth_points, labels, out_dir)
    return result


def format_table(r: Paper2dResult) -> str:
    """Table II plus AUC, learnt hyperparameters and the Fig. 2 border jumps."""
    hp = r.hyperparameters
    lines = [
        f"paper2d: {r.n_beams} beams -> {r.n_items} training items (hits + free segments)",
        "",
        f"{'method':<8} {'clustering s':>13} {'mapping s':>10} {'total s':>9} {'AUC':>7}",
    ]
    for key, m in r.methods.items():
        lines.append(
            f"{METHOD_NAMES[key]:<8} {m.clustering:>13.4f} {m.mapping:>10.4f} "
            f"{m.total:>9.4f} {m.auc:>7.4f}"
        )
    lgp, gp, ogm = r.methods["lgp"], r.methods["gp"], r.methods["ogm"]
    n = len(r.seed_aucs["lgp"])
    if n > 1:
        lines += ["", f"AUC over {n} simulated data sets (mean ± std):"]
        for key, values in r.seed_aucs.items():
            lines.append(f"  {METHOD_NAMES[key]:<8} {np.mean(values):.4f} ± {np.std(values):.4f}")
    lines += [
        "",
        f"OM_LGP / OM_GP total time: {lgp.total / gp.total:.3f}   (paper 0.198; target <= 0.2)",
        f"AUC(OM_LGP) - AUC(OM_GP): {lgp.auc - gp.auc:+.4f}   (target >= -0.01)",
        f"AUC(OM_LGP) - AUC(OGM):   {lgp.auc - ogm.auc:+.4f}   (target >= +0.03)",
        "",
        f"learning (kernel by marginal likelihood, alpha/beta by LOO): {r.learning_seconds:.3f} s",
        f"  l = {hp.length_scale:.3f}  sigma_f = {np.sqrt(hp.signal_variance):.3f}  "
        f"sigma_n = {np.sqrt(hp.noise_variance):.3f}  alpha = {hp.alpha:.3f}  beta = {hp.beta:.3f}",
        "  paper: l = 2.66  sigma_f = 2.81  sigma_n = 0.99  alpha = 7.94  beta = -1.42",
        "",
        f"Fig. 2 (1D) mean border jump: disjoint {r.fig2.jump_disjoint:.4f}, "
        f"overlapping {r.fig2.jump_overlap:.4f} "
        f"(ratio {r.fig2.jump_overlap / r.fig2.jump_disjoint:.3f}; target <= 0.5)",
    ]
    return "\n".join(lines)


def _plot(r: Paper2dResult, points: np.ndarray, labels: np.ndarray, out_dir: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    for key, m in r.methods.items():
        fpr, tpr, _ = roc_curve(labels, m.probabilities)
        ax.plot(fpr, tpr, label=f"{METHOD_NAMES[key]} (AUC {m.auc:.3f})")
    ax.plot([0, 1], [0, 1], color="0.7", ls=":")
    ax.set_xlabel("false positive rate")
    ax.set_ylabel("true positive rate")
    ax.set_title("ROC, paper 2D simulation (Fig. 4)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_dir / "fig4_roc.png", dpi=120)
    plt.close(fig)

    xs, ys = np.unique(points[:, 0]), np.unique(points[:, 1])
    fig, axes = plt.subplots(1, 5, figsize=(18, 3.6))
    grids = [("ground truth", labels.astype(float))] + [
        (METHOD_NAMES[k], m.probabilities) for k, m in r.methods.items()
    ]
    for ax, (title, values) in zip(axes, grids, strict=True):
        img = np.full((ys.size, xs.size), np.nan)
        img[np.searchsorted(ys, points[:, 1]), np.searchsorted(xs, points[:, 0])] = values
        ax.imshow(
            img,
            origin="lower",
            cmap="gray_r",
            vmin=0,
            vmax=1,
            extent=(xs[0], xs[-1], ys[0], ys[-1]),
        )
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out_dir / "fig3_maps.png", dpi=120)
    plt.close(fig)
