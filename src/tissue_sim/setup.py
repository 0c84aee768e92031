"""ament_python package of tissue_sim: the ROS-free core (tissue_sim.core), the nodes and the CLI."""
from pathlib import Path

from setuptools import find_packages, setup

package_name = 'tissue_sim'
here = Path(__file__).resolve().parent


def data_tree(sub):
    """(install dir, [files]) pairs for everything under tissue_sim/<sub>, kept as package data."""
    return [str(p.relative_to(here / package_name)) for p in (here / package_name / sub).rglob('*') if p.is_file()]


setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: data_tree('data') + data_tree('config')},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', [str(p.relative_to(here)) for p in sorted((here / 'launch').glob('*.launch.py'))]),
        ('share/' + package_name + '/urdf', [str(p.relative_to(here)) for p in sorted((here / 'description').glob('*.urdf'))]),
        ('share/' + package_name + '/meshes', [str(p.relative_to(here)) for p in sorted((here / 'description' / 'meshes').glob('*.stl'))]),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='tissue_sim team',
    maintainer_email='tissue-sim@example.org',
    description='Elastic skeletal-muscle model of a lower limb driven by muscle contraction, as a ROS 2 service.',
    license='BSD-3-Clause',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'simulator = tissue_sim.nodes.simulator:main',
            'activation = tissue_sim.nodes.activation:main',
            'recorder = tissue_sim.nodes.recorder:main',
            'replay = tissue_sim.nodes.replay:main',
            'tissue-sim = tissue_sim.cli:main',
        ],
    },
)
