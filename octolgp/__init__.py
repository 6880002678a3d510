"""octolgp: continuous occupancy maps with overlapping local Gaussian processes.

Kim & Kim, "Continuous Occupancy Maps using Overlapping Local Gaussian Processes",
IROS 2013, made online and OctoMap-style.
"""

from octolgp.config import (
    Hyperparameters,
    LearningConfig,
    MapConfig,
    OgmConfig,
    PartitionConfig,
    TrainingConfig,
)
from octolgp.errors import OctolgpError
from octolgp.scan import Scan

__version__ = "0.1.0"

__all__ = [
    "Hyperparameters",
    "LearningConfig",
    "MapConfig",
    "OctolgpError",
    "OgmConfig",
    "PartitionConfig",
    "Scan",
    "TrainingConfig",
    "__version__",
]
