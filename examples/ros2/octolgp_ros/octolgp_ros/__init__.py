"""ROS 2 node for octolgp: see :mod:`octolgp_ros.mapper`."""
