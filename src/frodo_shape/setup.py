"""Package setup for frodo_shape (ament_python; also installable with pip)."""
from setuptools import find_packages, setup

package_name = 'frodo_shape'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    include_package_data=True,
    # Shipped priors (weights, config, training codes, model card, plots) and training configs.
    package_data={package_name: ['configs/*.yaml', 'priors/*/*.pt', 'priors/*/*.yaml', 'priors/*/*.md',
                                 'priors/*/*.png', 'priors/*/*.json']},
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='FroDO maintainers',
    maintainer_email='frodo@example.org',
    description='Joint point/SDF shape embedding, image encoder, code fusion, training pipeline and shipped priors (paper Sec. 4, 4.2).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'shape_node = frodo_shape.shape_node:main'
        ],
    },
)
