"""What one step of the online map did: the record returned by every insert."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ScanUpdate:
    """What one :meth:`OnlineMap.insert_scan` did.

    Attributes
    ----------
    scan : int
        Number of the scan in the mission, from 1.
    touched_leaves : int
        Leaves whose box or halo the scan's evidence reached.
    refit_leaves : int
        Touched leaves whose GP inputs changed: refitted and re-predicted in the call,
        or, when the map defers fits (:attr:`OnlineMap.defers_fit`), at its next read.
    new_items : int
        Training items added over all leaves.
    pruned_leaves : int
        Refitted leaves that were pruned to one value.
    seconds : float
        Wall time of the call.
    stages : dict of str to float
        Seconds per stage: ``training``, ``assign``, ``fit`` (fit and predict),
        ``store``, and ``learning`` when hyperparameters were learnt in this call.
    buffered : bool
        True while scans are buffered to learn hyperparameters: the map holds no
        leaves until then, and queries answer provisionally
        (:attr:`OnlineMap.provisional`).
    n_leaves : int
        Leaves in the map after the call.
    memory_bytes : int
        Bytes held by the leaves after the call.
    repaired : int
        Kernel matrices that were not numerically positive definite (coincident
        items, tiny noise) and were repaired by jitter during this step
        (:func:`octolgp.gp.regression.cholesky`); counted per map, never shared.
    removed_leaves : int
        Leaves dropped because no evidence is left in them (a pose correction moved
        the scans that made them).
    """

    scan: int
    touched_leaves: int
    refit_leaves: int
    new_items: int
    pruned_leaves: int
    seconds: float
    stages: dict[str, float] = field(default_factory=dict)
    buffered: bool = False
    n_leaves: int = 0
    memory_bytes: int = 0
    repaired: int = 0
    removed_leaves: int = 0
