"""
The perception node's parameters, ROS-free: one per `PerceptionConfig` field (the model's
defaults, validated by the config's own check) and the node's own. The node declares them,
bringup checks them before any node starts, and the benchmarks read them.
"""
import dataclasses

from activeloc_ros.checks import file_or_empty, in_range, one_of, Param, positive
from activeloc_ros.perception.config import PerceptionConfig

RELIABILITIES = ('auto', 'best_effort', 'reliable')     # image_reliability

# Parameters without read_only take effect at the next frame.
NODE_PARAMS = [
    Param('publish_overlay', True, 'publish surprise_map/overlay (costs a few ms per frame)'),
    Param('overlay_alpha', 0.45, 'weight of the heat map in the overlay', in_range(0.0, 1.0)),
    Param('max_image_pixels', 3840 * 2160, 'frames of more pixels (width x height) are '
          'skipped with a warning (default: 3840x2160, 4K UHD)', positive),
    Param('image_transport', 'raw', 'raw: sensor_msgs/Image on camera/image_raw; compressed: '
          'sensor_msgs/CompressedImage (jpeg, png) on camera/image_raw/compressed',
          one_of('raw', 'compressed'), read_only=True),
    Param('image_reliability', 'auto', 'QoS reliability of the image subscription: auto '
          'follows the publishers (best effort if one offers only that, else reliable); '
          'best_effort hears every camera but loses large frames over DDS; reliable hears '
          'reliable cameras only', one_of(*RELIABILITIES), read_only=True),
    Param('diagnostics_period', 1.0, 'seconds between two /diagnostics messages', positive,
          read_only=True),
    Param('checkpoint', '', 'model checkpoint to start from (empty: fresh model)',
          file_or_empty, read_only=True),
    Param('pipeline', False, 'encode the next frame while learning from this one '
          '(perception.pipeline: the same maps; torch and the encoder get half the cores each '
          'unless num_threads is set). More maps/s from a camera faster than the model, '
          'but later ones (docs/performance.md). Not used when the encoder learns '
          '(update_encoder)',
          read_only=True),
]


def model_params() -> list[Param]:
    """One ROS parameter per PerceptionConfig field, validated by the config's own check."""
    params = []
    for field in dataclasses.fields(PerceptionConfig):
        def check(value, name=field.name):
            return PerceptionConfig.check(name, value)

        params.append(Param(field.name, field.default, field.metadata.get('help', field.name),
                            check, read_only=True))
    return params


MODEL_PARAMS = model_params()
PARAMS = MODEL_PARAMS + NODE_PARAMS      # all the node declares
