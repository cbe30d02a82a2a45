"""Install bearing_loc_ros the ament_python way (colcon) or with pip."""
from glob import glob
import os
import re

from setuptools import find_packages, setup

PACKAGE = 'bearing_loc_ros'
HERE = os.path.dirname(os.path.abspath(__file__))


def _version():
    """Read the version from package.xml so the two can never disagree."""
    with open(os.path.join(HERE, 'package.xml'), encoding='utf-8') as f:
        return re.search(r'<version>([^<]+)</version>', f.read()).group(1).strip()


setup(
    name=PACKAGE,
    version=_version(),
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.json')),
        ('share/' + PACKAGE + '/config/scenarios', glob('config/scenarios/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.py')),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'numba', 'pyyaml'],
    zip_safe=True,
    maintainer='bearing_loc_ros maintainers',
    maintainer_email='maintainers@bearing-loc.invalid',
    description='Networked multi-station direction finding for ROS 2.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'station_node = bearing_loc_ros.station_node:main',
            'simulator_node = bearing_loc_ros.simulator_node:main',
            'fusion_node = bearing_loc_ros.fusion_node:main',
            'view_node = bearing_loc_ros.view_node:main',
            'bearing_loc = bearing_loc_ros.cli:main',
        ],
    },
)
