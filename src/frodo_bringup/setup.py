"""Package setup for frodo_bringup (ament_python; also installable with pip)."""
from setuptools import find_packages, setup

package_name = 'frodo_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', ['launch/frodo.launch.py']),
        ('share/' + package_name + '/config', ['config/frodo.yaml']),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='FroDO maintainers',
    maintainer_email='frodo@example.org',
    description='The frodo command line (launch, play, record, run, synth, eval, train, demo), launch file, parameters and Rerun viewer.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'frodo = frodo_bringup.cli:main',
            'viewer_node = frodo_bringup.viewer_node:main'
        ],
    },
)
