"""
The benchmark scripts that run long run end to end on a tiny input.

Their figures are not checked here (they are what ``docs/benchmarks.md`` reports); what is
checked is that a script goes through every variant and prints its table, so that one that
stops half way (a helper it calls changed) is found before someone waits 20 minutes for it.
"""

import math
from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]
STAGE_VALUE = REPO / 'benchmarks' / 'bench_stage_value.py'


def variant_labels() -> list[str]:
    """Return the labels of ``bench_stage_value.VARIANTS``, in order."""
    sys.path.insert(0, str(REPO / 'benchmarks'))
    try:
        from bench_stage_value import VARIANTS
    finally:
        sys.path.remove(str(REPO / 'benchmarks'))
    return [label for label, _ in VARIANTS]


def stage_value_table(*args: str) -> tuple[str, list[str], list[list[str]]]:
    """
    Run bench_stage_value.py; return its output and its last table's header and rows.

    Header and rows are lists of cells, the label first (labels fill the first 24 characters).
    """
    out = subprocess.run([sys.executable, str(STAGE_VALUE), *args], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout[out.stdout.rindex('\nvariant'):].splitlines()[1:]
    head = ['variant'] + [' '.join(p) for p in zip(*[iter(lines[0][24:].split())] * 2)]
    return out.stdout, head, [[row[:24].strip(), *row[24:].split()] for row in lines[1:]]


def test_stage_value_scores_every_variant_on_a_rendered_scene(tmp_path):
    """One 4-pair demo render, without the clips: a row for every variant."""
    text, _, rows = stage_value_table(
        '--data', str(tmp_path / 'no_clips'), '--presets', 'demo', '--seeds', '0',
        '--frames', '4', '--rounds', '0', '--cache', str(tmp_path / 'cache'))
    assert 'KITTI clips not found' in text
    labels = variant_labels()
    assert max(len(label) for label in labels) <= 24  # the table's label column
    assert [row[0] for row in rows] == labels
    for row in rows:
        # The scene's t_rel: NaN, a 4-pair drive has no 100 m segment; that it printed one is
        # what is checked (the clips' test checks finite figures).
        float(row[1])


def test_stage_value_times_a_rendered_scene_of_the_size_asked(tmp_path):
    """``--render WxH`` without the clips: timed, run and scored, a row for every variant."""
    text, head, rows = stage_value_table('--data', str(tmp_path / 'no_clips'), '--presets',
                                         '--rounds', '1', '--render', '320x240')
    assert 'rendered urban scene 320x240' in text
    assert head == ['variant', '320x240 ms', '320x240 drift', '320x240 feats'], head
    assert [row[0] for row in rows] == variant_labels()
    for row in rows:
        saved, _, drift, feats = row[1:]
        assert math.isfinite(float(saved)), row
        assert math.isfinite(float(drift)) and float(drift) >= 0.0, row
        assert float(feats) > 10, row
    assert float(rows[0][1]) == 0.0  # the default against itself
    bad = subprocess.run([sys.executable, str(STAGE_VALUE), '--presets', '--rounds', '0',
                          '--render', '0x240'], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and '--render wants WxH' in bad.stderr


def test_stage_value_runs_the_clips_at_a_lower_frame_rate(shared_data):
    """Every fifth frame of the KITTI clips: finite drift and features for every variant."""
    text, head, rows = stage_value_table('--data', str(shared_data), '--presets', '--rounds',
                                         '0', '--every', '5')
    assert 'every 5th frame' in text
    drift = [i for i, cell in enumerate(head) if cell.endswith(' drift')]
    features = [i for i, cell in enumerate(head) if cell.endswith(' feats')]
    assert drift and len(drift) == len(features) and len(head) == 1 + 2 * len(drift), head
    assert [row[0] for row in rows] == variant_labels()
    for row in rows:
        assert len(row) == len(head), row
        assert all(math.isfinite(float(row[i])) and float(row[i]) >= 0.0 for i in drift), row
        assert all(float(row[i]) > 10 for i in features), row


@pytest.mark.skipif(not sys.platform.startswith('linux'),
                    reason='the benchmark counts page faults per thread (Linux)')
def test_allocator_benchmark_compares_both_settings_on_a_rendered_scene(tmp_path):
    """Six rendered pairs, one round: a row for glibc's defaults and one for the setting."""
    out = subprocess.run([sys.executable, str(REPO / 'benchmarks' / 'bench_allocator.py'),
                          '--data', str(tmp_path / 'no_clips'), '--rounds', '1', '--frames',
                          '6'], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert 'no KITTI clip' in out.stdout
    rows = [line.split() for line in out.stdout.splitlines() if line.startswith('urban ')]
    assert [row[1] for row in rows] == ['0', '32']
    for row in rows:
        assert all(math.isfinite(float(cell)) for cell in row[2:])
    assert 'ratio' in out.stdout.splitlines()[-1]
