"""
The benchmarks' methods, and how each one's perception and controller are assembled.

A method is a name: ``ours`` (the defaults), a paper Table 3 row (``ours-no_attn``,
``ours-pd-low_p``...), a preset of a params file (``ours-paper``: params/paper.yaml, the
paper as written), a baseline (``centre``, ``random``, ``oracle``), an unsupervised motion
anchor (``framediff``, ``mog2``, ``flow``) or an OpenCV tracker. ``--params FILE`` gives any
model method a ROS 2 params file's perception and controller sections, as bringup does.
"""
import dataclasses
import functools
from pathlib import Path

from activeloc_ros.bench.pointers import (
    ABLATIONS, CentrePointer, FlowPointer, FrameDiffPointer, ModelPointer, Mog2Pointer,
    OraclePointer, RandomPointer, TrackerMethod)
from activeloc_ros.control import ControllerConfig, PD_VARIANTS, PDConfig
from activeloc_ros.control.params import pd_from, PD_PARAMS
from activeloc_ros.errors import ConfigError
from activeloc_ros.paths import share_path
from activeloc_ros.screen import VirtualScreen

# methods that are a params file of the package laid over the defaults
PRESETS = {'ours-paper': 'params/paper.yaml'}

TRACKER_METHODS = ('tld', 'mil', 'mosse', 'kcf', 'csrt')


def table3_methods(pd: PDConfig) -> tuple[str, ...]:
    """
    The model's rows of the paper's Table 3 for a controller whose own law is ``pd``: the
    perception's ablations, then the PD variants whose gains differ from its own.
    """
    return ('ours', *(f'ours-{a}' for a in ABLATIONS if a != 'full'),
            *(f'ours-pd-{v}' for v, gains in PD_VARIANTS.items() if gains != (pd.kp, pd.kd)))


TABLE3_METHODS = table3_methods(PDConfig())
MODEL_METHODS = (*TABLE3_METHODS, *PRESETS)
MOTION_METHODS = ('framediff', 'mog2', 'flow')   # unsupervised anchors on the picture's change
METHODS = (*MODEL_METHODS, 'random', 'centre', 'oracle', *MOTION_METHODS, *TRACKER_METHODS)


def method_parts(name: str) -> tuple[dict, str | None]:
    """
    (PerceptionConfig overrides, PD variant or None for the default gains) of a model
    method name.
    """
    if name == 'ours':
        return {}, None
    if name in PRESETS:
        return params_file(share_path(PRESETS[name]))[0], None
    if _pd_variant(name) in PD_VARIANTS:
        return {}, _pd_variant(name)
    if name.startswith('ours-') and name[5:] in ABLATIONS:
        return dict(ABLATIONS[name[5:]]), None
    raise ConfigError(f'unknown method {name!r}; known: {", ".join(METHODS)}')


def make_pointer(name: str, settings: dict, seed: int, *, tracker_start: str = 'proposal'):
    """
    The pointer of a method (model methods get `settings` + their ablation; trackers start
    on an EdgeBoxes proposal, or with ``tracker_start='truth'`` on the target's true box).
    """
    if name in TRACKER_METHODS:
        return TrackerMethod(name, start=tracker_start)
    if name == 'random':
        return RandomPointer(seed=seed)
    if name == 'centre':
        return CentrePointer()
    if name == 'oracle':
        return OraclePointer()
    if name == 'framediff':
        return FrameDiffPointer()
    if name == 'mog2':
        return Mog2Pointer()
    if name == 'flow':
        return FlowPointer()
    overrides, _ = method_parts(name)
    if name in PRESETS:      # a preset is a starting point: the --set settings win over it
        return ModelPointer(name, {'seed': seed, **overrides, **settings})
    return ModelPointer(name, {'seed': seed, **settings, **overrides})


CONTROL_OPTIONS = ('settle_time', 'watchdog_timeout', 'step_delay_ms', 'min_peak',
                   'pan_limit_deg', 'tilt_limit_deg', 'confirm_deg')


def method_pd(name: str, control: dict) -> PDConfig:
    """
    The PD law of a method: its Table 3 variant's gains (whatever --control says of kp and
    kd), else the default's, with the `PD_PARAMS` among the --control settings: the
    controller node's names and units (``dead_band_deg`` in degrees).
    """
    return pd_from(control, _pd_variant(name))


def _pd_variant(name: str) -> str:
    """The PD variant an ``ours-pd-VARIANT`` method names ('' for any other)."""
    return name[len('ours-pd-'):] if name.startswith('ours-pd-') else ''


def controller_for(name: str, control: dict, screen: VirtualScreen | None = None
                   ) -> ControllerConfig:
    """
    The controller of a method: its PD variant plus the --control settings; with a
    `screen`, aimed no farther than its view stays on the screen (unless set; the
    `--aim-limits screen` rig).
    """
    unknown = sorted(set(control) - set(PD_PARAMS) - set(CONTROL_OPTIONS))
    if unknown:
        raise ConfigError(f'unknown --control settings {unknown}; known: '
                          f'{", ".join(PD_PARAMS + CONTROL_OPTIONS)}')
    if name in PRESETS:
        control = {**params_file(share_path(PRESETS[name]))[1], **control}
    pd = method_pd(name, control)
    options = {k: v for k, v in control.items() if k in CONTROL_OPTIONS}
    if screen is not None:
        pan, tilt = screen.aim_limits_deg()
        options.setdefault('pan_limit_deg', pan)
        options.setdefault('tilt_limit_deg', tilt)
    if name not in MODEL_METHODS:
        # the settle gate makes up for the surprise map's blindness to the camera's own
        # motion; the baselines see no such thing and mostly do better without it (mean
        # AAE over the dev set, 10 Hz camera, kd 0.1, no aim limits: oracle 6.0 vs 13.2
        # deg, random 22.5 vs 25.4, kcf 24.4 vs 25.2; mosse is the exception, 26.4 vs 24.7)
        options.setdefault('settle_time', 0.0)
    return ControllerConfig(pd=pd, **options)


def control_from_node(values: dict) -> dict:
    """
    The controller node's parameter values as the benchmarks' --control settings: the
    PD law's and the arm's, under the same names; the base's and the node's own parameters
    have no place on the screen.
    """
    return {k: v for k, v in values.items() if k in PD_PARAMS + CONTROL_OPTIONS}


def params_file(path: str | Path) -> tuple[dict, dict]:
    """
    (PerceptionConfig settings, --control settings) that a ROS 2 params file gives the
    perception and controller nodes, checked as the nodes check it.

    :raises ConfigError: no such file, or a key or value the nodes would refuse.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f'params file not found: {path}')
    perception, control = _params_file(str(path.resolve()), path.stat().st_mtime_ns)
    return dict(perception), dict(control)


@functools.lru_cache(maxsize=16)     # each run of a preset asks again
def _params_file(path: str, mtime_ns: int) -> tuple[dict, dict]:
    from activeloc_ros.checks import validate
    from activeloc_ros.control import params as controller_params
    from activeloc_ros.nodes.params_files import file_values, files_problems
    from activeloc_ros.perception import params as perception_params
    from activeloc_ros.perception.config import PerceptionConfig
    values, problems = {}, []
    for node, module in (('perception', perception_params),
                         ('controller', controller_params)):
        problems += files_problems(node, module.PARAMS, [path])
        values[node] = file_values(node, [path])
        problems += [f'{path}: {p}' for p in validate(module.PARAMS, values[node])]
    if problems:
        raise ConfigError('; '.join(problems))
    fields = {f.name for f in dataclasses.fields(PerceptionConfig)}
    perception = {k: v for k, v in values['perception'].items() if k in fields}
    return perception, control_from_node(values['controller'])
