"""
Property-based fuzzing (hypothesis) of the message conversions and of the core pipeline.

Random ``sensor_msgs/Image`` messages (valid and invalid encodings, steps, sizes and data
lengths), random ``CameraInfo`` pairs and random stereo sequences (images, calibrations,
stamps) go through the code the node runs. The only exceptions allowed to escape are the
documented validation errors (``ImageError``, ``CalibrationError``); every result is finite.
"""

from __future__ import annotations

import logging

from hypothesis import event, example, given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_msgs.msg import Image
from stereo_vo_ros.config import Config
from stereo_vo_ros.errors import CalibrationError, ImageError
from stereo_vo_ros.estimation.camera import StereoCalibration
from stereo_vo_ros.pipeline import StereoOdometry
from stereo_vo_ros.records import OdometryResult, StereoFrame, TrackingStatus
from stereo_vo_ros.ros import conversions as conv
from stereo_vo_ros.synthetic import render_sequence, SequenceSpec

FUZZ = settings(deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
ENCODINGS = sorted(conv.ENCODINGS) + ['yuv422', 'bayer_rggb8', '8UC1', '16UC1', 'MONO8', '',
                                      'rgb16', '32FC1', 'mono8 ', 'm\u00f6no8']
#: Floats a camera driver might put in a CameraInfo, sane and insane.
ODD_FLOATS = st.one_of(
    st.sampled_from([0.0, -0.0, 1.0, -1.0, np.nan, np.inf, -np.inf, 1e-300, 1e300, 5e-324]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.floats(-5e3, 5e3))


# -- images --------------------------------------------------------------------------------
@st.composite
def image_messages(draw):
    """Draw Image messages whose fields are mostly consistent, sometimes not at all."""
    encoding = draw(st.sampled_from(ENCODINGS))
    dtype, channels = conv.ENCODINGS.get(encoding, (np.uint8, draw(st.integers(1, 4))))
    width = draw(st.one_of(st.integers(0, 24), st.sampled_from([2**31 - 1, 2**32 - 1])))
    height = draw(st.one_of(st.integers(0, 24), st.sampled_from([2**31 - 1, 2**32 - 1])))
    row = width * channels * np.dtype(dtype).itemsize
    step = draw(st.one_of(st.just(row), st.integers(0, 8).map(lambda p: row + p),
                          st.integers(0, 2**32 - 1)))
    size = step * height
    if size > 4096:  # do not allocate gigabytes: such messages always have too few bytes
        n_bytes = draw(st.integers(0, 64))
    else:
        n_bytes = draw(st.one_of(st.just(size), st.integers(max(size - 3, 0), size + 3),
                                 st.integers(0, 600)))
    msg = Image()
    msg.encoding = encoding
    msg.width, msg.height, msg.step = width, height, min(step, 2**32 - 1)
    msg.is_bigendian = draw(st.integers(0, 255))
    msg.data = draw(st.binary(min_size=n_bytes, max_size=n_bytes))
    return msg


@settings(FUZZ, max_examples=400)
@given(msg=image_messages())
def test_image_conversion_raises_only_image_error(msg):
    try:
        pixels = conv.numpy_from_image(msg)
    except ImageError as exc:
        assert str(exc)  # messages name the offending value
        with pytest.raises(ImageError):
            conv.grey_from_image(msg)
        return
    dtype, channels = conv.ENCODINGS[msg.encoding]
    shape = (msg.height, msg.width) if channels == 1 else (msg.height, msg.width, channels)
    assert pixels.shape == shape and pixels.dtype == dtype
    assert len(msg.data) == msg.step * msg.height
    grey = conv.grey_from_image(msg)
    assert grey.shape == (msg.height, msg.width) and grey.dtype == dtype
    assert grey.flags.c_contiguous


@settings(FUZZ, max_examples=150)
@given(encoding=st.sampled_from(sorted(conv.ENCODINGS)), height=st.integers(1, 9),
       width=st.integers(1, 9), seed=st.integers(0, 2**32 - 1))
def test_image_round_trip_is_exact(encoding, height, width, seed):
    dtype, channels = conv.ENCODINGS[encoding]
    shape = (height, width) if channels == 1 else (height, width, channels)
    pixels = np.random.default_rng(seed).integers(0, np.iinfo(dtype).max, shape,
                                                  endpoint=True).astype(dtype)
    msg = conv.image_from_numpy(pixels, encoding)
    np.testing.assert_array_equal(conv.numpy_from_image(msg), pixels)


# -- calibration ---------------------------------------------------------------------------
@st.composite
def camera_info_pairs(draw):
    """Draw two CameraInfo around a plausible rectified pair, fields broken at random."""
    fx = draw(st.one_of(st.floats(50.0, 2000.0), ODD_FLOATS))
    fy = draw(st.one_of(st.just(fx), ODD_FLOATS))
    cx, cy = draw(st.one_of(st.floats(0.0, 1000.0), ODD_FLOATS)), draw(st.floats(0.0, 500.0))
    baseline = draw(st.one_of(st.floats(0.01, 2.0), ODD_FLOATS))
    width = draw(st.one_of(st.integers(1, 2000), st.sampled_from([0, 2**32 - 1])))
    height = draw(st.one_of(st.integers(1, 2000), st.sampled_from([0, 2**32 - 1])))
    P0 = np.array([[fx, 0.0, cx, 0.0], [0.0, fy, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    P1 = P0.copy()
    P1[0, 3] = -fx * baseline if np.isfinite(fx * baseline) else baseline
    for P in (P0, P1):  # sometimes any entry at all
        for _ in range(draw(st.integers(0, 2))):
            P[draw(st.integers(0, 2)), draw(st.integers(0, 3))] = draw(ODD_FLOATS)
    infos = []
    for P in (P0, P1):
        other_size = draw(st.booleans()) and draw(st.booleans())
        msg = conv.camera_info_from_matrices(
            P, width + (1 if other_size and P is P1 else 0), height,
            D=draw(st.lists(st.one_of(st.floats(-0.5, 0.5), ODD_FLOATS), max_size=8)),
            R=np.eye(3) if draw(st.booleans()) else
            np.array(draw(st.lists(ODD_FLOATS, min_size=9, max_size=9))).reshape(3, 3))
        msg.distortion_model = draw(st.sampled_from(['plumb_bob', 'rational_polynomial',
                                                     'equidistant', '', 'nonsense']))
        infos.append(msg)
    return infos


@settings(FUZZ, max_examples=400)
@given(infos=camera_info_pairs(), kind=st.sampled_from(['rectified', 'raw', 'fisheye']))
def test_calibration_from_camera_info_raises_only_calibration_error(infos, kind):
    left, right = infos
    try:
        with np.errstate(all='ignore'):  # absurd values overflow on their way to the error
            calib = conv.calibration_from_camera_info(left, right, kind)
    except CalibrationError as exc:
        assert str(exc)
        return
    assert kind in ('rectified', 'raw')
    assert np.isfinite(calib.baseline_m) and calib.baseline_m > 0
    assert calib.size[0] > 0 and calib.size[1] > 0
    for a in (calib.K_left, calib.K_right, calib.R_right_left, calib.t_right_left):
        assert np.all(np.isfinite(a))
    assert calib.K_left[0, 0] > 0 and calib.K_left[1, 1] > 0


def test_singular_projection_is_a_calibration_error():
    """Found by the fuzzer: positive focal lengths, yet a singular matrix (LinAlgError)."""
    P0 = np.array([[1e-300, 0.0, 0.0, 0.0], [1.0, 1e-300, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    P1 = np.array([[1e-300, 0.0, 0.0, -1e-300], [0.0, 1e-300, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    left, right = (conv.camera_info_from_matrices(P, 1, 1) for P in (P0, P1))
    with pytest.raises(CalibrationError, match='calibration matrices are numerically singular'):
        conv.calibration_from_camera_info(left, right)
    with pytest.raises(CalibrationError, match='numerically singular'):  # offline tools too
        StereoCalibration.from_projections(P0, P1, 1, 1)


def test_camera_info_with_wrong_array_lengths_is_a_calibration_error():
    msg = conv.camera_info_from_matrices(np.hstack([np.eye(3), np.zeros((3, 1))]), 4, 3)
    fields = {'k': list(msg.k), 'd': list(msg.d), 'r': list(msg.r), 'p': list(msg.p)[:11],
              'width': 4, 'height': 3}
    with pytest.raises(CalibrationError, match="'p' must have 12 values, got 11"):
        StereoCalibration.from_camera_info(fields, fields)


# -- pipeline ------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def frames():
    """Render a few 320x96 pairs (real texture and motion) once for the module."""
    spec = SequenceSpec.preset('demo', n_frames=10, width=320, height=96, turns=False,
                               start_time_s=50.0)
    return spec, list(render_sequence(spec))


FRAME_EDITS = ['none'] * 12 + [
    'black', 'white', 'noise', 'swap', 'mono16', 'crop', 'right_crop', 'float', 'colour',
    'empty', 'half_black', 'flip']
#: Edits that make an input the pipeline must refuse with an ImageError.
INVALID_EDITS = ('crop', 'right_crop', 'float', 'colour', 'empty')


def _edit(left: np.ndarray, right: np.ndarray, edit: str, rng: np.random.Generator):
    """Return the pair changed by ``edit`` (some edits give inputs the pipeline must refuse)."""
    if edit == 'black':
        return np.zeros_like(left), np.zeros_like(right)
    if edit == 'white':
        return np.full_like(left, 255), np.full_like(right, 255)
    if edit == 'noise':
        return (rng.integers(0, 256, left.shape, dtype=np.uint8),
                rng.integers(0, 256, right.shape, dtype=np.uint8))
    if edit == 'swap':
        return right, left
    if edit == 'mono16':
        return left.astype(np.uint16) * 257, right.astype(np.uint16) * 257
    if edit == 'crop':
        return left[:-8], right[:-8]
    if edit == 'right_crop':
        return left, right[:, 4:]
    if edit == 'float':
        return left.astype(np.float32), right.astype(np.float32)
    if edit == 'colour':
        return np.dstack([left] * 3), np.dstack([right] * 3)
    if edit == 'empty':
        return left[:0], right[:0]
    if edit == 'half_black':
        left = left.copy()
        left[:, : left.shape[1] // 2] = 0
        return left, right
    if edit == 'flip':
        return left[::-1].copy(), right[::-1].copy()
    return left, right


@st.composite
def stereo_runs(draw):
    """
    Draw a calibration near the rendered one, a short run of edited, odd pairs, and threads.

    About 30 % of the runs use the worker process (two threads): results do not depend on the
    thread count (``test_parallel``), and each worker process takes about a second to start.
    """
    scale = draw(st.sampled_from([1.0] * 4 + [0.5, 2.0, 1e-3, 1e3, 1e6, 1e-9, 1e12]))
    baseline_scale = draw(st.sampled_from([1.0] * 4 + [0.1, 10.0, 1e-5, 1e4, 1e9]))
    cx_shift = draw(st.sampled_from([0.0] * 4 + [40.0, -500.0, 1e5]))
    steps = draw(st.lists(st.tuples(
        # frame index offset: mostly forwards, sometimes repeats, teleports or backwards
        st.sampled_from([1] * 8 + [0, 2, -1, -3, 5, 9]),
        st.sampled_from([0.1] * 8 + [0.0, -0.05, 1e-9, 0.5, 3.0, -2.0, 1e4, -1e4]),
        st.sampled_from(FRAME_EDITS)), min_size=2, max_size=6))
    start = draw(st.sampled_from([0.0, 50.0, 1.7e9, -100.0, 1e12]))
    threads = draw(st.sampled_from([1, 1, 2]))
    return scale, baseline_scale, cx_shift, start, steps, draw(st.integers(0, 2**16)), threads


def _finite(result: OdometryResult) -> bool:
    return all(np.all(np.isfinite(a)) for a in (
        result.T_world_cam, result.pose_covariance, result.velocity,
        result.velocity_covariance))


@pytest.mark.parametrize('road', [False, True], ids=['default', 'road_vehicle'])
@settings(FUZZ, max_examples=100)
@given(run=stereo_runs())
# Found by this test: a singular information matrix in the filter escaped as LinAlgError ...
@example(run=(1e6, 1.0, 0.0, 0.0, [(1, 0.1, 'none')] * 5, 0, 2))
# ... and coasting made the velocity covariance indefinite (then singular) after 5 frames.
@example(run=(1.0, 1.0, 0.0, 0.0, [(1, 0.1, 'none')] * 2 + [(0, 0.1, 'black')] * 6 +
              [(1, 0.1, 'none')] * 4, 0, 2))
def test_pipeline_raises_only_validation_errors_and_stays_finite(frames, road, run):
    """
    Odd calibrations, stamps and images: only validation errors, finite and valid results.

    Also as on a road vehicle: the road alignment (``road.min_pixels`` lowered so that the
    320x96 pairs have road enough to align) and the rolling-vehicle prior on.
    """
    spec, rendered = frames
    scale, baseline_scale, cx_shift, start, steps, seed, threads = run
    P0, P1 = spec.projections()
    P0, P1 = P0.copy(), P1.copy()
    for P in (P0, P1):
        P[:2, :3] *= scale
        P[0, 2] += cx_shift
    P1[0, 3] = -P0[0, 0] * spec.baseline_m * baseline_scale
    calib = StereoCalibration.from_projections(P0, P1, spec.width, spec.height)
    config = Config().replace(**{'road.enabled': True, 'road.min_pixels': 50,
                                 'vehicle.nonholonomic': True}) if road else Config()
    vo = StereoOdometry(config.replace(**{'pipeline.threads': threads}))
    event(f'{vo.workers.kind} worker')
    rng = np.random.default_rng(seed)
    stamp, index = start, 0
    logging.disable(logging.WARNING)  # the pipeline's warnings are expected here
    try:
        for offset, dt, edit in steps:
            index = int(np.clip(index + offset, 0, len(rendered) - 1))
            stamp += dt
            left, right = _edit(rendered[index].left, rendered[index].right, edit, rng)
            try:
                result = vo.process(StereoFrame(left, right, stamp, calib))
            except ImageError as exc:
                assert edit in INVALID_EDITS, exc
                event('ImageError')
                continue
            event(f'status {result.status.value}')
            if result.road_fused:
                event('road motion fused')
            if result.vehicle_fused:
                event('vehicle prior fused')
            assert edit not in INVALID_EDITS
            assert _finite(result), (result.status, result.message)
            R = result.T_world_cam[:3, :3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
            for cov in (result.pose_covariance, result.velocity_covariance):
                np.testing.assert_allclose(cov, cov.T, rtol=1e-9, atol=1e-12)
                scale = max(1.0, float(np.abs(cov).max()))
                assert np.linalg.eigvalsh(cov).min() >= -1e-9 * scale, \
                    (result.status, result.message)
            assert isinstance(result.status, TrackingStatus)
            if result.accepted:
                odom = conv.base_odometry_from_result(
                    result, conv.transform_from_xyz_rpy([0, 0, 0], [-90, 0, -90]))
                assert odom.is_finite(), (result.status, result.message)
                assert np.linalg.eigvalsh(odom.pose_covariance).min() > 0
        vo.settle()  # the last pair's work after its pose raises nothing either
    finally:
        logging.disable(logging.NOTSET)
        vo.close()
