"""Benchmarks: `python -m activeloc_ros.bench {perception,passive,screen,...} --help`."""
import argparse
import io
import json
import multiprocessing
import os
from pathlib import Path
import signal
from typing import Callable, Iterator

from activeloc_ros import data
from activeloc_ros.errors import ConfigError
from activeloc_ros.paths import write_atomic


def names(values: list[str] | None) -> list[str]:
    """Command-line names given as separate words or comma-separated."""
    return [v for item in values or [] for v in item.split(',') if v]


def key_values(items: list[str], option: str) -> dict:
    """KEY=VALUE words as a dict; values are JSON when they parse, else strings."""
    out = {}
    for item in items:
        key, sep, value = item.partition('=')
        if not sep or not key:
            raise ConfigError(f'{option} expects KEY=VALUE, got {item!r}')
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            try:
                out[key] = float(value)     # nan, inf: numbers JSON does not spell
            except ValueError:
                out[key] = value
    return out


SEED_MAX = 2**32 - 1    # numpy's and torch's seeds


def check_seed(seed: int) -> None:
    """--seed: numpy and torch take 0 .. 2**32 - 1; raises ConfigError before any run."""
    if not 0 <= seed <= SEED_MAX:
        raise ConfigError(f'--seed must be in [0, {SEED_MAX}], got {seed}')


def output_dir(path: str | Path, option: str = '--out') -> Path:
    """
    The folder a benchmark writes to, made now: a path that is a file or cannot be made
    fails before the run, not after it with the results lost. Raises ConfigError.
    """
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f'{option} {path}: cannot make that folder: '
                          f'{exc.strerror or exc}') from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise ConfigError(f'{option} {path}: cannot write there')
    return out


def save_png(fig, path: Path, *, dpi: int = 110) -> Path:
    """Lay out a matplotlib figure, write it to ``path`` as PNG (atomically) and close it."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format='png', dpi=dpi)
    plt.close(fig)
    write_atomic(path, buf.getvalue())
    return path


def add_jobs_option(p: argparse.ArgumentParser) -> None:
    """--jobs: how many worker processes."""
    p.add_argument('--jobs', type=int, default=min(2, os.cpu_count() or 1), metavar='N',
                   help='worker processes (default: 2 or the number of cores)')


def add_output_options(p: argparse.ArgumentParser, out_help: str,
                       out_default: str | None = None) -> None:
    """--json, --out (``out_help``, ``out_default``) and --quiet: where the results go."""
    p.add_argument('--json', action='store_true', help='one JSON object per method on stdout')
    p.add_argument('--out', metavar='DIR', default=out_default, help=out_help)
    p.add_argument('--quiet', action='store_true', help='no progress on stderr')


def add_sequence_options(p: argparse.ArgumentParser) -> None:
    """--data, --sequences, --camera and --max-frames: which annotated sequences to run."""
    p.add_argument('--data', help=f'sequence root (default ${data.ENV_VAR} or '
                                  '../shared/data/sequences beside the repo)')
    p.add_argument('--sequences', nargs='+', metavar='NAME', help='only these sequences')
    p.add_argument('--camera', nargs='+', choices=sorted(data.KIND_ORDER), metavar='KIND',
                   help='only sequences of these camera kinds: static, pan, moving')
    p.add_argument('--max-frames', type=int, metavar='N', help='first N frames of each')


def load_selected(args: argparse.Namespace
                  ) -> tuple[Path, list[data.Sequence], list[tuple[str, str]]]:
    """
    (root, sequences, skipped) that `add_sequence_options` chose, the sequences in
    camera-kind then name order; raises ActivelocError.
    """
    root = data.resolve_data_root(args.data)
    sequences, skipped = data.load_sequences(root, names=names(args.sequences),
                                             cameras=args.camera)
    unknown = [name for name, reason in skipped if reason == data.NO_SUCH_SEQUENCE]
    if unknown:     # a typo stops the run at once, not after an hour without that sequence
        raise ConfigError(f'no sequence {", ".join(map(repr, unknown))} under {root}')
    sequences.sort(key=lambda s: (data.KIND_ORDER[s.camera_kind], s.name))
    return root, sequences, skipped


def in_threads(run: Callable[[dict], dict], job: dict) -> dict:
    """
    ``run(job)`` with torch's and OpenCV's thread counts set to ``job['threads']`` (when
    set), then back to the process's (with --jobs 1 that is the caller's process).
    """
    import cv2
    import torch
    before = torch.get_num_threads(), cv2.getNumThreads()
    if job.get('threads'):
        torch.set_num_threads(job['threads'])
        cv2.setNumThreads(job['threads'])   # OpenCV's own pool would oversubscribe the cores
    try:
        return run(job)
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])


def _ignore_sigint() -> None:
    # workers: Ctrl-C reaches the whole process group; the parent alone handles it
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_jobs(run_job: Callable[[dict], dict], work: list[dict], *, jobs: int
             ) -> Iterator[dict]:
    """
    The results of ``run_job`` (a module-level function) over ``work``: in this process
    for one job, else in ``jobs`` spawned worker processes, as they finish.
    """
    if jobs == 1:
        yield from map(run_job, work)
        return
    pool = multiprocessing.get_context('spawn').Pool(jobs, initializer=_ignore_sigint)
    try:
        yield from pool.imap_unordered(run_job, work)
    finally:
        pool.terminate()
