"""Launch the octolgp mapper with ``config/params.yaml``.

Arguments (``ros2 launch octolgp_ros octolgp.launch.py name:=value``):

- ``params`` (the package's ``config/params.yaml``): the parameter file.
- ``scan`` (``scan``) / ``points`` (``points``): the topics to remap the inputs from.
- ``map_file`` (empty: the parameter file's): the map file to write or resume.
- ``use_sim_time`` (``false``): ``true`` when playing a bag with ``--clock``.
"""

from pathlib import Path
from typing import Any

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def _mapper(context: LaunchContext, *args: Any, **kwargs: Any) -> list[Node]:
    """The node, with ``map_file`` overriding the parameter file only when it is given."""
    overrides: dict[str, Any] = {
        "use_sim_time": LaunchConfiguration("use_sim_time").perform(context) == "true",
    }
    map_file = LaunchConfiguration("map_file").perform(context)
    if map_file:
        overrides["map_file"] = map_file
    return [
        Node(
            package="octolgp_ros",
            executable="octolgp_mapper",
            name="octolgp_mapper",
            output="screen",
            parameters=[LaunchConfiguration("params"), overrides],
            remappings=[
                ("scan", LaunchConfiguration("scan")),
                ("points", LaunchConfiguration("points")),
            ],
        )
    ]


def generate_launch_description() -> LaunchDescription:
    """The launch arguments and the mapper node."""
    share = Path(get_package_share_directory("octolgp_ros"))
    return LaunchDescription(
        [
            DeclareLaunchArgument("params", default_value=str(share / "config" / "params.yaml")),
            DeclareLaunchArgument("scan", default_value="scan"),
            DeclareLaunchArgument("points", default_value="points"),
            DeclareLaunchArgument("map_file", default_value=""),
            DeclareLaunchArgument("use_sim_time", default_value="false"),
            OpaqueFunction(function=_mapper),
        ]
    )
