"""
Per-sequence plots over time of the screen benchmark: AAE, pan and tilt of every method,
from the per-frame records that `screen.json` holds (`frames`, `frame_columns`).
"""
import math
from pathlib import Path

from activeloc_ros.bench import save_png

PANELS = (('aae_deg', 'AAE (deg)'), ('pan_deg', 'pan (deg)'), ('tilt_deg', 'tilt (deg)'))


def series(result: dict, method: str, sequence: str, column: str) -> tuple[list, list]:
    """
    (times in s, values) of one per-frame column of a run; a frame without a value
    (not scored) is NaN, a gap in the line.
    """
    columns = result['frame_columns']
    t, k = columns.index('t'), columns.index(column)
    frames = result['frames'].get(f'{method}/{sequence}', [])
    return ([f[t] for f in frames],
            [math.nan if f[k] is None else f[k] for f in frames])


def time_plots(result: dict, out: Path) -> list[Path]:
    """
    One PNG per sequence, `time_<sequence>.png` in `out`: AAE, pan and tilt over the
    scene's time, one line per method (colours as in the bar charts); written atomically.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    colours = plt.get_cmap('tab20')
    paths = []
    for sequence in result['sequences']:
        fig, axes = plt.subplots(len(PANELS), 1, sharex=True, figsize=(10, 7))
        for i, row in enumerate(result['methods']):
            for ax, (column, _) in zip(axes, PANELS):
                t, values = series(result, row['method'], sequence, column)
                ax.plot(t, values, color=colours(i % colours.N), linewidth=1,
                        label=row['method'])
        for ax, (_, label) in zip(axes, PANELS):
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[-1].set_xlabel('scene time (s)')
        axes[0].set_title(f'{sequence}: error to the closest actor and camera angles')
        axes[0].legend(fontsize=7, ncol=2, loc='upper left', bbox_to_anchor=(1.0, 1.0))
        paths.append(save_png(fig, out / f'time_{sequence}.png', dpi=100))
    return paths
