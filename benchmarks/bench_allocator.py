"""
What ``pipeline.keep_freed_memory_mb`` changes: page faults and time per pair, in fresh processes.

The setting is process-wide and cannot be undone, so each run is a process of its own: it loads
the KITTI clips into memory (as ``bench_accuracy.py`` does), then runs the pipeline over each
clip with the setting at 0 (glibc's defaults) or at its default; runs with either value
alternate, round by round. Prints, per clip and value, the median over rounds of: the median
total ms per pair, the mean page faults of the caller's thread per pair, and its mean system
(kernel) CPU ms per pair (the first two pairs left out); then the ratio of the ms medians.

Whether glibc's defaults return a pair's memory to the system depends on what the process freed
before (glibc raises its thresholds after each large block it unmaps), so other processes (the
node, ``stereo_vo run``, ``bench_speed.py`` after its renders) may not show the faults at all.
The runs leave out the environment's glibc malloc settings (``MALLOC_*_``, ``GLIBC_TUNABLES``).
Without the clips a rendered urban scene (1241x376, ``--frames`` pairs) is used instead,
written to a temporary KITTI folder and loaded the same way.

Usage::

    python benchmarks/bench_allocator.py [--data ../shared/data] [--rounds 4] [--frames 40]
        [--set pipeline.threads=1]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_accuracy import KITTI_CLIPS, SHARED_DATA  # noqa: E402
import numpy as np  # noqa: E402
from stereo_vo_ros.allocator import malloc_settings  # noqa: E402
from stereo_vo_ros.config import Config  # noqa: E402

#: One run: load the clips, run each, print one JSON line per clip.
RUN = """
import json, resource, sys, time
from stereo_vo_ros.config import Config, overrides_from_items
from stereo_vo_ros.io import open_sequence
from stereo_vo_ros.pipeline import StereoOdometry
keep, folders, items = int(sys.argv[1]), sys.argv[2].split(','), json.loads(sys.argv[3])
clips = [(f, list(open_sequence(f))) for f in folders]
items = items + [f'pipeline.keep_freed_memory_mb={keep}']
config = Config().replace(**overrides_from_items(items))
for folder, frames in clips:
    vo = StereoOdometry(config)
    vo.workers.wait_ready()
    rows = []
    for frame in frames:
        r0 = resource.getrusage(resource.RUSAGE_THREAD)
        t0 = time.perf_counter()
        vo.process(frame)
        t1 = time.perf_counter()
        r1 = resource.getrusage(resource.RUSAGE_THREAD)
        rows.append(((t1 - t0) * 1e3, r1.ru_minflt - r0.ru_minflt,
                     (r1.ru_stime - r0.ru_stime) * 1e3))
    vo.close()
    print(json.dumps([folder, rows[2:]]))
"""


def run(keep: int, folders: list[str], items: list[str]) -> dict[str, np.ndarray]:
    """One process: {folder: (pairs, 3) total ms, page faults, system ms} per pair."""
    # Without the operator's malloc settings, which the pipeline would leave as set.
    operator = malloc_settings(os.environ)
    env = {key: value for key, value in os.environ.items() if key not in operator}
    env.update(OPENBLAS_NUM_THREADS='1', OMP_NUM_THREADS='1',
               PYTHONPATH=os.pathsep.join([str(ROOT)] + sys.path))
    out = subprocess.run([sys.executable, '-c', RUN, str(keep), ','.join(folders),
                          json.dumps(items)], capture_output=True, text=True, env=env)
    if out.returncode:
        sys.stderr.write(out.stderr)
        raise SystemExit(f'the run with keep_freed_memory_mb={keep} failed')
    result = {}
    for line in out.stdout.splitlines():
        if line.startswith('['):
            folder, rows = json.loads(line)
            result[folder] = np.asarray(rows, float)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data', type=Path, default=SHARED_DATA)
    parser.add_argument('--rounds', type=int, default=4)
    parser.add_argument('--frames', type=int, default=40,
                        help='pairs of the rendered scene used without the clips')
    parser.add_argument('--set', action='append', default=[], metavar='SECTION.KEY=VALUE',
                        help='overrides of the defaults for both values')
    args = parser.parse_args()
    default_keep = Config().pipeline.keep_freed_memory_mb
    if default_keep <= 0:
        raise SystemExit('pipeline.keep_freed_memory_mb is off by default: nothing to compare')
    folders = [str(args.data / name) for name in KITTI_CLIPS if (args.data / name).is_dir()]
    with tempfile.TemporaryDirectory() as tmp:
        if not folders:
            from stereo_vo_ros.io.kitti import write_kitti
            from stereo_vo_ros.synthetic import SequenceSpec, SyntheticSequence
            print(f'no KITTI clip in {args.data}: a rendered urban scene (1241x376, '
                  f'{args.frames} pairs) instead')
            seq = SyntheticSequence(SequenceSpec.preset('urban', n_frames=args.frames + 1,
                                                        seed=0))
            write_kitti(Path(tmp) / 'urban', seq, seq.ground_truth)
            folders = [str(Path(tmp) / 'urban')]
        compare(folders, default_keep, args)
    return 0


def compare(folders: list[str], default_keep: int, args: argparse.Namespace) -> None:
    """Run the rounds over ``folders`` and print the table."""
    print(f'clips: {", ".join(Path(f).name for f in folders)}; overrides: {args.set or "none"}; '
          f'{args.rounds} rounds, keep_freed_memory_mb 0 and {default_keep} alternated')
    stats = {(f, k): [] for f in folders for k in (0, default_keep)}
    for r in range(args.rounds):
        for keep in ((0, default_keep) if r % 2 == 0 else (default_keep, 0)):
            for folder, rows in run(keep, folders, args.set).items():
                stats[(folder, keep)].append((np.median(rows[:, 0]), rows[:, 1].mean(),
                                              rows[:, 2].mean()))
    print(f'{"clip":24s} {"keep MB":>7s} {"ms/pair":>8s} {"faults/pair":>11s} '
          f'{"sys ms/pair":>11s}')
    for folder in folders:
        medians = {}
        for keep in (0, default_keep):
            ms, faults, sys_ms = np.median(np.asarray(stats[(folder, keep)]), axis=0)
            medians[keep] = ms
            print(f'{Path(folder).name:24s} {keep:7d} {ms:8.2f} {faults:11.0f} {sys_ms:11.2f}')
        print(f'{"":24s} ratio {medians[default_keep] / medians[0]:.3f}')


if __name__ == '__main__':
    sys.exit(main())
