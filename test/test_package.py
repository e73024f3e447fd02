"""The package manifest: a native ROS 2 install (rosdep, colcon) gets what the code imports."""
import ast
from pathlib import Path
import xml.etree.ElementTree as ET

REPO = Path(__file__).resolve().parents[1]


def imported_top_level_modules() -> set[str]:
    names = set()
    for path in (REPO / 'activeloc_ros').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names.update(alias.name.split('.')[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split('.')[0])
    return names


def test_every_ros_package_the_code_imports_is_an_exec_depend():
    manifest = ET.parse(REPO / 'package.xml').getroot()
    depends = {e.text for e in manifest.iter() if e.tag in ('exec_depend', 'depend')}
    ros = {name for name in imported_top_level_modules()
           if name.endswith(('_msgs', '_interfaces')) or name in ('rclpy', 'ament_index_python')}
    assert ros >= {'rclpy', 'sensor_msgs'}, ros        # the scan itself works
    assert ros - depends == set(), 'imported but missing from package.xml'
