"""Build script for the stereo_vo_ros ament_python package (works with colcon and with pip)."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'stereo_vo_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    include_package_data=True,
    python_requires='>=3.10',
    # ROS 2 Python packages (rclpy, messages) come from the ROS install or from the
    # ros-jazzy-* wheels (extra "ros"); they are deliberately not hard requirements.
    install_requires=[
        'numpy>=1.24',
        'scipy>=1.10',
        'numba>=0.58',
        'opencv-python-headless>=4.6',
        'PyYAML>=6.0',
        'rosbags>=0.10',
        'matplotlib>=3.6',
        'tqdm>=4.60',
    ],
    extras_require={
        'ros': [
            'ros-jazzy-rclpy[fastrtps]',
            'ros-jazzy-sensor-msgs',
            'ros-jazzy-nav-msgs',
            'ros-jazzy-geometry-msgs',
            'ros-jazzy-std-msgs',
            'ros-jazzy-std-srvs',
            'ros-jazzy-diagnostic-msgs',
        ],
        'test': ['pytest', 'pytest-xdist', 'hypothesis', 'flake8', 'pydocstyle', 'evo'],
    },
    zip_safe=True,
    maintainer='stereo_vo_ros maintainers',
    maintainer_email='maintainers@stereo-vo-ros.invalid',
    description='Stereo visual odometry (trifocal ISPKF + light adaptive KLT) for ROS 2 Jazzy.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'stereo_vo = stereo_vo_ros.cli:main',
            'stereo_vo_node = stereo_vo_ros.ros:node_main',
        ],
    },
)
