"""Package setup for frodo_detection (ament_python; also installable with pip)."""
from setuptools import find_packages, setup

package_name = 'frodo_detection'

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
    description='Detection node: per-frame instance masks from /camera/instances or torchvision Mask R-CNN (paper Sec. 5.1).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'detection_node = frodo_detection.detection_node:main'
        ],
    },
)
