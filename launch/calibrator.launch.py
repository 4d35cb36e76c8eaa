"""Start one calibrator node: `ros2 launch radar_calib_ros calibrator.launch.py`.

Arguments
---------
params_file
    ROS 2 parameters file (default: the package's config/calibrator.yaml).
namespace
    Namespace of the node, its topics and services; one node per radar, each in its own
    namespace (``namespace:=radar_north``): relative topic names such as ``radar/points``
    then resolve to ``/radar_north/radar/points``. Give each radar its own ``output.path``
    and ``radar.frame_id`` in its params file.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    default_params = PathJoinSubstitution(
        [FindPackageShare('radar_calib_ros'), 'config', 'calibrator.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameters file of the calibrator'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node (one per radar)'),
        Node(package='radar_calib_ros', executable='calibrator', name='calibrator',
             namespace=LaunchConfiguration('namespace'),
             parameters=[LaunchConfiguration('params_file')],
             output='screen', emulate_tty=True),
    ])
