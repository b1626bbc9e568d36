from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'rkgnn_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench', 'tools']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (os.path.join('share', package_name, 'config'),
         glob('config/*.yaml') + glob('config/*.xml')),
        (os.path.join('share', package_name, 'launch'), glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='rkgnn_ros maintainers',
    maintainer_email='maintainers@rkgnn-ros.dev',
    description='Online RKGNN identification of robot arm dynamics for ROS 2',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'sim_arm = rkgnn_ros.sim_arm:main',
            'identifier = rkgnn_ros.identifier:main',
            'identify_bag = rkgnn_ros.identify_bag:main',
        ],
    },
)
