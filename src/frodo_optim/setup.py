"""Package setup for frodo_optim (ament_python; also installable with pip)."""
from setuptools import find_packages, setup

package_name = 'frodo_optim'

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
    description='Optimiser node: per-object pose and shape refinement (paper Sec. 5.3) and mesh publication.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'optim_node = frodo_optim.optim_node:main'
        ],
    },
)
