r"""Run the octolgp ROS 2 node from a source checkout, without building its package.

The node is the ament_python package ``examples/ros2/octolgp_ros`` (build it with colcon for
``ros2 run`` / ``ros2 launch``; its README says how). This script runs the same node with ROS 2
sourced, parameters as ``--ros-args``::

    python examples/ros2_node.py --ros-args -p input:=scan -p map_file:=lab.octolgp
    python examples/ros2_node.py --ros-args -p input:=points -p downsample:=0.2 \\
        -r points:=/velodyne_points
"""

from __future__ import annotations

import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent / "ros2" / "octolgp_ros"

if __name__ == "__main__":
    sys.path.insert(0, str(PACKAGE))
    from octolgp_ros.mapper import main

    main()
