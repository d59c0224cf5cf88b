"""Install the zeus_ros ament_python package (learning core, nodes, sim)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'zeus_ros'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(include=['zeus_ros', 'zeus_ros.*', 'sim_node', 'sim_node.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.json')
                                        + glob('config/*.xml')),
        ('share/' + PACKAGE + '/config/sweeps', glob('config/sweeps/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='zeus_ros developers',
    maintainer_email='zeus-ros@example.com',
    description='ZeUS zero-shot adaptation on ROS 2 with a live-swappable MuJoCo simulation.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'sim_node = zeus_ros.nodes.sim_node:main',
            'context_node = zeus_ros.nodes.context_node:main',
            'policy_node = zeus_ros.nodes.policy_node:main',
            'bringup = zeus_ros.ros_tools.bringup:main',
            'composed = zeus_ros.ros_tools.composed:main',
            'demo = zeus_ros.ros_tools.demo:main',
            'train = zeus_ros.learning_tools.train:main',
            'eval = zeus_ros.learning_tools.evaluate:main',
            'check_parity = zeus_ros.ros_tools.check_parity:main',
            'adaptation_report = zeus_ros.learning_tools.adaptation:main',
            'sweep = zeus_ros.learning_tools.sweep:main',
            'foxglove_view = zeus_ros.ros_tools.foxglove_view:main',
            'export_onnx = zeus_ros.learning_tools.export_onnx:main',
            'set_param = zeus_ros.ros_tools.set_param:main',
            'family_check = zeus_ros.learning_tools.family_check:main',
        ],
    },
)
