"""The one typed configuration: loading, validation, and the shipped YAML."""

from pathlib import Path

import pytest

from stereo_vo_ros import config as config_mod
from stereo_vo_ros.config import Config, ConfigError, from_dict, from_flat, load, to_yaml

REPO = Path(__file__).resolve().parents[1]


def test_shipped_yaml_is_the_defaults_and_documents_every_field():
    path = REPO / 'config' / 'stereo_vo.yaml'
    assert load(path) == Config()
    assert path.read_text() == config_mod.HEADER + to_yaml(), (
        'config/stereo_vo.yaml is stale: regenerate with '
        '`python -m stereo_vo_ros.config > config/stereo_vo.yaml`')
    for name, _, f in Config().items():
        assert f.metadata['doc'], f'{name} has no documentation'


def test_yaml_round_trip_with_overrides(tmp_path):
    cfg = Config().replace(**{'filter.type': 'iekf', 'tracker.max_features': 300,
                              'ros.base_from_camera_xyz': [0.1, 0.2, 0.3]})
    path = tmp_path / 'c.yaml'
    path.write_text(to_yaml(cfg, node='stereo_vo_node'))
    assert load(path) == cfg
    # Plain nested form (no ros__parameters) is accepted too.
    path.write_text('filter:\n  type: ukf\n')
    assert load(path).filter.type == 'ukf'


@pytest.mark.parametrize('data, match', [
    ({'filtr': {'type': 'ekf'}}, "unknown configuration section 'filtr'"),
    ({'filter': {'typ': 'ekf'}}, 'unknown parameter filter.typ'),
    ({'filter': {'type': 'kalman'}}, 'filter.type must be one of'),
    ({'tracker': {'max_features': 2}}, r'tracker.max_features must be within \[8, 5000\], got 2'),
    ({'tracker': {'max_features': 'many'}}, 'tracker.max_features must be an integer'),
    ({'ransac': {'enabled': 'yes'}}, 'ransac.enabled must be true or false'),
    ({'tracker': {'win_size_px': 20}}, 'must be odd'),
    ({'filter': {'pixel_noise_px': float('nan')}}, 'filter.pixel_noise_px must be within'),
    ({'ros': {'base_from_camera_xyz': [1, 2]}}, 'list of 3 numbers'),
])
def test_invalid_values_are_rejected_with_the_name(data, match):
    with pytest.raises(ConfigError, match=match):
        from_dict(data)


def test_flat_names_as_ros_parameters():
    cfg = from_flat({'filter.type': 'ekf', 'ransac.inlier_threshold_px': 1.5})
    assert cfg.filter.type == 'ekf' and cfg.ransac.inlier_threshold_px == 1.5
    with pytest.raises(ConfigError, match='no section'):
        from_flat({'type': 'ekf'})
    names = [name for name, _, _ in Config().items()]
    assert len(names) == len(set(names)) and 'pipeline.max_lost_time_s' in names


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match='cannot read configuration file'):
        load(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('filter: [1, 2\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load(bad)


def test_command_line_overrides():
    items = ['road.enabled=true', 'ransac.ground_weight=8', 'filter.type=ekf',
             'ros.odom_frame="map"']
    overrides = config_mod.overrides_from_items(items)
    assert overrides == {'road.enabled': True, 'ransac.ground_weight': 8,
                         'filter.type': 'ekf', 'ros.odom_frame': 'map'}
    cfg = Config().replace(**overrides)
    assert cfg.road.enabled and cfg.ransac.ground_weight == 8.0 and cfg.filter.type == 'ekf'
    with pytest.raises(ConfigError, match="'road.enabled'"):
        config_mod.overrides_from_items(['road.enabled'])
    with pytest.raises(ConfigError, match='unknown parameter'):
        Config().replace(**config_mod.overrides_from_items(['road.bogus=1']))


def test_road_vehicle_overlay_turns_on_the_road_parts_only():
    """config/road_vehicle.yaml: the road alignment and the vehicle's motion, the rest default."""
    cfg = load(REPO / 'config' / 'road_vehicle.yaml')
    assert cfg.road.enabled and cfg.vehicle.nonholonomic and cfg.vehicle.acceleration_std == 5.0
    changed = {name for (name, value, _), (_, default, _) in zip(cfg.items(), Config().items())
               if value != default}
    assert changed == {'road.enabled', 'vehicle.nonholonomic', 'vehicle.acceleration_std'}


def test_yaml_comments_are_wrapped():
    """Every comment of the generated and the shipped YAML fits in 120 columns."""
    for text in (to_yaml(), (REPO / 'config' / 'stereo_vo.yaml').read_text()):
        too_long = [line for line in text.splitlines() if len(line) > 120]
        assert not too_long, f'{len(too_long)} lines longer than 120 characters: {too_long[:3]}'
    comments = [line for line in to_yaml().splitlines() if line.lstrip().startswith('#')]
    assert max(map(len, comments)) <= config_mod.YAML_COMMENT_WIDTH


def test_public_api_imports_from_the_package():
    """``from stereo_vo_ros import Config, StereoOdometry`` is the documented entry point."""
    from stereo_vo_ros import Config as PublicConfig, StereoOdometry, TrackingStatus
    odometry = StereoOdometry(PublicConfig())
    assert PublicConfig is Config
    assert odometry.status is TrackingStatus.INITIALIZING
    assert odometry.T_world_cam.tolist() == [[float(i == j) for j in range(4)] for i in range(4)]
