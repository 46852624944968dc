"""
Launch the stereo visual odometry node.

Usage: ``ros2 launch stereo_vo_ros stereo_vo.launch.py`` with the defaults, or with a
namespace, topic remappings, a parameter file and bag time::

    ros2 launch stereo_vo_ros stereo_vo.launch.py namespace:=front
        left_image:=/cam/left/image_rect right_image:=/cam/right/image_rect
        left_info:=/cam/left/camera_info right_info:=/cam/right/camera_info
        params_file:=/path/to/stereo_vo.yaml use_sim_time:=true

Arguments: ``namespace``, ``node_name``, ``params_file`` (default: the installed
``config/stereo_vo.yaml``), ``use_sim_time``, ``log_level``, ``dds_profile`` and the
remapping targets ``left_image``, ``right_image``, ``left_info``, ``right_info``, ``odom``,
``path``.

``dds_profile`` is the Fast DDS XML profile of the node's process. Empty (the default), the
node starts with its own receive profile (``config/fastdds_node.xml``: images over UDP with a
16 MB receive buffer, so that no publisher loses large images to it) when the kernel allows
such a buffer; a path starts it with that profile instead, e.g. the installed
``config/fastdds_large_images.xml`` (shared memory with a 16 MB segment), which is the one to
give the process that publishes the images.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    """
    Describe the launch: its arguments and the stereo_vo node.

    Returns
    -------
    launch.LaunchDescription
        The declared arguments followed by the node action.

    """
    default_params = os.path.join(get_package_share_directory('stereo_vo_ros'), 'config',
                                  'stereo_vo.yaml')
    remaps = (
        ('left_image', 'left/image_rect', 'Left rectified image topic.'),
        ('right_image', 'right/image_rect', 'Right rectified image topic.'),
        ('left_info', 'left/camera_info', 'Left camera_info topic.'),
        ('right_info', 'right/camera_info', 'Right camera_info topic.'),
        ('odom', 'odom', 'Odometry output topic.'),
        ('path', 'path', 'Path output topic.'),
    )
    arguments = [
        DeclareLaunchArgument('namespace', default_value='',
                              description='Namespace of the node and its relative topics.'),
        DeclareLaunchArgument('node_name', default_value='stereo_vo',
                              description='Name of the node (params files may address it).'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter file (/**: ros__parameters: ...).'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='Use /clock (bag replay).'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='Logger level: debug, info, warn, error.'),
        DeclareLaunchArgument('dds_profile', default_value='',
                              description='Fast DDS XML profile of the node process; empty: '
                              'the node chooses (config/fastdds_node.xml when possible).'),
    ]
    arguments += [DeclareLaunchArgument(name, default_value=default, description=doc)
                  for name, default, doc in remaps]
    node = Node(
        package='stereo_vo_ros',
        executable='stereo_vo_node',
        name=LaunchConfiguration('node_name'),
        namespace=LaunchConfiguration('namespace'),
        output='screen',
        emulate_tty=True,
        parameters=[
            LaunchConfiguration('params_file'),
            {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                            value_type=bool)},
        ],
        remappings=[(default, LaunchConfiguration(name)) for name, default, _ in remaps],
        arguments=['--ros-args', '--log-level', LaunchConfiguration('log_level')],
        additional_env={'FASTRTPS_DEFAULT_PROFILES_FILE': LaunchConfiguration('dds_profile')},
    )
    return LaunchDescription(arguments + [node])
