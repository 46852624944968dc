"""
Tests of the dataset readers and writers: KITTI folders and rosbag2 stereo bags.

Real KITTI data is used when the shared clips are present (skipped otherwise); everything
else runs on small rendered sequences.
"""

from itertools import islice
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import get_typestore, Stores

from stereo_vo_ros.config import Config
from stereo_vo_ros.errors import DatasetError, ImageError
from stereo_vo_ros.io import (BagTopics, detect_format, KittiSequence, open_sequence,
                              render_to_bag, render_to_kitti, RosbagSequence,
                              SyntheticSequence, write_kitti, write_stereo_bag)
from stereo_vo_ros.io.rosbag import buffer_from_grey, ENCODINGS, grey_from_buffer
from stereo_vo_ros.records import StereoFrame
from stereo_vo_ros.synthetic import SequenceSpec, StereoRenderer

KITTI06 = 'kitti06_f0000-0050'


@pytest.fixture(scope='module')
def rendered() -> StereoRenderer:
    """Return a tiny rendered sequence (noise on, so images are not trivially smooth)."""
    return StereoRenderer(SequenceSpec.preset('demo', width=320, height=96, n_frames=6))


@pytest.fixture(scope='module')
def rendered_frames(rendered: StereoRenderer) -> list[StereoFrame]:
    """Return the rendered pairs as StereoFrames."""
    return list(rendered.frames())


def assert_same_frames(got: list[StereoFrame], expected: list[StereoFrame]) -> None:
    """Assert equal pixels and stamps, frame by frame."""
    assert len(got) == len(expected)
    for g, e in zip(got, expected):
        np.testing.assert_array_equal(g.left, e.left)
        np.testing.assert_array_equal(g.right, e.right)
        assert g.stamp_s == pytest.approx(e.stamp_s, abs=1e-9)


# -- KITTI -------------------------------------------------------------------------------------
def test_kitti_reads_the_real_clip(shared_data: Path) -> None:
    """The KITTI 06 clip gives 51 pairs, its calibration, stamps and poses."""
    seq = KittiSequence(shared_data / KITTI06)
    assert len(seq) == 51
    calib = seq.calibration
    assert calib.size == (1226, 370)
    assert calib.K_left[0, 0] == pytest.approx(707.0912)
    assert calib.baseline_m == pytest.approx(379.8145 / 707.0912)
    assert seq.stamps[1] == pytest.approx(0.1044989)
    gt = seq.ground_truth
    assert gt.shape == (51, 4, 4)
    np.testing.assert_allclose(gt[0], np.eye(4), atol=1e-6)
    assert gt[-1, 2, 3] > 50.0  # about 60 m forward
    frame = seq[0]
    assert frame.left.dtype == np.uint8 and frame.left.shape == (370, 1226)
    assert frame.right.shape == (370, 1226)
    assert frame.calibration is calib


def test_kitti_round_trip_of_the_real_clip(shared_data: Path, tmp_path: Path) -> None:
    """Writing and reading back keeps pixels, stamps, poses and calibration exactly."""
    seq = KittiSequence(shared_data / KITTI06)
    frames = list(islice(seq, 4))
    assert write_kitti(tmp_path / 'k', frames, seq.ground_truth[:4]) == 4
    back = KittiSequence(tmp_path / 'k')
    assert_same_frames(list(back), frames)
    np.testing.assert_array_equal(back.stamps, seq.stamps[:4])
    np.testing.assert_array_equal(back.ground_truth, seq.ground_truth[:4])
    assert back.calibration.same_as(seq.calibration)


def test_kitti_round_trip_of_a_rendered_sequence(rendered: StereoRenderer,
                                                 rendered_frames: list[StereoFrame],
                                                 tmp_path: Path) -> None:
    """A rendered sequence survives the KITTI layout bit for bit, ground truth included."""
    path = render_to_kitti(rendered.spec, tmp_path / 'synthetic')
    back = open_sequence(path)
    assert isinstance(back, KittiSequence)
    assert_same_frames(list(back), rendered_frames)
    np.testing.assert_array_equal(back.stamps, rendered.stamps)
    np.testing.assert_array_equal(back.ground_truth, rendered.poses)
    assert back.calibration.same_as(rendered.calibration)


def test_kitti_writer_keeps_full_precision(rendered_frames: list[StereoFrame],
                                           tmp_path: Path) -> None:
    """Stamps and poses are written with repr precision, not rounded."""
    frames = [StereoFrame(f.left, f.right, 1e9 + 0.1 + i / 3.0, f.calibration)
              for i, f in enumerate(rendered_frames[:2])]
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, :3, 3] = [1.0 / 3.0, -2.0e-17, 123456.789012345678]
    write_kitti(tmp_path / 'k', frames, poses)
    back = KittiSequence(tmp_path / 'k')
    np.testing.assert_array_equal(back.stamps, [f.stamp_s for f in frames])
    np.testing.assert_array_equal(back.ground_truth, poses)
    assert '0.3333333333333333' in (tmp_path / 'k' / 'poses.txt').read_text()


def test_kitti_reader_and_writer_errors(rendered_frames: list[StereoFrame],
                                        tmp_path: Path) -> None:
    """Missing folders, files and inconsistent counts raise DatasetError naming them."""
    with pytest.raises(DatasetError, match='does not exist'):
        KittiSequence(tmp_path / 'nowhere')
    path = tmp_path / 'k'
    write_kitti(path, rendered_frames[:3])
    assert KittiSequence(path).ground_truth is None
    with pytest.raises(DatasetError, match='already holds'):
        write_kitti(path, rendered_frames[:3])
    (path / 'times.txt').write_text('0.0\n0.1\n')
    with pytest.raises(DatasetError, match='2 stamps for 3 images'):
        KittiSequence(path)
    (path / 'times.txt').unlink()
    assert KittiSequence(path).stamps[2] == pytest.approx(0.2)  # 10 Hz default
    calib = (path / 'calib.txt').read_text().splitlines()
    (path / 'calib.txt').write_text(calib[0] + '\n')
    with pytest.raises(DatasetError, match='P1'):
        KittiSequence(path)
    (path / 'calib.txt').write_text('\n'.join(calib) + '\n')
    (path / 'image_1' / '000002.png').unlink()
    with pytest.raises(DatasetError, match='000002.png'):
        KittiSequence(path)
    with pytest.raises(DatasetError, match='image_1'):
        (path / 'image_1' / '000000.png').unlink()
        (path / 'image_1' / '000001.png').unlink()
        (path / 'image_1').rmdir()
        KittiSequence(path)


# -- rosbag2 -----------------------------------------------------------------------------------
@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_bag_round_trip(storage: str, rendered: StereoRenderer,
                        rendered_frames: list[StereoFrame], tmp_path: Path) -> None:
    """Images, stamps, calibration and ground truth come back from a written bag."""
    path = tmp_path / 'bag'
    count = write_stereo_bag(path, rendered_frames, rendered.calibration, rendered.poses,
                             storage=storage)
    assert count == len(rendered_frames)
    seq = RosbagSequence(path)
    assert len(seq) == len(rendered_frames)
    assert_same_frames(list(seq), rendered_frames)
    np.testing.assert_allclose(seq.stamps, rendered.stamps, atol=1e-9)
    assert seq.calibration.same_as(rendered.calibration)
    np.testing.assert_allclose(seq.ground_truth, rendered.poses, atol=1e-12)
    single = next(path.glob('*.mcap' if storage == 'mcap' else '*.db3'))
    assert len(open_sequence(single)) == len(rendered_frames)


@pytest.mark.parametrize('encoding', sorted(ENCODINGS))
def test_bag_encodings_with_padded_rows(encoding: str, rendered_frames: list[StereoFrame],
                                        tmp_path: Path) -> None:
    """Every supported encoding round-trips to grey, with row padding in ``step``."""
    frames = rendered_frames[:2]
    write_stereo_bag(tmp_path / 'bag', frames, encoding=encoding, row_padding=7,
                     storage='mcap')
    back = list(RosbagSequence(tmp_path / 'bag'))
    for got, sent in zip(back, frames):
        if ENCODINGS[encoding][0] is np.uint16:
            assert got.left.dtype == np.uint16
            np.testing.assert_array_equal(got.left, sent.left.astype(np.uint16) * 257)
        else:
            np.testing.assert_array_equal(got.left, sent.left)
            np.testing.assert_array_equal(got.right, sent.right)


def test_grey_from_buffer_honours_step_and_byte_order() -> None:
    """Row padding is skipped, big-endian mono16 is swapped, bad fields raise ImageError."""
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    data, step = buffer_from_grey(img, 'bgr8', row_padding=5)
    assert step == 4 * 3 + 5
    np.testing.assert_array_equal(grey_from_buffer('bgr8', 4, 3, step, data), img)
    wide = np.array([[1, 2], [3, 65535]], np.uint16)
    big = np.zeros((2, 6), np.uint8)  # step 6: 4 bytes of pixels + 2 of padding per row
    big[:, :4] = wide.astype('>u2').view(np.uint8).reshape(2, 4)
    np.testing.assert_array_equal(grey_from_buffer('mono16', 2, 2, 6, big.tobytes(), True), wide)
    with pytest.raises(ImageError, match='step 3'):
        grey_from_buffer('mono8', 4, 3, 3, bytes(12))
    with pytest.raises(ImageError, match='11 bytes'):
        grey_from_buffer('mono8', 4, 3, 4, bytes(11))
    with pytest.raises(ImageError, match='yuv422'):
        grey_from_buffer('yuv422', 4, 3, 8, bytes(24))


def test_bag_without_the_expected_topics(rendered_frames: list[StereoFrame],
                                         tmp_path: Path) -> None:
    """A bag lacking the topics raises DatasetError naming the topics it has."""
    topics = BagTopics(left_image='/cam0/image', right_image='/cam1/image',
                       left_info='/cam0/info', right_info='/cam1/info')
    write_stereo_bag(tmp_path / 'bag', rendered_frames[:2], topics=topics)
    with pytest.raises(DatasetError, match=r'lacks topic.*/left/image_rect.*/cam0/image'):
        RosbagSequence(tmp_path / 'bag')
    seq = RosbagSequence(tmp_path / 'bag', topics)
    assert len(seq) == 2 and seq.ground_truth is None
    cfg = Config().replace(**{'ros.left_image_topic': '/cam0/image',
                              'ros.right_image_topic': '/cam1/image',
                              'ros.left_info_topic': '/cam0/info',
                              'ros.right_info_topic': '/cam1/info'})
    assert len(open_sequence(tmp_path / 'bag', cfg)) == 2


@pytest.mark.parametrize('received', ['in order', 'reversed'])
def test_bag_pairs_images_with_equal_stamps_only(received: str,
                                                 rendered_frames: list[StereoFrame],
                                                 tmp_path: Path) -> None:
    """Images pair by equal header stamps, lone ones are skipped; pairs come in stamp order."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    calib = rendered_frames[0].calibration
    topics = BagTopics()
    left_ns = [0, 100_000_000, 200_000_000, 300_000_000]
    right_ns = [0, 100_000_000, 250_000_000, 300_000_000]
    with Writer(tmp_path / 'bag', version=9) as writer:
        conn = {name: writer.add_connection(topic, kind, typestore=ts) for name, topic, kind in (
            ('l', topics.left_image, 'sensor_msgs/msg/Image'),
            ('r', topics.right_image, 'sensor_msgs/msg/Image'),
            ('lc', topics.left_info, 'sensor_msgs/msg/CameraInfo'),
            ('rc', topics.right_info, 'sensor_msgs/msg/CameraInfo'))}
        for side, stamps, cam in (('l', left_ns, calib.left), ('r', right_ns, calib.right)):
            for i, ns in enumerate(stamps):
                header = T['std_msgs/msg/Header'](
                    stamp=T['builtin_interfaces/msg/Time'](sec=0, nanosec=ns), frame_id='cam')
                img = rendered_frames[i].left
                data, step = buffer_from_grey(img, 'mono8')
                msg = T['sensor_msgs/msg/Image'](header=header, height=img.shape[0],
                                                 width=img.shape[1], encoding='mono8',
                                                 is_bigendian=0, step=step, data=data)
                at = ns if received == 'in order' else 1_000_000_000 - ns  # bag receive time
                writer.write(conn[side], at, ts.serialize_cdr(msg, 'sensor_msgs/msg/Image'))
                info = T['sensor_msgs/msg/CameraInfo'](
                    header=header, height=cam.height, width=cam.width,
                    distortion_model='plumb_bob', d=np.zeros(5), k=cam.K.ravel(),
                    r=cam.R.ravel(), p=cam.P.ravel(), binning_x=0, binning_y=0,
                    roi=T['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0,
                                                              width=0, do_rectify=False))
                writer.write(conn[side + 'c'], at,
                             ts.serialize_cdr(info, 'sensor_msgs/msg/CameraInfo'))
    seq = RosbagSequence(tmp_path / 'bag')
    np.testing.assert_allclose(seq.stamps, [0.0, 0.1, 0.3])
    frames = list(seq)
    assert [f.stamp_s for f in frames] == pytest.approx([0.0, 0.1, 0.3])
    np.testing.assert_array_equal(frames[2].left, rendered_frames[3].left)


# -- choosing the format -------------------------------------------------------------------------
def test_open_sequence_chooses_the_format(rendered: StereoRenderer,
                                          rendered_frames: list[StereoFrame],
                                          tmp_path: Path) -> None:
    """KITTI folders, bag folders and files, and synthetic presets open with the right class."""
    write_kitti(tmp_path / 'kitti', rendered_frames)
    render_to_bag(rendered.spec, tmp_path / 'bag_sqlite')
    render_to_bag(rendered.spec, tmp_path / 'bag_mcap', storage='mcap')
    assert detect_format(tmp_path / 'kitti') == 'kitti'
    assert detect_format(tmp_path / 'bag_sqlite') == 'rosbag'
    assert detect_format(next((tmp_path / 'bag_mcap').glob('*.mcap'))) == 'rosbag'
    assert isinstance(open_sequence(tmp_path / 'kitti'), KittiSequence)
    assert isinstance(open_sequence(tmp_path / 'bag_sqlite'), RosbagSequence)
    (tmp_path / 'bag_mcap' / 'metadata.yaml').unlink()  # a folder with one .mcap file
    bare = open_sequence(tmp_path / 'bag_mcap')
    assert_same_frames(list(bare), rendered_frames)
    np.testing.assert_allclose(bare.ground_truth, rendered.poses, atol=1e-12)
    synthetic = open_sequence('synthetic:demo')
    assert isinstance(synthetic, SyntheticSequence) and len(synthetic) == 60


def test_open_sequence_errors(tmp_path: Path) -> None:
    """A missing path, an unknown folder or format raises DatasetError naming it."""
    with pytest.raises(DatasetError, match='does not exist'):
        open_sequence(tmp_path / 'missing')
    (tmp_path / 'empty').mkdir()
    with pytest.raises(DatasetError, match='neither a KITTI folder'):
        open_sequence(tmp_path / 'empty')
    (tmp_path / 'notes.txt').write_text('x')
    with pytest.raises(DatasetError, match='not a .db3 or .mcap'):
        open_sequence(tmp_path / 'notes.txt')
    with pytest.raises(DatasetError, match='unknown sequence format'):
        open_sequence(tmp_path / 'empty', fmt='tum')
    (tmp_path / 'broken.db3').write_bytes(b'not a database')
    with pytest.raises(DatasetError, match='broken.db3'):
        open_sequence(tmp_path / 'broken.db3')
