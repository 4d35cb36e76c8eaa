"""ament_python / pip package definition of radar_calib_ros."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'radar_calib_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={package_name: ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/msg_schemas', glob('msg_schemas/*')),
    ],
    python_requires='>=3.10',
    install_requires=[
        'setuptools',
        'numpy>=1.24',
        'scipy>=1.10',
        'filterpy==2.0.0',
        'rosbags>=0.11',
        'pyproj>=3.4',
        'PyYAML>=6.0',
        'scikit-learn>=1.2',
        'threadpoolctl>=3.1',
        'tqdm>=4.60',
        'matplotlib>=3.6',
    ],
    extras_require={
        'test': ['pytest>=7', 'hypothesis>=6', 'catkin_pkg>=0.5'],
    },
    zip_safe=True,
    maintainer='radar_calib_ros maintainers',
    maintainer_email='radar-calib@example.com',
    description='Target-less geo-referenced extrinsic calibration of roadside radars.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'calibrator = radar_calib_ros.node:main',
            'radar-calib = radar_calib_ros.cli:main',
        ],
    },
)
