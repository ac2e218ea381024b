"""ament_python package: ``colcon build`` installs the executables to lib/brace_control."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'brace_control'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=[package_name, f'{package_name}.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{package_name}']),
        (f'share/{package_name}', ['package.xml']),
        (f'share/{package_name}/config', glob('config/*.yaml') + glob('config/*.eds') + glob('config/*.xml')),
        (f'share/{package_name}/launch', glob('launch/*.launch.py')),
    ],
    package_data={package_name: ['py.typed']},
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='brace_control developers',
    maintainer_email='brace_control@example.org',
    description='ROS 2 control stack for rehabilitation braces on parallel mechanisms',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'ik_node = brace_control.nodes.ik_node:main',
            'trajectory_node = brace_control.nodes.trajectory_node:main',
            'can_driver_node = brace_control.nodes.can_driver_node:main',
            'kinetics_node = brace_control.nodes.kinetics_node:main',
            'interaction_node = brace_control.nodes.interaction_node:main',
            'bringup = brace_control.bringup:main',
            'brace-bringup = brace_control.bringup:main',
            'brace-bag = brace_control.bag:main',
            'brace-workspace = brace_control.tools.workspace:main',
            'brace-kinematics = brace_control.tools.kinematics:main',
            'brace-fourbar-report = brace_control.tools.fourbar_report:main',
            'brace-spm-study = brace_control.tools.spm_study:main',
            'brace-continuum-plot = brace_control.tools.continuum_plot:main',
            'brace-design = brace_control.tools.design:main',
            'brace-commission = brace_control.commission:main',
            'brace_commission = brace_control.commission:main',
        ],
    },
)
