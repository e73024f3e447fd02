"""
The predictor and its losses: what the paper's Sec. 3.2 defines, with no state of its own.

`Predictor` maps each cell's features to its predicted next features (attention and stacked
LSTMs, all cells one batch); the functions below weigh its error by the motion, score it
(L_global, L_attn), turn the per-cell error into the surprise map and read the action's
location off the map. `perception.model.SurpriseModel` runs them online, one frame a step.
"""
import math

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from activeloc_ros import metrics
from activeloc_ros.errors import ConfigError
from activeloc_ros.perception.config import PerceptionConfig


class Predictor(nn.Module):
    """Per-cell Bahdanau attention and stacked LSTMs; all cells share the weights."""

    def __init__(self, cfg: PerceptionConfig, channels: int):
        super().__init__()
        if cfg.head == 'none' and cfg.hidden != channels:
            raise ConfigError(f"perception parameter 'head' none needs hidden == encoder "
                              f'channels ({channels}), got hidden={cfg.hidden}')
        self.hidden = cfg.hidden
        self.layers = cfg.layers
        self.rescale = cfg.attn_rescale
        self.w1 = nn.Linear(channels, cfg.attn_units)
        self.w2 = nn.Linear(cfg.hidden, cfg.attn_units, bias=False)
        self.v = nn.Linear(cfg.attn_units, 1, bias=False)
        # one matmul per LSTM: gates (i, f, g, o) of [input, h_prev], as torch.nn.LSTM
        sizes = [channels] + [cfg.hidden] * (cfg.layers - 1)
        self.cells = nn.ModuleList(nn.Linear(n + cfg.hidden, 4 * cfg.hidden) for n in sizes)
        self.head = nn.Linear(cfg.hidden, channels) if cfg.head == 'linear' else nn.Identity()
        self.residual = cfg.residual
        if cfg.residual and cfg.head == 'linear':
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def initial_state(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        zeros = torch.zeros(self.layers, n, self.hidden)
        return zeros, zeros.clone()                             # (L, N, H) each

    def forward(self, f: torch.Tensor, state: tuple[torch.Tensor, torch.Tensor]
                ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """
        Predict each cell's next feature from its current one.

        :param f: (N, C) features of the N cells.
        :param state: (h, c), each (L, N, H), after the previous frame.
        :return: fhat (N, C), attention (N,) summing to 1, the new (h, c).
        """
        h_prev, c_prev = state
        score = torch.tanh(self.w1(f) + self.w2(h_prev[-1]))   # (N, A)
        alpha = torch.softmax(self.v(score).squeeze(1), dim=0)  # (N,) over the cells
        x = alpha[:, None] * f                                  # (N, C)
        if self.rescale:
            x = x * f.shape[0]
        hs, cs = [], []
        for i, cell in enumerate(self.cells):
            gates = GateProduct.apply(x, h_prev[i], cell.weight, cell.bias)  # (N, 4H)
            ig, fg, gg, og = gates.chunk(4, dim=1)
            c = torch.sigmoid(fg) * c_prev[i] + torch.sigmoid(ig) * torch.tanh(gg)
            x = torch.sigmoid(og) * torch.tanh(c)               # (N, H)
            hs.append(x)
            cs.append(c)
        fhat = self.head(x)                                     # (N, C)
        if self.residual:
            fhat = fhat + f
        return fhat, alpha, (torch.stack(hs), torch.stack(cs))


class GateProduct(torch.autograd.Function):
    """
    An LSTM's gates, [x, h] W^T + b, as `nn.Linear` on the concatenation computes them
    (under autocast too), but whose backward skips the product that only the input's part
    of the concatenation needs when that part asks for no gradient: the state h never does
    (it is detached between frames), which saves 23% of the update's arithmetic.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor, h: torch.Tensor, weight: torch.Tensor,
                bias: torch.Tensor) -> torch.Tensor:
        dtype = (torch.get_autocast_dtype('cpu') if torch.is_autocast_enabled('cpu')
                 else x.dtype)
        xh = torch.cat([x, h], dim=1).to(dtype)                 # (N, C + H)
        w = weight.to(dtype)                                    # (4H, C + H)
        ctx.save_for_backward(xh, w)
        ctx.split = x.shape[1]
        with torch.autocast('cpu', enabled=False):
            return torch.addmm(bias.to(dtype), xh, w.t())       # (N, 4H)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        xh, w = ctx.saved_tensors
        n = ctx.split
        need_x, need_h, need_w, need_b = ctx.needs_input_grad
        grad_x = grad_h = None
        if need_x and need_h:
            grad_x, grad_h = (grad @ w).split([n, w.shape[1] - n], dim=1)
        elif need_x:
            grad_x = grad @ w[:, :n]
        elif need_h:
            grad_h = grad @ w[:, n:]
        return (grad_x, grad_h, grad.t() @ xh if need_w else None,
                grad.sum(0) if need_b else None)


def motion_weight(diff: torch.Tensor, kind: str, scale: float) -> torch.Tensor:
    """Weight of each feature's prediction error by its motion `diff` = f_t - f_{t-1}."""
    if kind == 'abs_sigmoid':
        return 2.0 * torch.sigmoid(diff.abs() / scale) - 1.0
    if kind == 'sigmoid':
        return torch.sigmoid(diff / scale)
    if kind == 'raw':
        return diff.square()
    return torch.ones_like(diff)


GAP_FACTORS = (0.25, 4.0)   # a burst of frames or a pause does not make the weights extreme


def gap_factor(gap: float | None, period: float, power: float) -> float:
    """
    How much the motion scale grows for frames ``gap`` seconds apart (rounded to the
    millisecond, against stamp jitter) when it was set for frames ``period`` apart:
    (gap / period) ** power, within `GAP_FACTORS`. 1 without a period (0) or a usable gap.
    """
    gap = round(gap, 3) if gap is not None and math.isfinite(gap) else 0.0
    if not period or gap <= 0:
        return 1.0
    low, high = GAP_FACTORS
    return min(max((gap / period) ** power, low), high)


def global_error(f_next: torch.Tensor, fhat: torch.Tensor, weight: torch.Tensor, *,
                 reduction: str) -> tuple[torch.Tensor, torch.Tensor]:
    """L_global and the per-cell error e (channel mean), from (N, C) tensors."""
    err = weight * (f_next - fhat).square()                     # (N, C)
    loss = err.mean() if reduction == 'mean' else err.sum()
    return loss, err.mean(dim=1)                                # (), (N,)


def attention_loss(alpha: torch.Tensor, target: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Paper Eq. 3: attention (N,) against the previous surprise map (N,), on features (N, C)."""
    gap = alpha - target                                        # (N,)
    return torch.linalg.vector_norm(gap) + torch.linalg.vector_norm(gap[:, None] * f)


def surprise_map(e: torch.Tensor, temperature: float) -> torch.Tensor:
    return torch.softmax(e / temperature, dim=0)                # (N,)


def configured_location(grid: torch.Tensor, cfg: PerceptionConfig) -> tuple[float, float]:
    """`action_location` with the location settings of `cfg`."""
    return action_location(grid, cfg.location, cfg.location_share, cfg.location_prior,
                           cfg.location_floor, region_share=cfg.location_region_share,
                           region_spread=cfg.location_region_spread)


def action_location(grid: torch.Tensor, kind: str, share: float,
                    prior: float = 0.0, floor: str = 'zero', *,
                    region_share: float = 0.5,
                    region_spread: float = 0.0) -> tuple[float, float]:
    """
    (x, y) of the action on a (rows, cols) map, in cells (0.5 = the first cell's centre):
    'peak' the argmax cell's centre; 'mass' the centroid of the cells that reach `share` of
    the peak, each weighted by its map value (`floor` 'zero') or by its height above the
    map's lowest cell ('min'; a map with nothing above its floor gives the grid's centre);
    'region' the centre of the box round the peak's blob (`metrics.blob_box` with
    `region_share`): the cells connected to the peak whose log stands at least that share
    of the way from the map's lowest cell up to its peak, the whole moving person rather
    than the head and shoulders that are most surprising. With `region_spread` > 0, the
    mean of that centre at three bars, `region_share` and `region_spread` below and above
    it: a cell crossing one bar moves the location by a sixth of a cell, not half of one.
    With `prior` > 0 the map is first weighted by a Gaussian of that width (cells) on the
    grid's centre, where the camera looks.
    """
    rows, cols = grid.shape
    ys, xs = torch.meshgrid(torch.arange(rows) + 0.5, torch.arange(cols) + 0.5, indexing='ij')
    near = (torch.exp(-((xs - cols / 2) ** 2 + (ys - rows / 2) ** 2) / (2 * prior ** 2))
            if prior > 0 else torch.ones(()))
    weighted = grid * near
    if kind == 'peak':
        row, col = divmod(int(torch.argmax(weighted)), cols)
        return col + 0.5, row + 0.5
    if kind == 'region':
        bars = ((region_share - region_spread, region_share, region_share + region_spread)
                if region_spread > 0 else (region_share,))
        heat = weighted.numpy()
        boxes = [metrics.blob_box(heat, (cols, rows), share=min(max(bar, 0.0), 1.0))
                 for bar in bars]
        if boxes[0] is None:                    # no positive peak: every bar alike
            return cols / 2, rows / 2
        return (sum(x + w / 2 for x, _, w, _ in boxes) / len(boxes),
                sum(y + h / 2 for _, y, _, h in boxes) / len(boxes))
    height = (grid - grid.min()) * near if floor == 'min' else weighted
    weight = torch.where(weighted >= share * weighted.max(), height, torch.zeros(()))
    total = weight.sum()
    if total <= 0:
        return cols / 2, rows / 2
    return float((weight * xs).sum() / total), float((weight * ys).sum() / total)
