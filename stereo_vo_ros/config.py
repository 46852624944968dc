"""
One typed configuration for every part of the pipeline, online and offline.

The configuration is a tree of dataclasses (one section per component). It is loaded from a
YAML file in the ROS 2 parameter form::

    /**:
      ros__parameters:
        tracker:
          max_features: 200

so the very same file serves ``ros2 run ... --params-file`` and ``stereo_vo run --config``.
Each field carries its documentation, its unit and its valid range in the dataclass field
metadata; the ROS node declares its parameters (with descriptors) from the same metadata and the
YAML in ``config/stereo_vo.yaml`` is checked against it by a test, so the schema lives in one
place only. Unknown or misspelt keys are rejected, never ignored.

This module holds the root ``Config``, its loading (YAML file, nested dict, dotted ROS names,
``--set`` overrides), its validation and the writer of the commented YAML
(``python -m stereo_vo_ros.config``). The sections themselves, with the documentation, range
and choices of every parameter, are in ``config_sections.py``; they are re-exported here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import json
from pathlib import Path
import textwrap
from typing import Any, Iterator

import yaml

from .config_sections import (  # noqa: F401 (re-exported)
    BucketingConfig, FilterConfig, PipelineConfig, RansacConfig, RigConfig, RoadConfig,
    RosConfig, TRACKER_VARIANTS, TrackerConfig, VehicleConfig)
from .errors import ConfigError


@dataclass
class Config:
    """The whole configuration: one section per component."""

    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    bucketing: BucketingConfig = field(default_factory=BucketingConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)  # noqa: A003
    ransac: RansacConfig = field(default_factory=RansacConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    road: RoadConfig = field(default_factory=RoadConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    ros: RosConfig = field(default_factory=RosConfig)

    def __post_init__(self) -> None:
        validate(self)

    # -- flat views ---------------------------------------------------------------------
    def items(self) -> Iterator[tuple[str, Any, dataclasses.Field]]:
        """Yield ``(dotted_name, value, field)`` for every leaf parameter."""
        for sec in dataclasses.fields(self):
            section = getattr(self, sec.name)
            for f in dataclasses.fields(section):
                yield f'{sec.name}.{f.name}', getattr(section, f.name), f

    def as_dict(self) -> dict[str, dict[str, Any]]:
        """Return the nested plain-dict form (what the YAML holds under ros__parameters)."""
        return dataclasses.asdict(self)

    def replace(self, **dotted: Any) -> 'Config':
        """Return a copy with dotted overrides such as ``{'filter.type': 'ekf'}``."""
        data = self.as_dict()
        for key, value in dotted.items():
            sec, _, name = key.partition('.')
            if sec not in data or name not in data[sec]:
                raise ConfigError(f'unknown parameter {key!r}')
            data[sec][name] = value
        return from_dict(data)


SECTIONS = {f.name: f.default_factory for f in dataclasses.fields(Config)}


def _coerce(name: str, value: Any, f: dataclasses.Field) -> Any:
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    kind = type(default)
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f'{name} must be true or false, got {value!r}')
        return value
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f'{name} must be an integer, got {value!r}')
        return value
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f'{name} must be a number, got {value!r}')
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f'{name} must be a string, got {value!r}')
        return value
    if kind is list:
        if not isinstance(value, (list, tuple)) or len(value) != len(default):
            raise ConfigError(f'{name} must be a list of {len(default)} numbers, got {value!r}')
        try:
            return [float(v) for v in value]
        except (TypeError, ValueError):
            raise ConfigError(f'{name} must be a list of numbers, got {value!r}') from None
    return value  # pragma: no cover


def validate(cfg: Config) -> None:
    """Check every value against its type, range and choices; raise ConfigError if not."""
    for name, value, f in cfg.items():
        meta = f.metadata
        if meta.get('choices') and value not in meta['choices']:
            raise ConfigError(f'{name} must be one of {list(meta["choices"])}, got {value!r}')
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            lo, hi = meta.get('lo'), meta.get('hi')
            if value != value or (lo is not None and value < lo) or (
                    hi is not None and value > hi):
                raise ConfigError(f'{name} must be within [{lo}, {hi}], got {value!r}')
    if cfg.tracker.win_size_px % 2 == 0:
        raise ConfigError(f'tracker.win_size_px must be odd, got {cfg.tracker.win_size_px}')
    if cfg.tracker.min_disparity_px >= cfg.tracker.max_disparity_px:
        raise ConfigError('tracker.min_disparity_px must be below tracker.max_disparity_px')
    if cfg.road.min_depth_m >= cfg.road.max_depth_m:
        raise ConfigError('road.min_depth_m must be below road.max_depth_m')


def from_dict(data: dict[str, Any] | None) -> Config:
    """Build a Config from the nested dict form; unknown keys raise ConfigError."""
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError(f'configuration must be a mapping, got {type(data).__name__}')
    sections = {}
    for sec_name, raw in data.items():
        if sec_name not in SECTIONS:
            raise ConfigError(f'unknown configuration section {sec_name!r}; known: '
                              f'{sorted(SECTIONS)}')
        if not isinstance(raw, dict):
            raise ConfigError(f'section {sec_name!r} must be a mapping, got {raw!r}')
        cls_fields = {f.name: f for f in dataclasses.fields(SECTIONS[sec_name]())}
        values = {}
        for key, value in raw.items():
            if key not in cls_fields:
                raise ConfigError(f'unknown parameter {sec_name}.{key}; known: '
                                  f'{sorted(cls_fields)}')
            values[key] = _coerce(f'{sec_name}.{key}', value, cls_fields[key])
        sections[sec_name] = SECTIONS[sec_name]().__class__(**values)
    return Config(**sections)


def from_flat(params: dict[str, Any]) -> Config:
    """Build a Config from dotted names (``{'filter.type': 'ekf'}``), as ROS parameters are."""
    nested: dict[str, dict[str, Any]] = {}
    for key, value in params.items():
        sec, dot, name = key.partition('.')
        if not dot:
            raise ConfigError(f'parameter {key!r} has no section (expected section.name)')
        nested.setdefault(sec, {})[name] = value
    return from_dict(nested)


def overrides_from_items(items: list[str]) -> dict[str, Any]:
    """
    Parse ``section.key=value`` items (command-line ``--set``) into dotted overrides.

    Values are read as JSON (``true``, ``4``, ``"x"``), else kept as strings; pass the result to
    :meth:`Config.replace`, which rejects unknown keys. Raises ConfigError for an item without
    ``=``.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition('=')
        if not sep:
            raise ConfigError(f'override {item!r}: expected section.key=value')
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def load(path: str | Path | None = None) -> Config:
    """
    Load a Config from a YAML file (ROS 2 params form or plain nested form).

    ``None`` gives the defaults. Accepts ``{node_name or '/**': {'ros__parameters': {...}}}``
    (the first node entry is used) or the plain nested sections.
    """
    if path is None:
        return Config()
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f'cannot read configuration file {str(path)!r}: {exc.strerror}') \
            from None
    try:
        doc = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f'configuration file {str(path)!r} is not valid YAML: {exc}') from None
    if not isinstance(doc, dict):
        raise ConfigError(f'configuration file {str(path)!r} must hold a mapping')
    for value in doc.values():
        if isinstance(value, dict) and 'ros__parameters' in value:
            doc = value['ros__parameters'] or {}
            break
    return from_dict(doc)


#: Longest comment line of the generated YAML (characters, indentation and ``#`` included).
YAML_COMMENT_WIDTH = 100


def to_yaml(cfg: Config | None = None, node: str = '/**') -> str:
    """Render a Config as a commented ROS 2 parameter file (comments wrapped at 100 columns)."""
    cfg = cfg or Config()
    lines = [f'{node}:', '  ros__parameters:']
    for sec in dataclasses.fields(cfg):
        section = getattr(cfg, sec.name)
        lines.append(f'    # {type(section).__doc__.strip().splitlines()[0]}')
        lines.append(f'    {sec.name}:')
        for f in dataclasses.fields(section):
            meta = f.metadata
            note = meta['doc']
            if meta.get('lo') is not None:
                note += f' Range [{meta["lo"]}, {meta["hi"]}].'
            if meta.get('dynamic'):
                note += ' Settable at run time.'
            lines.extend(textwrap.wrap(note, width=YAML_COMMENT_WIDTH,
                                       initial_indent='      # ', subsequent_indent='      # ',
                                       break_long_words=False, break_on_hyphens=False))
            dumped = yaml.safe_dump(getattr(section, f.name), default_flow_style=True)
            dumped = dumped.strip().removesuffix('...').strip()
            lines.append(f'      {f.name}: {dumped}')
    return '\n'.join(lines) + '\n'


def main() -> None:
    """Print the default configuration as a ROS 2 parameter file (config/stereo_vo.yaml)."""
    import sys
    sys.stdout.write(HEADER + to_yaml())


HEADER = """\
# stereo_vo_ros parameters: one file for the node (ros2 run/launch --params-file) and the
# offline tools (stereo_vo run --config). Generated from stereo_vo_ros/config.py by
# `python -m stereo_vo_ros.config > config/stereo_vo.yaml`; a test keeps the two in step.
"""


if __name__ == '__main__':
    main()
