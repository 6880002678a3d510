"""octolgp: continuous occupancy maps with overlapping local Gaussian processes.

Kim & Kim, "Continuous Occupancy Maps using Overlapping Local Gaussian Processes",
IROS 2013, made online and OctoMap-style.

The package logs to ``logging.getLogger("octolgp")`` (learnt hyperparameters, jitter
repairs, skipped input, truncated recordings); it has a ``NullHandler``, so nothing
is printed unless the application configures logging.
"""

import logging

from octolgp.batch.build import build_map
from octolgp.config import (
    ExactConfig,
    Hyperparameters,
    LatticeConfig,
    LearningConfig,
    MapConfig,
    OgmConfig,
    OnlineConfig,
    PartitionConfig,
    TrainingConfig,
)
from octolgp.errors import OctolgpError
from octolgp.gp.learning import learn_hyperparameters
from octolgp.io import load_scans
from octolgp.mapping.online import OnlineMap, ScanUpdate
from octolgp.scan import Scan

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "ExactConfig",
    "Hyperparameters",
    "LatticeConfig",
    "LearningConfig",
    "MapConfig",
    "OctolgpError",
    "OgmConfig",
    "OnlineConfig",
    "OnlineMap",
    "PartitionConfig",
    "Scan",
    "ScanUpdate",
    "TrainingConfig",
    "__version__",
    "build_map",
    "learn_hyperparameters",
    "load_scans",
]
