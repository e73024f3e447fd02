"""
Checkpoints of the surprise model: its config, weights, optimiser and running state, so
a loaded model continues learning where the saved one stopped.
"""
import torch

from activeloc_ros.errors import WeightsError
from activeloc_ros.perception.config import PerceptionConfig
from activeloc_ros.perception.encoder_weights import build_encoder
from activeloc_ros.perception.model import SurpriseModel


def save(model: SurpriseModel, path: str) -> None:
    """Config, weights, optimiser and the running state, so `load` resumes learning."""
    torch.save({
        'config': model.cfg.to_dict(),
        'encoder': model.encoder.state_dict(),
        'predictor': model.predictor.state_dict(),
        'optimizer': model.optimizer.state_dict(),
        'running': {
            'state': model.state, 'x_prev': model.x_prev, 'f_prev': model.f_prev,
            'map_prev': model.map_prev, 'map_prev2': model.map_prev2,
            'loss_window': list(model.loss_window), 'nan_events': model.nan_events,
            'frame_index': model.frame_index, 'updates': model.updates,
            'grey_prev': (None if model.grey_prev is None
                          else torch.from_numpy(model.grey_prev)),
            't_prev': model.t_prev,
        },
    }, path)


def load(path: str) -> SurpriseModel:
    """
    Rebuild a saved model. Raises WeightsError for a file that is missing or not such a
    checkpoint.
    """
    try:
        return _load(path)
    except Exception as exc:   # torch's unpickler meets a file of junk with any error
        raise WeightsError(f'cannot load the checkpoint {path}: '
                           f'{type(exc).__name__}: {exc}') from None


def _load(path: str) -> SurpriseModel:
    ckpt = torch.load(path, map_location='cpu', weights_only=True)
    # a checkpoint saved before encoder_pad (motion_period) existed was learned without
    # the border (with one motion scale at any frame rate)
    cfg = PerceptionConfig.from_dict({'encoder_pad': 0, 'motion_period': 0.0,
                                      **ckpt['config']})
    # the checkpoint holds the encoder weights: no weight cache needed
    encoder = build_encoder(cfg.encoder, pretrained=False, classifier=False)
    encoder.load_state_dict(ckpt['encoder'])
    model = SurpriseModel(cfg, encoder=encoder)
    model.predictor.load_state_dict(ckpt['predictor'])
    model.optimizer.load_state_dict(ckpt['optimizer'])
    run = ckpt['running']
    model.state = tuple(run['state']) if run['state'] is not None else None
    model.x_prev, model.f_prev = run['x_prev'], run['f_prev']
    if model.x_prev is not None and cfg.channels_last:
        model.x_prev = model.x_prev.contiguous(memory_format=torch.channels_last)
    model.map_prev, model.map_prev2 = run['map_prev'], run['map_prev2']
    model.loss_window.extend(run['loss_window'])
    model.nan_events, model.frame_index = run['nan_events'], run['frame_index']
    model.updates = run['updates']
    grey_prev = run.get('grey_prev')
    model.grey_prev = None if grey_prev is None else grey_prev.numpy()
    model.t_prev = run.get('t_prev')
    model._take_snapshot()
    return model
