"""Simulator -> fusion chain for a native ROS 2 install.

Run: ``ros2 launch bearing_loc_ros demo.launch.py``.

Arguments: ``scenario`` (a file in share/bearing_loc_ros/config/scenarios or a path; default
seed000.yaml), ``estimator`` (default mle), ``time_scale`` (default 1.0), ``stations`` (default the
three stations of Wang, Zhang & Wu (2006), as in seed000.yaml). The fusion node runs with
use_sim_time and the simulator publishes /clock. Without a native install (PyPI wheels only),
``make demo`` runs the same chain.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory('bearing_loc_ros')
    return LaunchDescription([
        DeclareLaunchArgument('scenario', default_value='seed000.yaml'),
        DeclareLaunchArgument('estimator', default_value='mle'),
        DeclareLaunchArgument('time_scale', default_value='1.0'),
        DeclareLaunchArgument('stations', default_value='[station_1, station_2, station_3]'),
        Node(package='bearing_loc_ros', executable='simulator_node', name='simulator',
             output='screen',
             parameters=[{'scenario': LaunchConfiguration('scenario'),
                          'time_scale': LaunchConfiguration('time_scale'),
                          'exit_when_done': False}]),
        Node(package='bearing_loc_ros', executable='fusion_node', name='fusion',
             output='screen',
             parameters=[os.path.join(share, 'config', 'fusion.yaml'),
                         {'use_sim_time': True,
                          'estimator': LaunchConfiguration('estimator'),
                          'stations': LaunchConfiguration('stations')}]),
    ])
