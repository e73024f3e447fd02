from glob import glob

from setuptools import find_packages, setup

package_name = 'activeloc_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/params', glob('params/*.yaml')),
        ('share/' + package_name + '/bags/vtest', glob('bags/vtest/*')),
        ('share/' + package_name + '/arduino/braccio_serial',
         glob('activeloc_ros/arduino/braccio_serial/*.ino')),
        ('share/' + package_name + '/arduino', ['activeloc_ros/arduino/README.md']),
    ],
    package_data={package_name: ['arduino/braccio_serial/*.ino']},
    python_requires='>=3.10',
    # rclpy and the message packages come from a sourced ROS 2 Jazzy or, where there is
    # none, from the PyPI wheels in the 'ros' extra (the Makefile decides which).
    install_requires=[
        'numpy>=1.24',
        'torch==2.13.0',
        'opencv-contrib-python-headless>=4.11,<5.1',   # exact pins: numpy1 / numpy2 below
        'mcap==1.6.0',
        'rosbags==0.11.9',
        'PyYAML>=6.0',
        'matplotlib>=3.7',
        'pyserial==3.5',
        'av==17.1.0',      # H.264 videos (its wheels bundle FFmpeg with libx264)
        # the tracking world: a 3D engine that renders on the CPU; its wheel ships the
        # humanoid and the motion-capture clips (pybullet_data)
        'pybullet==3.2.7',
        # the int8 encoder (encoder_precision: int8): OpenVINO runs it, NNCF quantises it once
        'openvino==2026.4.1',
        'nncf==3.4.0',
    ],
    extras_require={
        'ros': [
            'ros-jazzy-rclpy[fastrtps]==7.1.6',
            'ros-jazzy-common-interfaces==5.3.6',
        ],
        # One of these pins OpenCV. A sourced ROS 2 Jazzy brings numpy 1.26, which OpenCV 5
        # wheels refuse: in a --system-site-packages venv they would pull numpy 2 and shadow
        # it (ros-perception/vision_opencv#535). The 4.11 wheel works with both.
        'numpy1': ['numpy>=1.24,<2', 'opencv-contrib-python-headless==4.11.0.86'],
        'numpy2': ['numpy>=2', 'opencv-contrib-python-headless==5.0.0.93'],
        'realsense': ['pyrealsense2'],
        'test': ['pytest==9.2.0', 'hypothesis==6.170.15',
                 # ament_flake8's checks (test_flake8.py)
                 'flake8==7.5.0', 'flake8-blind-except==0.2.1', 'flake8-builtins==3.1.0',
                 'flake8-class-newline==1.6.0', 'flake8-comprehensions==3.17.0',
                 'flake8-deprecated==2.4.0', 'flake8-import-order==0.19.2',
                 'flake8-quotes==3.4.0',
                 # ament_pep257's (test_pep257.py)
                 'pydocstyle==6.3.0'],
    },
    zip_safe=True,
    maintainer='activeloc_ros developers',
    maintainer_email='activeloc-ros@users.noreply.github.com',
    description='Active action localization with predictive learning and reactive control.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'camera_node = activeloc_ros.nodes.camera_node:main',
            'sim_node = activeloc_ros.nodes.sim_node:main',
            'tracking_node = activeloc_ros.nodes.tracking_node:main',
            'perception_node = activeloc_ros.nodes.perception_node:main',
            'controller_node = activeloc_ros.nodes.controller_node:main',
            'arm_node = activeloc_ros.nodes.arm_node:main',
            'bringup = activeloc_ros.bringup:main',
        ],
    },
)
