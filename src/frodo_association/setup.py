"""Package setup for frodo_association (ament_python; also installable with pip)."""
from setuptools import find_packages, setup

package_name = 'frodo_association'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    include_package_data=True,
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='FroDO maintainers',
    maintainer_email='frodo@example.org',
    description='Association node: ray-segment DP-means clustering of detections into objects, 3D boxes and detection pruning (paper Sec. 5.1, supplement).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'association_node = frodo_association.association_node:main'
        ],
    },
)
