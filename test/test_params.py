"""Every key of params/<node>.yaml is a declared parameter of that node, with a description."""
import pytest
import yaml

from conftest import PARAMS, params_args


def node_class(name):
    from activeloc_ros.arm_node import ArmNode
    from activeloc_ros.camera_node import CameraNode
    from activeloc_ros.controller_node import ControllerNode
    from activeloc_ros.perception_node import PerceptionNode
    return {'camera': CameraNode, 'perception': PerceptionNode,
            'controller': ControllerNode, 'arm': ArmNode}[name]


@pytest.mark.parametrize('name', ['camera', 'perception', 'controller', 'arm'])
def test_params_file_matches_declared_parameters(context, name):
    content = yaml.safe_load((PARAMS / f'{name}.yaml').read_text())
    keys = set(content['/**']['ros__parameters'])
    node = node_class(name)(context=context, cli_args=params_args(name))
    try:
        undeclared = {k for k in keys if not node.has_parameter(k)}
        assert not undeclared, f'{name}.yaml sets parameters the node does not declare'
        for key in keys:
            assert node.describe_parameter(key).description, f'{key} has no description'
            assert node.get_parameter(key).value == content['/**']['ros__parameters'][key]
    finally:
        node.destroy_node()


def test_perception_yaml_repeats_the_model_defaults():
    """The YAML overrides the dataclass, so a stale value would silently change the model."""
    import dataclasses
    from activeloc_ros.perception.model import PerceptionConfig
    values = yaml.safe_load((PARAMS / 'perception.yaml').read_text())['/**']['ros__parameters']
    for field in dataclasses.fields(PerceptionConfig):
        assert field.name in values, f'perception.yaml lacks {field.name}'
        assert values[field.name] == field.default, f'perception.yaml: stale {field.name}'
