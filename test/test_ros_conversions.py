"""Tests of the ROS message conversions (images, camera info, odometry, diagnostics)."""

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import Image
from stereo_vo_ros.errors import CalibrationError, ImageError
from stereo_vo_ros.records import Correspondences, OdometryResult, TrackingStatus
from stereo_vo_ros.ros import conversions as conv
from stereo_vo_ros.ros.diagnostics import processing_ms

RNG = np.random.default_rng(7)

#: Body (x forward, y left, z up) <- optical (x right, y down, z forward).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _padded_msg(pixels: np.ndarray, encoding: str, pad: int, big_endian: bool = False
                ) -> Image:
    """Build an Image by hand with ``pad`` bytes of junk after every row."""
    h, w = pixels.shape[:2]
    wire = pixels.astype(pixels.dtype.newbyteorder('>' if big_endian else '<'))
    rows = wire.reshape(h, -1).view(np.uint8).reshape(h, -1)
    junk = np.full((h, pad), 0xAB, np.uint8)
    msg = Image()
    msg.height, msg.width, msg.encoding = h, w, encoding
    msg.is_bigendian = int(big_endian)
    msg.step = rows.shape[1] + pad
    msg.data = np.hstack([rows, junk]).tobytes()
    return msg


@pytest.mark.parametrize('encoding,dtype,channels', [
    ('mono8', np.uint8, 1), ('mono16', np.uint16, 1), ('rgb8', np.uint8, 3),
    ('bgr8', np.uint8, 3), ('rgba8', np.uint8, 4), ('bgra8', np.uint8, 4)])
@pytest.mark.parametrize('pad', [0, 5])
def test_every_encoding_with_and_without_row_padding(encoding, dtype, channels, pad):
    shape = (7, 11) if channels == 1 else (7, 11, channels)
    pixels = RNG.integers(0, np.iinfo(dtype).max, size=shape, dtype=dtype)
    out = conv.numpy_from_image(_padded_msg(pixels, encoding, pad))
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, pixels)
    grey = conv.grey_from_image(_padded_msg(pixels, encoding, pad))
    assert grey.shape == (7, 11) and grey.dtype == dtype


def test_mono16_big_endian_is_swapped_to_native():
    pixels = np.array([[1, 256, 258], [0x1234, 0xFFFE, 7]], np.uint16)
    msg = _padded_msg(pixels, 'mono16', pad=2, big_endian=True)
    assert bytes(msg.data[:2]) == b'\x00\x01'  # really big-endian on the wire
    out = conv.numpy_from_image(msg)
    np.testing.assert_array_equal(out, pixels)
    assert out.dtype == np.uint16 and out.dtype.isnative


def test_colour_to_grey_uses_the_channel_order_of_the_encoding():
    red = np.zeros((2, 3, 3), np.uint8)
    red[..., 0] = 200  # first channel
    as_rgb = conv.grey_from_image(_padded_msg(red, 'rgb8', 0))
    as_bgr = conv.grey_from_image(_padded_msg(red, 'bgr8', 0))
    # ITU-R 601 luma: 0.299 R + 0.587 G + 0.114 B
    assert np.all(np.abs(as_rgb.astype(int) - round(0.299 * 200)) <= 1)
    assert np.all(np.abs(as_bgr.astype(int) - round(0.114 * 200)) <= 1)


def test_image_round_trip_and_message_fields():
    pixels = RNG.integers(0, 255, size=(4, 6, 3), dtype=np.uint8)
    stamp = conv.time_from_nanoseconds(12_345_678_901)
    msg = conv.image_from_numpy(pixels, 'bgr8', stamp, 'cam')
    assert (msg.width, msg.height, msg.step, msg.encoding) == (6, 4, 18, 'bgr8')
    assert msg.header.frame_id == 'cam'
    assert conv.nanoseconds_from_time(msg.header.stamp) == 12_345_678_901
    np.testing.assert_array_equal(conv.numpy_from_image(msg), pixels)
    u16 = RNG.integers(0, 65535, size=(3, 5), dtype=np.uint16)
    np.testing.assert_array_equal(conv.numpy_from_image(conv.image_from_numpy(u16, 'mono16')),
                                  u16)


@pytest.mark.parametrize('encoding', ['yuv422', '32FC1', 'bayer_rggb8', ''])
def test_unsupported_encoding_is_named_in_the_error(encoding):
    msg = _padded_msg(np.zeros((2, 2), np.uint8), 'mono8', 0)
    msg.encoding = encoding
    with pytest.raises(ImageError, match=repr(encoding).replace('[', r'\[')):
        conv.numpy_from_image(msg)


def test_bad_sizes_raise_image_error():
    good = _padded_msg(np.zeros((4, 5), np.uint8), 'mono8', 0)
    short_step = _padded_msg(np.zeros((4, 5), np.uint8), 'mono8', 0)
    short_step.step = 4
    with pytest.raises(ImageError, match='step 4'):
        conv.numpy_from_image(short_step)
    truncated = _padded_msg(np.zeros((4, 5), np.uint8), 'mono8', 0)
    truncated.data = bytes(good.data)[:-1]
    with pytest.raises(ImageError, match='19 bytes'):
        conv.numpy_from_image(truncated)
    empty = Image(encoding='mono8', width=0, height=3, step=0)
    with pytest.raises(ImageError, match='0x3'):
        conv.numpy_from_image(empty)
    with pytest.raises(ImageError, match='bgr8'):
        conv.image_from_numpy(np.zeros((2, 2), np.uint8), 'bgr8')
    with pytest.raises(ImageError, match='mono8'):
        conv.image_from_numpy(np.zeros((2, 2), np.float32), 'mono8')


def _kitti_infos():
    fx, cx, cy, base = 718.856, 607.1928, 185.2157, 0.5372
    P0 = np.array([[fx, 0, cx, 0], [0, fx, cy, 0], [0, 0, 1, 0]])
    P1 = P0.copy()
    P1[0, 3] = -fx * base
    return (conv.camera_info_from_matrices(P0, 1241, 376, frame_id='left'),
            conv.camera_info_from_matrices(P1, 1241, 376, frame_id='right'), P0)


def test_camera_info_to_stereo_calibration():
    left, right, P0 = _kitti_infos()
    calib = conv.calibration_from_camera_info(left, right, 'rectified')
    assert calib.size == (1241, 376)
    assert calib.baseline_m == pytest.approx(0.5372, rel=1e-12)
    np.testing.assert_allclose(calib.K_left, P0[:, :3])
    np.testing.assert_allclose(calib.t_right_left, [-0.5372, 0, 0], atol=1e-12)
    raw = conv.calibration_from_camera_info(left, right, 'raw')
    assert raw.kind == 'raw'
    swapped = conv.calibration_from_camera_info
    with pytest.raises(CalibrationError, match='right of the left'):
        swapped(right, left, 'rectified')
    left.width = 640
    with pytest.raises(CalibrationError, match='sizes differ'):
        swapped(left, right, 'rectified')


def test_camera_info_key_changes_with_the_geometry_only():
    left, _, P0 = _kitti_infos()
    other, _, _ = _kitti_infos()
    other.header.stamp = conv.time_from_nanoseconds(5)
    assert conv.camera_info_key(left) == conv.camera_info_key(other)
    other.p = (P0 * 1.01).ravel().tolist()
    assert conv.camera_info_key(left) != conv.camera_info_key(other)


def test_default_base_from_camera_is_the_optical_to_body_rotation():
    T = conv.transform_from_xyz_rpy([0.1, 0.2, 0.3], [-90.0, 0.0, -90.0])
    np.testing.assert_allclose(T[:3, :3], R_BASE_OPTICAL, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])


def _result(T_world_cam, cov=None, velocity=None, vcov=None, status=TrackingStatus.OK):
    return OdometryResult(
        stamp_s=1.5, T_world_cam=T_world_cam,
        pose_covariance=np.zeros((6, 6)) if cov is None else cov,
        velocity=np.zeros(6) if velocity is None else velocity,
        velocity_covariance=np.eye(6) * 1e-4 if vcov is None else vcov, status=status)


def _camera_pose(yaw_left_rad, forward_m):
    """Camera that drove ``forward_m`` along its optical z and turned left by ``yaw``."""
    T = np.eye(4)
    # Turning left is a rotation about the body z (up), i.e. about the optical -y axis.
    T[:3, :3] = Rotation.from_rotvec([0.0, -yaw_left_rad, 0.0]).as_matrix()
    T[:3, 3] = [0.0, 0.0, forward_m]
    return T


def test_odometry_message_is_in_rep103_body_frames():
    T_base_cam = conv.transform_from_xyz_rpy([0, 0, 0], [-90, 0, -90])
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 2e-6, 3e-6])  # optical x, y, z, rx, ry, rz
    velocity = np.array([0.0, 0.0, 2.0, 0.0, -0.3, 0.0])  # forward 2 m/s, turning left
    vcov = np.diag([1e-2, 2e-2, 3e-2, 1e-3, 2e-3, 3e-3])
    res = _result(_camera_pose(0.0, 5.0), cov, velocity, vcov)
    odom = conv.base_odometry_from_result(res, T_base_cam)
    stamp = conv.time_from_nanoseconds(1_500_000_000)
    msg = conv.odometry_msg(odom, stamp, 'odom', 'base_link')
    assert (msg.header.frame_id, msg.child_frame_id) == ('odom', 'base_link')
    assert conv.nanoseconds_from_time(msg.header.stamp) == 1_500_000_000
    p = msg.pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], [5.0, 0.0, 0.0], atol=1e-12)
    q = msg.pose.pose.orientation
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [0, 0, 0, 1], atol=1e-12)
    pose_cov = np.array(msg.pose.covariance).reshape(6, 6)
    # ROS order (x, y, z, rx, ry, rz) in the body axes: body x = optical z, y = -optical x,
    # z = -optical y for the rotations ...
    np.testing.assert_allclose(np.diag(pose_cov)[3:], [3e-6, 1e-6, 2e-6], rtol=1e-9)
    # ... except through the lever arm of the position (5 m along x): y picks up 25 * var(rz).
    np.testing.assert_allclose(np.diag(pose_cov)[:3], [3e-4, 1e-4 + 25 * 2e-6, 2e-4 + 25 * 1e-6],
                               rtol=1e-9)
    tw = msg.twist.twist
    np.testing.assert_allclose([tw.linear.x, tw.linear.y, tw.linear.z], [2, 0, 0], atol=1e-12)
    np.testing.assert_allclose([tw.angular.x, tw.angular.y, tw.angular.z], [0, 0, 0.3],
                               atol=1e-12)
    twist_cov = np.array(msg.twist.covariance).reshape(6, 6)
    np.testing.assert_allclose(np.diag(twist_cov), [3e-2, 1e-2, 2e-2, 3e-3, 1e-3, 2e-3])
    assert np.all(np.isfinite(pose_cov)) and np.all(np.isfinite(twist_cov))
    assert np.all(np.linalg.eigvalsh(pose_cov) > 0)


def test_base_pose_is_the_conjugated_camera_pose_with_a_lever_arm():
    # Camera 1.2 m ahead of and 0.3 m above the body origin.
    T_base_cam = conv.transform_from_xyz_rpy([1.2, 0.0, 0.3], [-90, 0, -90])
    yaw = 0.5
    res = _result(_camera_pose(yaw, 10.0))
    odom = conv.base_odometry_from_result(res, T_base_cam)
    expected = T_base_cam @ res.T_world_cam @ np.linalg.inv(T_base_cam)
    np.testing.assert_allclose(odom.T_odom_base, expected, atol=1e-12)
    # The body turned left by yaw about its own z axis; odom is the body at the start.
    np.testing.assert_allclose(odom.T_odom_base[:3, :3],
                               Rotation.from_euler('z', yaw).as_matrix(), atol=1e-12)
    assert odom.T_odom_base[2, 3] == pytest.approx(0.0, abs=1e-12)


def _se3_exp(xi):
    """Vectorised SE(3) exponential of (N, 6) twists (rho, phi) -> (N, 4, 4)."""
    rho, phi = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(phi, axis=1)[:, None, None]
    W = np.zeros((len(xi), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    W[:, 1, 0], W[:, 2, 0], W[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    W2 = W @ W
    V = np.eye(3) + (1 - np.cos(theta)) / theta ** 2 * W + (theta - np.sin(theta)) / \
        theta ** 3 * W2
    T = np.tile(np.eye(4), (len(xi), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(phi).as_matrix()
    T[:, :3, 3] = (V @ rho[:, :, None])[:, :, 0]
    return T


def test_pose_covariance_matches_monte_carlo_in_ros_convention():
    T_base_cam = conv.transform_from_xyz_rpy([0.5, -0.2, 1.0], [-90, 5, -80])
    T_wc = _camera_pose(0.7, 8.0)
    T_wc[:3, 3] += [1.0, -0.5, 0.0]
    A = RNG.normal(size=(6, 6)) * np.array([0.05] * 3 + [0.01] * 3)[:, None]
    cov = A @ A.T
    odom = conv.base_odometry_from_result(_result(T_wc, cov), T_base_cam)
    xi = RNG.multivariate_normal(np.zeros(6), cov, size=40000)
    samples = T_base_cam @ _se3_exp(xi) @ T_wc @ np.linalg.inv(T_base_cam)
    dp = samples[:, :3, 3] - odom.T_odom_base[:3, 3]
    dtheta = Rotation.from_matrix(samples[:, :3, :3] @ odom.T_odom_base[:3, :3].T).as_rotvec()
    empirical = np.cov(np.hstack([dp, dtheta]).T)
    scale = np.sqrt(np.outer(np.diag(empirical), np.diag(empirical)))
    np.testing.assert_allclose(odom.pose_covariance / scale, empirical / scale, atol=0.03)


def test_camera_pose_from_base_pose_inverts_the_conversion():
    T_base_cam = conv.transform_from_xyz_rpy([0.3, 0.1, 1.1], [-92, 1, -88])
    T_wc = _camera_pose(-0.4, 3.0)
    A = RNG.normal(size=(6, 6)) * 0.01
    cov = A @ A.T + np.eye(6) * 1e-6
    odom = conv.base_odometry_from_result(_result(T_wc, cov), T_base_cam)
    T_back, cov_back = conv.camera_pose_from_base_pose(odom.T_odom_base, odom.pose_covariance,
                                                       T_base_cam)
    np.testing.assert_allclose(T_back, T_wc, atol=1e-12)
    np.testing.assert_allclose(cov_back, cov, atol=1e-12)


def test_lost_status_gives_large_finite_covariance_and_zero_cov_is_made_definite():
    T_base_cam = conv.transform_from_xyz_rpy([0, 0, 0], [-90, 0, -90])
    first = conv.base_odometry_from_result(_result(np.eye(4)), T_base_cam)
    assert np.all(np.linalg.eigvalsh(first.pose_covariance) >= conv.MIN_VARIANCE * 0.999)
    lost = conv.base_odometry_from_result(_result(np.eye(4), status=TrackingStatus.LOST),
                                          T_base_cam)
    assert lost.is_finite()
    assert np.all(np.diag(lost.pose_covariance) >= conv.LOST_VARIANCE * 0.999)
    assert np.all(np.diag(lost.twist_covariance) >= conv.LOST_VARIANCE * 0.999)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    assert not conv.base_odometry_from_result(_result(bad), T_base_cam).is_finite()


def test_path_pose_and_transform_messages():
    T = conv.transform_from_xyz_rpy([1, 2, 3], [0, 0, 90])
    stamp = conv.time_from_nanoseconds(42)
    pose = conv.pose_stamped_msg(T, stamp, 'odom')
    assert pose.header.frame_id == 'odom'
    np.testing.assert_allclose(
        conv.transform_from_pose(pose.pose.position, pose.pose.orientation), T, atol=1e-12)
    tf = conv.transform_msg(T, stamp, 'odom', 'base_link')
    assert (tf.header.frame_id, tf.child_frame_id) == ('odom', 'base_link')
    np.testing.assert_allclose(
        conv.transform_from_pose(tf.transform.translation, tf.transform.rotation), T,
        atol=1e-12)


def test_diagnostic_status_values():
    status = conv.diagnostic_status(DiagnosticStatus.WARN, 'vo', 'lost', {'inliers': 3,
                                    'processing_ms': 12.3456789}, 'cam')
    assert status.level == DiagnosticStatus.WARN
    assert {kv.key: kv.value for kv in status.values} == {'inliers': '3',
                                                          'processing_ms': '12.3457'}


def test_processing_time_adds_the_work_after_the_pose():
    res = OdometryResult(0.0, np.eye(4), np.zeros((6, 6)), np.zeros(6), np.zeros((6, 6)),
                         TrackingStatus.OK, timings_ms={'total': 10.0})
    assert processing_ms(res) == 10.0
    res.timings_ms['after_pose'] = 0.75  # the pipeline's settle() ran
    assert processing_ms(res) == 10.75
    assert np.isnan(processing_ms(OdometryResult(0.0, np.eye(4), np.zeros((6, 6)), np.zeros(6),
                                                 np.zeros((6, 6)), TrackingStatus.OK)))


def test_debug_image_draws_inliers_green_and_outliers_red():
    left = np.full((40, 60), 100, np.uint8)
    cur = np.array([[10.0, 10.0], [40.0, 30.0]])
    feats = Correspondences(cur - 2, cur - 2, cur, cur)
    img = conv.debug_image(left, feats, np.array([True, False]))
    assert img.shape == (40, 60, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[10, 10], [0, 255, 0])
    np.testing.assert_array_equal(img[30, 40], [0, 0, 255])
    np.testing.assert_array_equal(img[0, 59], [100, 100, 100])
    plain = conv.debug_image(np.full((5, 5), 4000, np.uint16), None, None)
    assert plain.dtype == np.uint8 and plain.max() == 255
